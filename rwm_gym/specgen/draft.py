"""A spec being generated: its tables in file order, the comments that explain them, and what was assumed."""

from __future__ import annotations

import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rwm_gym.spec import TaskSpec, parse_spec
from rwm_gym.specgen.toml_text import significant, table_text


@dataclass
class Table:
    """One TOML table of a spec being written: its values, comments per key and a note above it."""

    name: str
    values: dict
    comments: dict[str, str] = field(default_factory=dict)
    array: bool = False
    """`[[name]]` (one of several) rather than `[name]`."""
    note: str = ""
    """Comment lines written above the table."""


@dataclass
class SpecDraft:
    """A spec being generated: header, tables and the choices made without being told."""

    header: list[str]
    """Comment lines at the top of the file."""
    tables: list[Table]
    assumptions: list[str] = field(default_factory=list)
    """What the generator chose without being told; printed and written into the header."""

    def table(self, name: str) -> Table:
        return next(t for t in self.tables if t.name == name)

    def state_tables(self) -> list[Table]:
        return [t for t in self.tables if t.name == "state"]

    def text(self) -> str:
        lines = [f"# {line}" if line else "#" for line in self.header]
        if self.assumptions:
            lines += ["#", "# Assumed by `rwm-gym spec` (check and edit):"] + [f"#  - {a}" for a in self.assumptions]
        parts = ["\n".join(lines)]
        for t in self.tables:
            note = "".join(f"# {line}\n" for line in t.note.splitlines()) if t.note else ""
            parts.append(note + table_text(t.name, t.values, t.comments, array=t.array))
        return "\n\n".join(parts) + "\n"

    def parse(self) -> TaskSpec:
        """The spec as written; its model (the MJCF copy the generator wrote) may lie in that copy's folder."""
        model = self.table("task").values.get("model") if any(t.name == "task" for t in self.tables) else ""
        return parse_spec(self.text(), where="<generated spec>", model_dir=Path(model).parent if model else None)


def fill_normalization(draft: SpecDraft, episodes: int, steps: int, seed: int = 0) -> str:
    """Set every state column's mean and std (and the foot-height std) from a short random-policy collection.

    The data are what `rwm-gym collect --env SPEC --policy random --episodes E --max-steps T --seed S` writes; std is
    floored at max(0.05 x the group's largest std, 0.01) so a column that hardly moves is not blown up; figures are
    rounded to 4 significant digits. Returns the sentence the spec's state comment carries.
    """
    from rwm_gym.data.collect import collect
    from rwm_gym.data.dataset import Dataset

    spec = draft.parse()
    with tempfile.TemporaryDirectory(prefix="rwm-spec-") as tmp:
        path = collect(
            spec,
            "random",
            episodes,
            Path(tmp) / "random.h5",
            seed=seed,
            max_steps=steps,
            num_envs=min(episodes, 4),
            progress=False,
        )
        data = Dataset.load(path)
        state, feet = data["state"].astype(np.float64), data["foot_height"].astype(np.float64)
        rows = data.num_steps
    for table in draft.state_tables():
        columns = state[:, spec.state_slices[table.values["name"]]]
        mean, std = columns.mean(axis=0), columns.std(axis=0)
        std = np.maximum(std, max(0.05 * std.max(), 0.01))
        table.values["mean"] = [significant(v) for v in mean]
        table.values["std"] = [significant(v) for v in std]
    if feet.shape[1]:
        draft.table("privileged").values["foot_height_std"] = significant(max(feet.std(), 0.01))
    return (
        f"mean and std of {episodes} random-policy episodes, {rows} rows\n(`rwm-gym collect --policy random "
        f"--episodes {episodes} --max-steps {steps} --seed {seed}`),\nstd floored at max(0.05 x the group's "
        f"largest std, 0.01), rounded to 4 significant digits."
    )

"""Which model kind to train for a data size and a compute budget, read off a measured table (`--model auto`).

The table (`assets/model_choice.json`, written by `benchmarks/budget_curve.py --write-recommendation`) holds, per
robot and CPU-minute budget, the held-out relative error at 100 forecast steps of every kind trained from scratch on
that robot's data (its rows are given), with its provenance: the command, budgets, hardware and load.

The rule, `choose_kind`: take the robots whose data size is nearest the user's (in log rows; every robot within a
factor 2 of the nearest one counts), then their budget nearest the user's (in log CPU-minutes); average each kind's
error over those robots (geometric mean, so one robot's blow-up does not hide the others); pick the lowest, except
that the default kind (rwm, the paper's model) is kept while its error is within `TOLERANCE` (10 %) of the lowest.
No kind more than 10 % above the lowest is ever picked.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path

FORMAT_NAME = "rwm-gym-model-choice"
FORMAT_VERSION = 1
TOLERANCE = 0.10
"""The default kind is kept while its error is at most this fraction above the lowest."""
DEFAULT_KIND = "rwm"
CANDIDATES = ("rwm", "mlp", "rssm", "transformer")
"""Kinds the rule picks from (no_change, which learns nothing, is the reference the line reports)."""


class ModelChoiceError(ValueError):
    """A model-choice table that cannot be read or has nothing for the request; the message is one line."""


@dataclass(frozen=True)
class Measurement:
    """One robot at one budget: each kind's held-out error after training from scratch for `cpu_minutes`."""

    robot: str
    rows: int
    """Rows (transitions) of the robot's training data."""
    cpu_minutes: float
    """The budget: CPU-minutes of one process at one torch thread."""
    errors: dict[str, float]
    """kind -> relative L1 error at the table's horizon (no_change included as the reference)."""
    iterations: dict[str, int] = field(default_factory=dict)
    """kind -> gradient steps the budget bought."""


@dataclass(frozen=True)
class ModelChoiceTable:
    """The measurements `choose_kind` reads, with where they come from; a JSON file with a format name and version."""

    measurements: tuple[Measurement, ...]
    horizon: int = 100
    """Forecast step the errors are measured at."""
    provenance: dict = field(default_factory=dict)
    """command, budgets, robots, hardware, load average, commit: where the numbers come from."""

    def to_dict(self) -> dict:
        return {
            "format": FORMAT_NAME,
            "format_version": FORMAT_VERSION,
            "horizon": self.horizon,
            "provenance": self.provenance,
            "measurements": [asdict(m) for m in self.measurements],
        }

    @classmethod
    def from_dict(cls, data: dict, where: str = "model-choice table") -> ModelChoiceTable:
        if data.get("format") != FORMAT_NAME:
            raise ModelChoiceError(f"{where}: format {data.get('format')!r} is not {FORMAT_NAME!r}")
        if int(data.get("format_version", 0)) > FORMAT_VERSION:
            raise ModelChoiceError(f"{where}: format_version {data['format_version']} is newer than this reader's")
        try:
            measurements = tuple(Measurement(**m) for m in data["measurements"])
        except (KeyError, TypeError) as err:
            raise ModelChoiceError(f"{where}: a measurement is malformed ({err})") from None
        if not measurements:
            raise ModelChoiceError(f"{where}: no measurements")
        return cls(measurements, int(data.get("horizon", 100)), dict(data.get("provenance", {})))

    @classmethod
    def load(cls, path: str | os.PathLike) -> ModelChoiceTable:
        try:
            data = json.loads(Path(path).read_text())
        except (OSError, json.JSONDecodeError) as err:
            raise ModelChoiceError(f"{path}: cannot read the model-choice table ({err})") from None
        return cls.from_dict(data, str(path))

    def save(self, path: str | os.PathLike) -> Path:
        from rwm_gym.atomic import write_json

        write_json(Path(path), self.to_dict())
        return Path(path)


def shipped_table() -> ModelChoiceTable:
    """The table shipped with the package (`assets/model_choice.json`)."""
    from rwm_gym.resources import shipped_file

    return ModelChoiceTable.load(shipped_file("assets/model_choice.json"))


@dataclass(frozen=True)
class Choice:
    """What `choose_kind` picked, and from which measurements."""

    kind: str
    errors: dict[str, float]
    """kind -> error at the measured budget (geometric mean over `robots`), candidates and no_change."""
    cpu_minutes: float
    """The measured budget used."""
    robots: tuple[str, ...]
    rows: tuple[int, ...]
    iterations: int | None
    """Gradient steps the picked kind would make in the asked budget, from its measured rate (None: not measured)."""
    horizon: int

    def reason(self, asked_minutes: float, asked_rows: int) -> str:
        """One line: what was picked and the measured errors it was picked on."""
        best = min((e, k) for k, e in self.errors.items() if k in CANDIDATES)[1]
        ranked = sorted(((e, k) for k, e in self.errors.items() if k in CANDIDATES))
        figures = ", ".join(f"{k} {e:.3f}" for e, k in ranked)
        sizes = "/".join(map(str, sorted(set(self.rows))))
        if "no_change" in self.errors:
            figures += f"; no change {self.errors['no_change']:.3f}"
        why = "lowest" if self.kind == best else f"the default, within {TOLERANCE:.0%} of {best}"
        steps = f", about {self.iterations:,} iterations in {asked_minutes:g} CPU-minutes" if self.iterations else ""
        return (
            f"--model auto: {self.kind} ({why}{steps}); measured error at {self.horizon} steps after "
            f"{self.cpu_minutes:g} CPU-minutes on {', '.join(self.robots)} ({sizes} rows; yours {asked_rows}): "
            f"{figures}"
        )


def _log_distance(a: float, b: float) -> float:
    return abs(math.log(a / b))


def choose_kind(table: ModelChoiceTable, rows: int, cpu_minutes: float, tolerance: float = TOLERANCE) -> Choice:
    """The kind to train on `rows` rows of data for `cpu_minutes` CPU-minutes (the rule in the module docstring)."""
    if rows < 1 or not cpu_minutes > 0:
        raise ModelChoiceError(f"need rows >= 1 and a budget > 0 CPU-minutes, got {rows} rows and {cpu_minutes}")
    budget, chosen = _nearest(table, rows, cpu_minutes)
    errors = _mean_errors(chosen)
    candidates = {k: e for k, e in errors.items() if k in CANDIDATES}
    if not candidates:
        raise ModelChoiceError(f"the model-choice table measures none of {', '.join(CANDIDATES)} at {budget:g} min")
    lowest = min(candidates, key=lambda k: (candidates[k], k))
    kind = lowest
    if DEFAULT_KIND in candidates and candidates[DEFAULT_KIND] <= (1.0 + tolerance) * candidates[lowest]:
        kind = DEFAULT_KIND
    return Choice(
        kind,
        errors,
        budget,
        tuple(m.robot for m in chosen),
        tuple(m.rows for m in chosen),
        _iterations(chosen, kind, cpu_minutes),
        table.horizon,
    )


def _nearest(table: ModelChoiceTable, rows: int, cpu_minutes: float) -> tuple[float, list[Measurement]]:
    """The measured budget nearest `cpu_minutes` among the robots whose data size is nearest `rows` (every robot
    within a factor 2 of the nearest one), and those robots' measurements at it."""
    sizes = {m.rows for m in table.measurements}
    nearest = min(_log_distance(s, rows) for s in sizes)
    near_sizes = {s for s in sizes if _log_distance(s, rows) <= nearest + math.log(2.0)}
    pool = [m for m in table.measurements if m.rows in near_sizes]
    budget = min({m.cpu_minutes for m in pool}, key=lambda b: (_log_distance(b, cpu_minutes), b))
    return budget, [m for m in pool if m.cpu_minutes == budget]


def _mean_errors(chosen: list[Measurement]) -> dict[str, float]:
    """kind -> geometric mean of its error over `chosen`, for the kinds every one of them measured finitely."""
    kinds = set.intersection(*(set(m.errors) for m in chosen))
    return {
        k: math.exp(sum(math.log(max(m.errors[k], 1e-12)) for m in chosen) / len(chosen))
        for k in sorted(kinds)
        if all(math.isfinite(m.errors[k]) for m in chosen)
    }


def _iterations(chosen: list[Measurement], kind: str, cpu_minutes: float) -> int | None:
    """Gradient steps `kind` would make in `cpu_minutes`, at its median measured rate (None: not measured)."""
    rates = [m.iterations[kind] / m.cpu_minutes for m in chosen if m.iterations.get(kind)]
    return round(sorted(rates)[len(rates) // 2] * cpu_minutes) if rates else None

"""The physics rows behind a world model's whole lineage, and their share of model-free PPO's.

A checkpoint's provenance holds its lineage (`rwm_gym.data.lineage`): the physics sources of the data it was
trained on, united with those of the checkpoint it was fine-tuned from, each source once. `physics_rows` reads the
total; `share_text` words it against N_mf, the physics steps the task's model-free teacher needed to reach tracking
0.80 (ANYmal D's `assets/policies/anymal_d_ppo_physics.json`: 32.2 M), the reference of every sample-efficiency figure.
"""

from __future__ import annotations

import json
import os
from functools import cache

from rwm_gym.data.lineage import SOURCES_KEY, checked, total_rows, union


def checkpoint_lineage(meta) -> dict[str, int]:
    """{source: rows} behind a checkpoint (`CheckpointMeta`): its provenance's lineage, else (a checkpoint from before
    lineages were recorded) the rows of the dataset it was trained on, as one source; {} if neither is known."""
    provenance = meta.provenance
    if SOURCES_KEY in provenance:
        return checked(provenance[SOURCES_KEY], f"{meta.path}: provenance")
    if "dataset_steps" in provenance and provenance.get("sha256"):
        return {f"sha256:{provenance['sha256']}": int(provenance["dataset_steps"])}
    return {}


def lineage_provenance(dataset_sources: dict[str, int], init=None) -> dict:
    """The provenance entries of a model trained on data of `dataset_sources`, fine-tuned from the checkpoint whose
    metadata is `init` (None: from scratch): the united lineage and its total."""
    lineage = union(checkpoint_lineage(init), dataset_sources) if init is not None else dict(dataset_sources)
    return {SOURCES_KEY: lineage, "physics_rows": total_rows(lineage)}


def physics_rows(path: str | os.PathLike) -> tuple[int | None, str]:
    """Physics rows of a checkpoint's whole lineage, and where the figure comes from (or why it is unknown)."""
    from rwm_gym.model.checkpoint import dataset_rows, read_meta

    meta = read_meta(path)
    if SOURCES_KEY in meta.provenance:
        lineage = checkpoint_lineage(meta)
        return total_rows(lineage), f"{path}'s lineage: {len(lineage)} physics source(s), each counted once"
    rows, source = dataset_rows(path)  # a checkpoint from before lineages: its own dataset alone
    return rows, source + ("; models it was fine-tuned from are not counted" if rows is not None else "")


DEFAULT_TASK = "AnymalD-MuJoCo-v0"
"""The task whose N_mf a figure is worded against when it names none."""


@cache
def n_mf(env_id: str = DEFAULT_TASK) -> int | None:
    """N_mf of a task (its physics env id): the physics steps its model-free teacher needed to reach tracking 0.80,
    read from the shipped `<spec>_ppo_physics.json` of the task's spec file (`envs/<spec>.toml`); None where no
    shipped teacher of it records one."""
    from rwm_gym.resources import assets_dir
    from rwm_gym.spec import shipped_spec_file

    found = shipped_spec_file(env_id)
    record = None if found is None else assets_dir() / "policies" / f"{found[0].stem}_ppo_physics.json"
    if record is None or not record.is_file() or "n_mf" not in (teacher := json.loads(record.read_text())):
        return None
    return int(teacher["n_mf"]["physics_steps"])


def share_text(rows: int | None, env_id: str = DEFAULT_TASK) -> str:
    """'2,496,757 (7.7 % of N_mf = 32.2 M, model-free PPO's to tracking 0.80)' against the task's N_mf; the rows
    alone where the task has none; '?' for unknown rows."""
    if rows is None:
        return "?"
    n = n_mf(env_id)
    if n is None:
        return f"{rows:,} (no N_mf: no shipped model-free teacher of {env_id} reached tracking 0.80)"
    return f"{rows:,} ({100 * rows / n:.1f} % of N_mf = {n / 1e6:.1f} M, model-free PPO's to tracking 0.80)"

"""The physics rows behind a world model's whole lineage, and their share of model-free PPO's.

A checkpoint's provenance holds its lineage (`rwm_gym.data.lineage`): the physics sources of the data it was
trained on, united with those of the checkpoint it was fine-tuned from, each source once. `physics_rows` reads the
total; `share_text` words it against N_mf, the physics steps the model-free teacher needed to reach tracking 0.80
(`assets/policies/anymal_d_ppo_physics.json`: 32.2 M), the reference of every sample-efficiency figure here.
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


@cache
def n_mf() -> int:
    """N_mf: the model-free teacher's physics steps to tracking 0.80 (the shipped `anymal_d_ppo_physics.json`)."""
    from rwm_gym.resources import assets_dir

    record = json.loads((assets_dir() / "policies" / "anymal_d_ppo_physics.json").read_text())
    return int(record["n_mf"]["physics_steps"])


def share_text(rows: int | None) -> str:
    """'2,496,757 (7.7 % of N_mf = 32.2 M, the model-free teacher's physics steps to tracking 0.80)', or '?'."""
    if rows is None:
        return "?"
    return f"{rows:,} ({100 * rows / n_mf():.1f} % of N_mf = {n_mf() / 1e6:.1f} M, model-free PPO's to tracking 0.80)"

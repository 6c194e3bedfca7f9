"""The physics rows behind a dataset or a model, each counted once however often it is reused.

A dataset's *physics sources* map an identity to a row count: a collected file is its own source (its sha256, its
rows); a merge holds the union of its parts' sources (`merge_datasets` records it in the metadata under
`SOURCES_KEY`); a reset file cut from a dataset holds that dataset's sources. A world model's lineage is the union of
its training data's sources and those of the checkpoint it was fine-tuned from (`rwm_gym.model.train` records it in
the checkpoint's provenance), so a buffer that holds an earlier buffer, or a model fine-tuned again on data it has
seen, adds nothing twice. The sum of a lineage's rows is the physics-sample cost the paper's sample-efficiency
figures compare against model-free PPO.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping

SOURCES_KEY = "physics_sources"
"""The metadata key (a dataset's) and provenance key (a checkpoint's) of a lineage: {source id: rows}."""


def physics_sources(dataset, sha256: str | None = None) -> dict[str, int]:
    """{source id: rows} of a `Dataset`: those its metadata records (a merge, a cut), else the file itself
    (`sha256`: its hash when the caller has it already)."""
    recorded = dataset.info.metadata.get(SOURCES_KEY)
    if recorded:
        return checked(recorded, str(dataset.path))
    return {f"sha256:{sha256 or dataset.file_hash()}": int(dataset.num_steps)}


def checked(sources: object, where: str) -> dict[str, int]:
    """`sources` as {str: int >= 0}, else a one-line ValueError naming `where`."""
    if not isinstance(sources, Mapping) or not all(
        isinstance(k, str) and isinstance(v, int) and not isinstance(v, bool) and v >= 0 for k, v in sources.items()
    ):
        raise ValueError(f"{where}: {SOURCES_KEY} must map source names to row counts >= 0")
    return dict(sources)


def union(*lineages: Mapping[str, int]) -> dict[str, int]:
    """The sources of all `lineages`, each once (a source seen with two counts keeps the larger)."""
    merged: dict[str, int] = {}
    for lineage in lineages:
        for source, rows in lineage.items():
            merged[source] = max(rows, merged.get(source, 0))
    return merged


def total_rows(lineage: Mapping[str, int]) -> int:
    """Physics rows of a lineage: the sum over its sources."""
    return int(sum(lineage.values()))


def union_of(datasets: Iterable) -> dict[str, int]:
    """The union of several datasets' sources."""
    return union(*(physics_sources(d) for d in datasets))

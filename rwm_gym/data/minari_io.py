"""Datasets to and from Minari (the Farama offline-RL format), so collections travel to offline-RL code.

    rwm-gym export --minari DATA.h5 --out DIR      # DIR holds a Minari dataset (`minari.MinariDataset(DIR)`)
    rwm-gym import --minari DIR --out DATA.h5

An episode of L transitions maps onto Minari's fields as Minari expects: `observations` (L+1, O) the policy
observation (the spec's `[observation]` groups built from state, command and the previous action; no noise),
`actions` (L, A), `rewards`, `terminations` and `truncations` (L,); every per-row field of the dataset (`state`,
`contact`, `foot_height`, `qpos`, `qvel`, `command` and any extra field) goes into `infos` with its L+1 rows. The
dataset's file attributes (the spec text, columns, policy, seed, ...) are kept under the metadata key `rwm_gym`, so
import rebuilds the file field for field (tested). Needs the optional extra `rwm-gym[minari]`.
"""

from __future__ import annotations

import json
import shutil
import tempfile
from pathlib import Path

import numpy as np

from rwm_gym.data.dataset import Dataset, DatasetInfo, write_dataset
from rwm_gym.output_guard import check_output, claim
from rwm_gym.task.observation import build_observation

METADATA_KEY = "rwm_gym"
_TRANSITION_FIELDS = ("action", "reward", "terminated", "truncated")


def _minari():
    try:
        import minari
    except ImportError:
        raise ValueError("Minari is not installed: pip install 'rwm-gym[minari]'") from None
    return minari


def _observations(spec, episode: dict[str, np.ndarray]) -> np.ndarray:
    previous = np.concatenate([np.zeros_like(episode["action"][:1]), episode["action"][:-1]])
    return build_observation(spec, episode["state"], episode["command"], previous).astype(np.float32)


def export_minari(data: str | Path, out: str | Path, *, dataset_id: str | None = None, overwrite: bool = False) -> Path:
    """Write dataset `data` as a Minari dataset in folder `out` (built beside it, then moved into place)."""
    minari = _minari()
    import gymnasium as gym

    # absolute: Minari's storage joins a relative path onto itself
    out = check_output(out, inputs=[data], overwrite=overwrite, folder=True)
    ds = Dataset.load(data)
    spec = ds.spec()
    row_fields = [f for f in ds.fields if f not in _TRANSITION_FIELDS]
    shapes = {f: [str(ds[f].dtype), list(ds[f].shape[1:])] for f in row_fields}
    observation_space = gym.spaces.Box(-np.inf, np.inf, (spec.observation_dim,), np.float32)
    action_space = gym.spaces.Box(-1.0, 1.0, (spec.action_dim,), np.float32)
    name = dataset_id or f"rwm-gym/{spec.name.lower()}/{Path(data).stem.replace('_', '-')}-v0"
    info = ds.info
    meta = {
        "env_id": info.env_id,
        "spec_text": info.spec_text,
        "dt": info.dt,
        "columns": info.columns,
        "policy": info.policy,
        "seed": info.seed,
        "physics_params": info.physics_params,
        "metadata": info.metadata,
        "complete": info.complete,
        "format_version": info.format_version,
        "created_by": info.created_by,
        "fields": shapes,
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    with claim(out):
        for orphan in out.parent.glob(f".{out.name}-*"):  # left by a killed export
            shutil.rmtree(orphan, ignore_errors=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}-", dir=out.parent))
        _write_minari(tmp, out, ds, spec, name, meta, row_fields, observation_space, action_space, minari)
    return out


def _write_minari(
    tmp: Path,
    out: Path,
    ds: Dataset,
    spec,
    name: str,
    meta: dict,
    row_fields: list[str],
    observation_space,
    action_space,
    minari,
) -> None:
    """Build the Minari dataset in `tmp`, then swap it for `out` (the old `out` goes only once the new one is there)."""
    from minari.data_collector.episode_buffer import EpisodeBuffer
    from minari.dataset.minari_storage import MinariStorage

    info = ds.info
    try:
        storage = MinariStorage.new(
            tmp, observation_space=observation_space, action_space=action_space, data_format="hdf5", jpeg_encoding=False
        )
        storage.update_metadata(
            {
                "dataset_id": name,
                "minari_version": minari.__version__,
                "algorithm_name": info.policy,
                "description": f"rwm-gym dataset of {spec.name}",
                METADATA_KEY: json.dumps(meta),
            }
        )
        buffers = []
        for i in range(ds.num_episodes):
            ep = ds.episode(i)
            terminations = np.zeros(len(ep["state"]) - 1, dtype=bool)
            truncations = terminations.copy()
            terminations[-1:], truncations[-1:] = ep["terminated"][-1], ep["truncated"][-1]
            buffers.append(
                EpisodeBuffer(
                    id=i,
                    observations=_observations(spec, ep),
                    actions=ep["action"][:-1],
                    rewards=ep["reward"][:-1],
                    terminations=terminations,
                    truncations=truncations,
                    infos={f: ep[f] for f in row_fields if ep[f].size},
                )
            )  # h5py cannot chunk zero-width arrays
        storage.update_episodes(buffers)
        old = tmp.with_name(tmp.name + "-old")
        if out.exists():
            out.rename(old)
        tmp.rename(out)
        if old.is_dir():
            shutil.rmtree(old)
        elif old.exists():
            old.unlink()
    finally:
        if tmp.exists():
            shutil.rmtree(tmp)


def _check_minari_folder(folder: Path) -> None:
    """Before Minari reads `folder`: its two files are regular files inside it (no link out), the metadata is small
    JSON naming the hdf5 format, and the HDF5 file holds its own data (`check_self_contained`)."""
    import h5py

    from rwm_gym.data.hdf5_guard import check_self_contained
    from rwm_gym.untrusted import regular_file

    if not folder.is_dir():
        raise ValueError(f"{folder}: not a readable Minari dataset (not a folder)")
    files = {}
    for name in ("metadata.json", "main_data.hdf5"):
        path = folder / name
        if not path.exists():
            raise ValueError(f"{folder}: not a readable Minari dataset exported by rwm-gym (no {name})")
        if path.is_symlink() or not path.resolve().is_relative_to(folder.resolve()):
            raise ValueError(f"{path}: a link to {path.resolve()}; a Minari dataset must hold its own files")
        files[name] = regular_file(path, "Minari file")
    if files["metadata.json"].stat().st_size > 64 << 20:
        raise ValueError(f"{files['metadata.json']}: over 64 MiB, not Minari metadata")
    try:
        data_format = json.loads(files["metadata.json"].read_text()).get("data_format", "hdf5")
    except (ValueError, AttributeError):
        raise ValueError(f"{files['metadata.json']}: not a JSON object") from None
    if data_format != "hdf5":
        raise ValueError(f"{folder}: data format {data_format!r}; rwm-gym imports the hdf5 Minari datasets it exports")
    main_data = files["main_data.hdf5"]
    try:
        with h5py.File(main_data, "r") as f:
            check_self_contained(f, main_data, ValueError)
    except OSError as err:
        raise ValueError(f"{main_data}: not a readable HDF5 file ({' '.join(str(err).split())})") from None


def import_minari(folder: str | Path, out: str | Path, *, overwrite: bool = False) -> Path:
    """Rebuild the rwm-gym dataset that `export_minari` wrote into `folder` (atomic write of `out`)."""
    minari = _minari()
    folder, out = Path(folder), check_output(out, inputs=[folder], overwrite=overwrite)
    _check_minari_folder(folder)
    try:
        dataset = minari.MinariDataset(folder)
    except (ValueError, OSError, KeyError, AssertionError) as err:  # what Minari raises for a folder it cannot read
        raise ValueError(f"{folder}: not a readable Minari dataset ({type(err).__name__}: {err})") from None
    raw = dataset.storage.metadata.get(METADATA_KEY)
    if raw is None:
        raise ValueError(
            f"{folder}: a Minari dataset not exported by rwm-gym (no '{METADATA_KEY}' metadata), "
            "so its task spec is unknown"
        )
    meta = json.loads(raw)
    shapes = meta.pop("fields")
    info = DatasetInfo(
        **{
            k: meta[k]
            for k in (
                "env_id",
                "dt",
                "columns",
                "policy",
                "seed",
                "physics_params",
                "metadata",
                "complete",
                "format_version",
                "created_by",
            )
        },
        spec_text=meta["spec_text"],
    )

    def episodes():
        for ep in dataset.iterate_episodes():
            rows = len(ep.rewards) + 1
            out_ep = {}
            for name, (dtype, tail) in shapes.items():
                value = (ep.infos or {}).get(name)
                out_ep[name] = np.zeros((rows, *tail), dtype=dtype) if value is None else np.asarray(value, dtype)
            out_ep["action"] = np.concatenate([ep.actions, np.zeros_like(ep.actions[:1])]).astype(np.float32)
            out_ep["reward"] = np.append(ep.rewards, 0.0).astype(np.float32)
            for name, flags in (("terminated", ep.terminations), ("truncated", ep.truncations)):
                column = np.zeros(rows, dtype=bool)
                column[-1] = bool(flags[-1]) if len(flags) else False
                out_ep[name] = column
            yield out_ep

    write_dataset(out, info, episodes())
    return out

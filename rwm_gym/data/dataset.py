"""The dataset format: many episodes of a robot in one HDF5 file, read and written only through this module.

Layout. An episode of L transitions has L+1 rows; episodes are concatenated along axis 0 (T rows in all) and
`episode_lengths` (int64, (E,)) holds the row count of each. Row t holds the quantities at time t:

    state[t]        float32 (T, S)   the world-model state (columns from the task spec)
    contact[t]      bool    (T, C)   contact flag of each contact body
    foot_height[t]  float32 (T, F)   m, height of each foot (F may be 0)
    qpos[t]         float64 (T, nq)  simulator generalized positions (for resetting an env to row t)
    qvel[t]         float64 (T, nv)  simulator generalized velocities
    command[t]      float32 (T, K)   the command in force when action[t] is chosen (K may be 0)
    action[t]       float32 (T, A)   applied in state[t], leads to state[t+1]
    reward[t]       float32 (T,)     earned by the transition t -> t+1
    terminated[t]   bool    (T,)     row t is the final state of a terminated episode
    truncated[t]    bool    (T,)     row t is the final state of a time-limited episode

The last row of each episode has no transition: its action and reward are 0. Extra per-step fields (any name, any
numeric dtype, first axis T) are allowed and round-trip. In the file, fields live in the group `steps/` and
`episode_lengths` at the root; the root attributes are `format`, `format_version`, `env_id`, `spec` (the task spec's
TOML text), `dt` (policy step, s), `columns` (JSON {field: [column names]}), `policy`, `seed`, `physics_params`
(JSON), `complete` (false while being written), `created_by` (package version) and `metadata` (JSON).

The writer fills a partial file beside the destination (`NAME.partial-XXXXXXXX`) and renames it onto the destination
when it closes (on an exception too, with `complete` false), so the destination is only ever a whole file that plain
h5py opens, and two writers of one destination never share a file. It flushes after each episode, data rows before
`episode_lengths`, so a writer killed mid-way leaves a partial file that `Dataset.load` reads (plain h5py needs
`h5clear -s` first), holding every finished episode.
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import secrets
import shutil
import tomllib
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import h5py
import numpy as np

from rwm_gym.atomic import atomic_write
from rwm_gym.data.hdf5_guard import check_self_contained
from rwm_gym.data.lineage import SOURCES_KEY, physics_sources, union
from rwm_gym.spec import TaskSpec, parse_spec

FORMAT_NAME = "rwm-gym-dataset"
FORMAT_VERSION = 1
_FIELDS: dict[str, tuple[type, int]] = {  # required field -> (dtype, ndim)
    "state": (np.float32, 2),
    "action": (np.float32, 2),
    "contact": (np.bool_, 2),
    "foot_height": (np.float32, 2),
    "terminated": (np.bool_, 1),
    "truncated": (np.bool_, 1),
    "command": (np.float32, 2),
    "reward": (np.float32, 1),
    "qpos": (np.float64, 2),
    "qvel": (np.float64, 2),
}
REQUIRED_FIELDS: tuple[str, ...] = tuple(_FIELDS)
_ATTRS = ("format", "format_version", "env_id", "spec", "dt", "columns", "policy", "seed", "physics_params", "complete")
_CHUNK_ROWS = 512


class DatasetError(ValueError):
    """A dataset file or episode is malformed; the one-line message reads "path: field 'x': what is wrong"."""


@dataclass(frozen=True)
class DatasetInfo:
    """File-level description of a dataset. `complete`, `format_version` and `created_by` are set by the writer."""

    env_id: str
    spec_text: str = field(repr=False)
    """The task spec's TOML text, verbatim."""
    dt: float
    """s, policy step."""
    columns: dict[str, list[str]]
    """Column names of every field that has columns, e.g. {"state": spec.state_columns, ...}."""
    policy: str
    """Name/description of the collecting policy."""
    seed: int
    physics_params: dict
    """Physical parameters of the model that produced the data (JSON-serialisable)."""
    metadata: dict = field(default_factory=dict)
    """Anything else (JSON-serialisable)."""
    complete: bool = False
    format_version: int = FORMAT_VERSION
    created_by: str = ""


MIN_FREE_BYTES = 1 << 20
"""Free space an append leaves beside the episode's own bytes (twice them): room for HDF5's metadata and chunks."""


class DatasetWriter:
    """Append episodes to a new dataset file; use as a context manager (an exception leaves `complete` false)."""

    def __init__(
        self, path: str | os.PathLike, info: DatasetInfo, *, overwrite: bool = False, in_place: bool = False
    ) -> None:
        """in_place: write `path` itself instead of a partial file renamed onto it at the end, for a writer whose
        killed run must leave its episodes at `path` (a resumable run's parts); plain h5py then needs `h5clear -s`."""
        from rwm_gym import __version__
        from rwm_gym.output_guard import claim, remove_orphans

        self.path = Path(path)
        if self.path.exists() and not overwrite:
            raise DatasetError(f"{self.path}: file exists (pass --overwrite, or overwrite=True, to replace it)")
        parse_spec(info.spec_text, where=f"{self.path}:spec")
        self._claim = claim(self.path)
        self._claim.__enter__()  # held until `close`: a second writer of `path` fails at once
        if not in_place:
            remove_orphans(self.path, f"{self.path.name}.partial-*")
        self.replaces = self.path.exists()
        """Whether `path` held a file before: a run that fails then keeps it instead of leaving a partial one."""
        self.info = info
        self.num_episodes = 0
        self._widths: dict[str, tuple[tuple[int, ...], np.dtype]] = {}
        self.partial_path = (
            self.path if in_place else self.path.with_name(f"{self.path.name}.partial-{secrets.token_hex(4)}")
        )
        """Where the episodes go until `close` renames the file onto `path`."""
        try:
            self._file = h5py.File(self.partial_path, "w" if in_place else "x", libver="latest")
        except BaseException:
            self._claim.__exit__(None, None, None)
            raise
        attrs = {
            "format": FORMAT_NAME,
            "format_version": FORMAT_VERSION,
            "env_id": info.env_id,
            "spec": info.spec_text,
            "dt": float(info.dt),
            "columns": json.dumps(info.columns),
            "policy": info.policy,
            "seed": int(info.seed),
            "physics_params": json.dumps(info.physics_params),
            "complete": False,
            "created_by": __version__,
            "metadata": json.dumps(info.metadata),
        }
        self._file.attrs.update(attrs)
        self._file.create_group("steps")
        self._file.create_dataset("episode_lengths", shape=(0,), maxshape=(None,), dtype=np.int64, chunks=(1024,))
        self._file.flush()

    def _error(self, name: str, what: str) -> DatasetError:
        return DatasetError(f"{self.path}: field '{name}': {what} (episode {self.num_episodes})")

    def _validate(self, episode: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """The episode's arrays cast to their stored dtypes, or the first problem as a DatasetError."""
        self._check_field_names(episode)
        rows = len(episode["state"]) if np.ndim(episode["state"]) else 0
        out = {name: self._validate_field(name, np.asarray(value), rows) for name, value in episode.items()}
        for name in ("action", "reward"):
            if out[name][-1].any():
                raise self._error(name, "must be 0 in the last row of an episode (it has no transition)")
        for name in ("terminated", "truncated"):
            if out[name][:-1].any():
                raise self._error(name, "true before the last row of the episode")
        return out

    def _check_field_names(self, episode: Mapping[str, np.ndarray]) -> None:
        """Every required field, and the same fields as the earlier episodes."""
        missing = [name for name in REQUIRED_FIELDS if name not in episode]
        if missing:
            raise self._error(missing[0], "missing")
        if self._widths and set(episode) != set(self._widths):
            name = sorted(set(episode) ^ set(self._widths))[0]
            raise self._error(name, "present in only some episodes")

    def _validate_field(self, name: str, value: np.ndarray, rows: int) -> np.ndarray:
        """One field cast to its stored dtype: `rows` rows, the row shape of earlier episodes and of its columns,
        finite."""
        value = self._cast(name, value)
        ndim = _FIELDS[name][1] if name in _FIELDS else value.ndim
        if value.ndim != ndim or value.ndim == 0:
            raise self._error(name, f"expected {ndim} dimensions, got shape {value.shape}")
        if len(value) != rows or rows < 1:
            raise self._error(name, f"has {len(value)} rows, 'state' has {rows} (need the same, >= 1)")
        if name in self._widths and value.shape[1:] != self._widths[name][0]:
            raise self._error(name, f"row shape {value.shape[1:]}, earlier episodes {self._widths[name][0]}")
        if name in self.info.columns and (value.ndim != 2 or value.shape[1] != len(self.info.columns[name])):
            raise self._error(name, f"shape {value.shape} does not match {len(self.info.columns[name])} columns")
        if value.dtype.kind in "fc" and not np.isfinite(value).all():
            raise self._error(name, "contains NaN or inf")
        return value

    def _cast(self, name: str, value: np.ndarray) -> np.ndarray:
        """`value` as its field's dtype (a known field's, else the dtype of earlier episodes, else its own)."""
        if name not in _FIELDS and value.dtype.kind not in "biufc":
            raise self._error(name, f"dtype {value.dtype} is not numeric or bool")
        dtype = _FIELDS[name][0] if name in _FIELDS else self._widths.get(name, ((), value.dtype))[1]
        try:
            return value.astype(dtype, casting="same_kind", copy=False)
        except TypeError:
            raise self._error(name, f"dtype {value.dtype} cannot be stored as {np.dtype(dtype)}") from None

    def append_episode(self, episode: Mapping[str, np.ndarray]) -> None:
        """Validate one episode ({field: (L+1, ...) array}) and append it; on error nothing is written."""
        arrays = self._validate(episode)
        need = 2 * sum(value.nbytes for value in arrays.values()) + MIN_FREE_BYTES
        free = shutil.disk_usage(self.partial_path.parent).free
        if free < need:  # HDF5 that runs out of space mid-write can crash the process; stop while it is whole
            raise OSError(
                errno.ENOSPC,
                f"No space left on device for episode {self.num_episodes} of {self.path} "
                f"({free / 2**20:.1f} MiB free, {need / 2**20:.1f} MiB needed)",
            )
        steps, rows = self._file["steps"], len(arrays["state"])
        first = not self._widths
        for name, value in arrays.items():
            if name not in steps:
                tail = value.shape[1:]
                chunks = (_CHUNK_ROWS, *tail) if all(tail) and np.prod(tail) <= 4096 else True
                steps.create_dataset(name, shape=(0, *tail), maxshape=(None, *tail), dtype=value.dtype, chunks=chunks)
                self._widths[name] = (tail, value.dtype)
        if first:  # every dataset exists now: from here on, HDF5 orders its writes so a crash leaves a readable file
            self._file.swmr_mode = True
        for name, value in arrays.items():
            data = steps[name]
            data.resize(len(data) + rows, axis=0)
            data[len(data) - rows :] = value
        self._file.flush()  # data rows reach the file before the episode is counted
        lengths = self._file["episode_lengths"]
        lengths.resize(len(lengths) + 1, axis=0)
        lengths[-1] = rows
        self._file.flush()
        self.num_episodes += 1

    def close(self, complete: bool = True) -> None:
        """Close the file, mark it `complete` and move it onto `path`. An incomplete file goes onto `path` only if no
        file was there (its finished episodes are kept); a file that was there stays, and the partial one goes."""
        if not self._file.id.valid:
            return
        try:
            self._file.close()
            if complete:
                with h5py.File(self.partial_path, "r+", libver="latest") as f:  # read-only while in SWMR mode
                    f.attrs["complete"] = True
            if self.partial_path != self.path:
                if complete or not self.replaces:
                    os.replace(self.partial_path, self.path)
                else:
                    self.partial_path.unlink()
        except BaseException:
            if self.partial_path != self.path and self.partial_path.exists():
                self.partial_path.unlink()
            raise
        finally:
            self._claim.__exit__(None, None, None)

    def __enter__(self) -> DatasetWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close(complete=exc_type is None)


class Dataset:
    """A dataset read eagerly into numpy (the HDF5 file is closed after `load`)."""

    def __init__(self, path: Path, info: DatasetInfo, data: dict[str, np.ndarray], episode_lengths: np.ndarray):
        self.path, self.info, self._data = path, info, data
        self.episode_lengths = episode_lengths
        self.episode_starts = np.concatenate([[0], np.cumsum(episode_lengths)[:-1]]).astype(np.int64)
        self.num_episodes = len(episode_lengths)
        self.num_steps = int(episode_lengths.sum())
        self.fields: tuple[str, ...] = tuple(data)

    @classmethod
    def load(cls, path: str | os.PathLike) -> Dataset:
        """Read and validate a dataset; any problem raises a one-line DatasetError naming the file and field."""
        path = Path(path)
        if not path.is_file():
            if path.exists() and not path.is_dir():  # opening a FIFO would wait for a writer
                raise DatasetError(f"{path}: not a regular file (a FIFO, socket or device); a dataset is a file")
            raise FileNotFoundError(f"{path}: no such dataset file")
        where = "file"
        try:
            with _open_for_reading(path) as f:
                check_self_contained(f, path, DatasetError)  # before any value is read
                where = "attribute 'format'"
                if f.attrs.get("format") != FORMAT_NAME:
                    raise DatasetError(f"{path}: {where}: expected {FORMAT_NAME!r}, got {f.attrs.get('format')!r}")
                for name in _ATTRS:
                    if name not in f.attrs:
                        raise DatasetError(f"{path}: attribute '{name}': missing")
                where = "attribute 'format_version'"
                if int(f.attrs["format_version"]) > FORMAT_VERSION:
                    raise DatasetError(
                        f"{path}: {where}: version {int(f.attrs['format_version'])} is newer than "
                        f"this reader's {FORMAT_VERSION}; upgrade rwm-gym"
                    )
                a = f.attrs
                where = "attributes"
                info = DatasetInfo(
                    env_id=str(a["env_id"]),
                    spec_text=str(a["spec"]),
                    dt=float(a["dt"]),
                    columns=json.loads(a["columns"]),
                    policy=str(a["policy"]),
                    seed=int(a["seed"]),
                    physics_params=json.loads(a["physics_params"]),
                    metadata=json.loads(a.get("metadata", "{}")),
                    complete=bool(a["complete"]),
                    format_version=int(a["format_version"]),
                    created_by=str(a.get("created_by", "")),
                )
                where = "field 'episode_lengths'"
                if "episode_lengths" not in f:
                    raise DatasetError(f"{path}: {where}: missing")
                lengths = np.asarray(f["episode_lengths"][:], dtype=np.int64)
                steps = f["steps"] if "steps" in f else {}
                data = {}
                for name in (*REQUIRED_FIELDS, *(n for n in steps if n not in _FIELDS)):
                    where = f"field '{name}'"
                    if name not in steps:
                        raise DatasetError(f"{path}: {where}: missing")
                    data[name] = steps[name][:]
        except (OSError, RuntimeError, KeyError, ValueError, TypeError) as err:
            if isinstance(err, DatasetError):
                raise
            message = " ".join(str(err).split()) or type(err).__name__
            raise DatasetError(f"{path}: {where}: not a readable HDF5 file, truncated or corrupt ({message})") from None
        return cls(path, info, _check(path, info, data, lengths), lengths)

    def episode(self, i: int) -> dict[str, np.ndarray]:
        """Every field of episode i, rows start..start+length (views into the concatenated arrays)."""
        if not -self.num_episodes <= i < self.num_episodes:
            raise IndexError(f"{self.path}: episode {i} out of range ({self.num_episodes} episodes)")
        start = self.episode_starts[i]
        rows = slice(start, start + self.episode_lengths[i])
        return {name: value[rows] for name, value in self._data.items()}

    def __getitem__(self, name: str) -> np.ndarray:
        if name not in self._data:
            raise KeyError(f"{self.path}: field {name!r} not in dataset (fields: {', '.join(self.fields)})")
        return self._data[name]

    def spec(self) -> TaskSpec:
        return parse_spec(self.info.spec_text, where=f"{self.path}:spec")

    def split_episodes(self, val_fraction: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
        """Sorted (train, val) episode ids, held out by whole episode; deterministic in (val_fraction, seed).

        With 0 < val_fraction and at least two episodes, each side gets at least one episode.
        """
        if not 0.0 <= val_fraction < 1.0:
            raise ValueError(f"val_fraction must be in [0, 1), got {val_fraction}")
        n = self.num_episodes
        n_val = int(round(val_fraction * n))
        if val_fraction > 0 and n >= 2:
            n_val = min(max(n_val, 1), n - 1)
        order = np.random.default_rng(seed).permutation(n)
        return np.sort(order[n_val:]), np.sort(order[:n_val])

    def file_hash(self) -> str:
        """sha256 hex digest of the file's bytes, for provenance."""
        with open(self.path, "rb") as f:
            return hashlib.file_digest(f, "sha256").hexdigest()


def _open_for_reading(path: Path) -> h5py.File:
    """Open a dataset read-only, also one whose writer was killed (its SWMR-write flag is still set)."""
    try:
        return h5py.File(path, "r")
    except OSError as err:
        if "already open for write" not in str(err):
            raise
        return h5py.File(path, "r", libver="latest", swmr=True)


def _check(path: Path, info: DatasetInfo, data: dict[str, np.ndarray], lengths: np.ndarray) -> dict[str, np.ndarray]:
    """Validate loaded arrays against each other and the attributes; return them cut to the finished episodes."""
    if lengths.ndim != 1 or (lengths < 1).any():
        raise DatasetError(f"{path}: field 'episode_lengths': must be a 1-D array of positive row counts")
    if not (np.isfinite(info.dt) and info.dt > 0):
        raise DatasetError(f"{path}: attribute 'dt': must be a finite policy step > 0 s, got {info.dt}")
    if lengths.sum(dtype=np.float64) >= 2**62:  # before the int64 sum, which such lengths wrap to any row count
        raise DatasetError(f"{path}: field 'episode_lengths': the episodes add up to more rows than a file can hold")
    total = int(lengths.sum())
    for name, value in data.items():
        dtype, ndim = _FIELDS.get(name, (value.dtype, value.ndim))
        if value.dtype != dtype or value.ndim != ndim:
            raise DatasetError(
                f"{path}: field '{name}': expected {np.dtype(dtype)} with {ndim} dims, got {value.dtype} {value.shape}"
            )
        if len(value) < total or (len(value) > total and info.complete):
            raise DatasetError(f"{path}: field '{name}': {len(value)} rows but episode_lengths sum to {total}")
        data[name] = value = value[:total]  # rows past the sum belong to an episode cut off mid-write
        if name in info.columns and value.shape[1] != len(info.columns[name]):
            raise DatasetError(
                f"{path}: field '{name}': {value.shape[1]} columns but the 'columns' attribute "
                f"names {len(info.columns[name])}"
            )
        if value.dtype.kind in "fc" and not np.isfinite(value).all():
            raise DatasetError(f"{path}: field '{name}': contains NaN or inf")
    return data


def write_dataset(path: str | os.PathLike, info: DatasetInfo, episodes: Iterable[Mapping[str, np.ndarray]]) -> None:
    """Write a whole dataset atomically: into a temp file in the same folder, then os.replace onto `path`."""

    def write(tmp: str) -> None:
        with DatasetWriter(tmp, info, overwrite=True) as writer:
            for episode in episodes:
                writer.append_episode(episode)

    atomic_write(path, write)


def _spec_without_pointers(text: str) -> dict:
    """A spec's TOML minus the entries that do not say what the data is: where files live (default_checkpoint) and
    the robot's mirror (`[symmetry]`, which data written before the table was added lacks)."""
    parsed = tomllib.loads(text)
    parsed.get("task", {}).pop("default_checkpoint", None)
    parsed.pop("symmetry", None)
    return parsed


def is_merge_of(out: str | os.PathLike, paths: Sequence[str | os.PathLike]) -> bool:
    """Whether `out` is `merge_datasets(paths, out)` of these files as they are now (their bytes, in this order).

    Lets a loop that grows its buffer skip rewriting one it already wrote: the check hashes the sources, which at
    1.7 M rows takes ~2 s against ~25 s for the merge.
    """
    if not Path(out).exists():
        return False
    try:
        sources = Dataset.load(out).info.metadata.get("merged_from", [])
    except (OSError, DatasetError):
        return False
    return [s.get("sha256") for s in sources] == [Dataset.load(p).file_hash() for p in paths]


def merge_datasets(paths: Sequence[str | os.PathLike], out: str | os.PathLike) -> None:
    """Concatenate the episodes of datasets of the same task (spec, columns, dt) into `out` (atomic).

    Specs must agree except for file pointers (`default_checkpoint`) and the `[symmetry]` table. Only the fields every
    file has are kept (a PPO
    run's `ppo_iteration` is dropped when merged with collector data); metadata["dropped_fields"] names them. The
    merged file keeps the first file's env_id, dt and seed; policy and physics_params are kept when all files agree
    (else policies are joined and physics_params left empty); metadata["merged_from"] records each source.
    """
    if not paths:
        raise ValueError("merge_datasets: no input files")
    sets = [Dataset.load(p) for p in paths]
    _check_same_task(sets)
    common, dropped = _common_fields(sets)
    info = _merged_info(sets, dropped)
    episodes = ({name: d.episode(i)[name] for name in common} for d in sets for i in range(d.num_episodes))
    write_dataset(out, info, episodes)


def _check_same_task(sets: list[Dataset]) -> None:
    """The same spec (but for file pointers), columns and dt in every dataset as in the first."""
    first = sets[0]
    first_spec = _spec_without_pointers(first.info.spec_text)
    for d in sets[1:]:
        for what, a, b in (
            ("attribute 'spec'", _spec_without_pointers(d.info.spec_text), first_spec),
            ("attribute 'columns'", d.info.columns, first.info.columns),
            ("attribute 'dt'", d.info.dt, first.info.dt),
        ):
            if a != b:
                raise DatasetError(f"{d.path}: {what}: differs from {first.path}, cannot merge")


def _common_fields(sets: list[Dataset]) -> tuple[list[str], list[str]]:
    """The fields every dataset has (in the first's order; each of one row shape and dtype in all), and the others,
    sorted."""
    first = sets[0]
    common = [name for name in first.fields if all(name in d.fields for d in sets)]
    dropped = sorted({name for d in sets for name in d.fields} - set(common))
    for d in sets[1:]:
        for name in common:
            if d[name].shape[1:] != first[name].shape[1:] or d[name].dtype != first[name].dtype:
                raise DatasetError(f"{d.path}: field '{name}': shape or dtype differs from {first.path}, cannot merge")
    return common, dropped


def _merged_info(sets: list[Dataset], dropped: list[str]) -> DatasetInfo:
    """The first dataset's info, with the policies joined, physics_params kept if all agree, and each source, the
    union of their physics sources (`rwm_gym.data.lineage`) and the dropped fields in the metadata."""
    first = sets[0]
    policies = list(dict.fromkeys(d.info.policy for d in sets))
    same_physics = all(d.info.physics_params == first.info.physics_params for d in sets)
    sources = [
        {
            "path": str(d.path),
            "sha256": d.file_hash(),
            "policy": d.info.policy,
            "seed": d.info.seed,
            "episodes": d.num_episodes,
            "physics_params": d.info.physics_params,
        }
        for d in sets
    ]
    lineage = union(*(physics_sources(d, s["sha256"]) for d, s in zip(sets, sources, strict=True)))
    metadata = {**first.info.metadata, "merged_from": sources, SOURCES_KEY: lineage}
    if dropped:
        metadata["dropped_fields"] = dropped
    return replace(
        first.info,
        policy=" + ".join(policies),
        physics_params=first.info.physics_params if same_physics else {},
        metadata=metadata,
    )

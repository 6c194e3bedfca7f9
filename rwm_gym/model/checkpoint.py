"""World-model checkpoints: one safetensors file that rebuilds the model alone, never executing code from the file.

Tensors: `model/<name>` (the state dict), `norm/state_mean`, `norm/state_std` (float64), and for resuming
`optim/<param index>/<key>` (optimizer state) and `train/<name>` (RNG states). The safetensors header metadata holds
`format` ("rwm-gym-checkpoint"), `format_version` and `meta`, a JSON object with: model_config, train_config, spec
(the task spec's TOML text), foot_height_std, provenance (dataset path, sha256, train/val episode ids), stats
(iterations,
losses, wall time), extras (free, e.g. the imagined env's reset-data info), package_version, and the optimizer layout
(param groups and non-tensor state). Saves are atomic: a temp file in the same folder, then os.replace.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import save_file

from rwm_gym.atomic import atomic_write
from rwm_gym.data.dataset import Dataset
from rwm_gym.model.base import WorldModel
from rwm_gym.model.config import ModelConfig, TrainConfig, config_difference
from rwm_gym.model.factory import build_model
from rwm_gym.model.normalization import Normalizer
from rwm_gym.spec import TaskSpec, parse_spec
from rwm_gym.untrusted import memory_cap_bytes

FORMAT_NAME = "rwm-gym-checkpoint"
FORMAT_VERSION = 1


class CheckpointError(ValueError):
    """A checkpoint cannot be used; the one-line message names the file and what differs."""


@dataclass(frozen=True)
class CheckpointMeta:
    """Everything in a checkpoint besides the weights."""

    path: Path
    model_config: ModelConfig
    spec: TaskSpec
    normalizer: Normalizer
    train_config: TrainConfig | None = None
    provenance: dict = field(default_factory=dict)
    """dataset path, sha256, train_episodes, val_episodes (ids), ..."""
    stats: dict = field(default_factory=dict)
    """iterations, wall_s, last losses, validation errors, ..."""
    extras: dict = field(default_factory=dict)
    """Free JSON for downstream users (e.g. the imagined env's reset data)."""
    package_version: str = ""
    format_version: int = FORMAT_VERSION
    optimizer_layout: dict | None = field(default=None, repr=False)


def save_checkpoint(
    path: str | os.PathLike,
    model: WorldModel,
    spec: TaskSpec,
    *,
    normalizer: Normalizer | None = None,
    train_config: TrainConfig | None = None,
    provenance: dict | None = None,
    stats: dict | None = None,
    extras: dict | None = None,
    optimizer: torch.optim.Optimizer | None = None,
    training_state: dict[str, torch.Tensor] | None = None,
) -> Path:
    """Write `model` (and optionally the optimizer and `training_state` tensors, for resuming) to `path` atomically."""
    from rwm_gym import __version__

    path = Path(path)
    normalizer = normalizer or Normalizer.from_spec(spec)
    tensors = {f"model/{name}": t.detach().cpu().contiguous().clone() for name, t in model.state_dict().items()}
    tensors["norm/state_mean"] = torch.from_numpy(np.array(normalizer.state_mean, dtype=np.float64))
    tensors["norm/state_std"] = torch.from_numpy(np.array(normalizer.state_std, dtype=np.float64))
    layout = None
    if optimizer is not None:
        state = optimizer.state_dict()
        layout = {"param_groups": state["param_groups"], "values": {}}
        for index, entry in state["state"].items():
            for key, value in entry.items():
                if isinstance(value, torch.Tensor):
                    tensors[f"optim/{index}/{key}"] = value.detach().cpu().contiguous().clone()
                else:
                    layout["values"][f"{index}/{key}"] = value
    for name, value in (training_state or {}).items():
        tensors[f"train/{name}"] = value.detach().cpu().contiguous().clone()
    meta = {
        "model_config": model.config.to_dict(),
        "train_config": train_config and train_config.to_dict(),
        "spec": spec.text,
        "foot_height_std": normalizer.foot_height_std,
        "provenance": provenance or {},
        "stats": stats or {},
        "extras": extras or {},
        "package_version": __version__,
        "optimizer": layout,
    }
    header = {"format": FORMAT_NAME, "format_version": str(FORMAT_VERSION), "meta": json.dumps(meta)}
    return atomic_write(path, lambda tmp: save_file(tensors, tmp, metadata=header))


def _read(path: Path, device: str | torch.device) -> tuple[dict[str, str], dict[str, torch.Tensor]]:
    if not path.is_file():
        if path.exists() and not path.is_dir():  # a FIFO or device: opening it could wait or read without end
            raise CheckpointError(f"{path}: not a regular file (a FIFO, socket or device); a checkpoint is a file")
        raise FileNotFoundError(f"{path}: no such checkpoint file")
    try:
        with safe_open(str(path), framework="pt", device=str(device)) as f:
            header = f.metadata() or {}
            tensors = {name: f.get_tensor(name) for name in f.keys()}
    except (SafetensorError, OSError) as err:
        raise CheckpointError(f"{path}: not a safetensors file or truncated ({' '.join(str(err).split())})") from None
    if header.get("format") != FORMAT_NAME:
        raise CheckpointError(f"{path}: format {header.get('format')!r} is not {FORMAT_NAME!r}")
    version = header.get("format_version", "")
    if not version.isdigit() or int(version) > FORMAT_VERSION:
        raise CheckpointError(
            f"{path}: format_version {version!r} not supported (this reader knows up to "
            f"{FORMAT_VERSION}); upgrade rwm-gym"
        )
    return header, tensors


def read_meta(path: str | os.PathLike) -> CheckpointMeta:
    """The metadata of a checkpoint, without building its model."""
    return _meta(Path(path), *_read(Path(path), "cpu"))


def dataset_rows(path: str | os.PathLike) -> tuple[int | None, str]:
    """Rows (physics transitions) of the dataset a checkpoint was trained on, and where the figure comes from.

    Read from the provenance (`dataset_steps`), else from the dataset file it names when that file is found (as
    named, or beside the checkpoint) with the recorded sha256; otherwise None and the reason.
    """
    provenance = read_meta(path).provenance
    if "dataset_steps" in provenance:
        return int(provenance["dataset_steps"]), f"rows of the world model's dataset ({path} provenance)"
    named = provenance.get("dataset")
    if not named:
        return None, f"unknown: {path} names no dataset in its provenance"
    for candidate in (Path(named), Path(path).parent / named):
        if candidate.is_file():
            dataset = Dataset.load(candidate)
            if provenance.get("sha256") in (None, dataset.file_hash()):
                return int(dataset.num_steps), f"rows of {candidate}, the world model's dataset"
    return None, (
        f"unknown: {path} predates the row count in its provenance (dataset_steps) and its dataset "
        f"{named} (with its sha256) is not here"
    )


def _meta(path: Path, header: dict[str, str], tensors: dict[str, torch.Tensor]) -> CheckpointMeta:
    try:
        meta = json.loads(header["meta"])
        config = ModelConfig.from_dict(meta["model_config"])
        train = meta.get("train_config")
        spec = parse_spec(meta["spec"], where=f"{path}:spec")
        normalizer = Normalizer(
            tensors["norm/state_mean"].cpu().numpy(),
            tensors["norm/state_std"].cpu().numpy(),
            float(meta["foot_height_std"]),
        )
        return CheckpointMeta(
            path,
            config,
            spec,
            normalizer,
            train and TrainConfig.from_dict(train),
            meta.get("provenance", {}),
            meta.get("stats", {}),
            meta.get("extras", {}),
            meta.get("package_version", ""),
            int(header["format_version"]),
            meta.get("optimizer"),
        )
    except KeyError as err:
        raise CheckpointError(f"{path}: metadata field {err.args[0]!r} missing") from None
    except (ValueError, TypeError, RecursionError) as err:
        if isinstance(err, CheckpointError):
            raise
        raise CheckpointError(f"{path}: metadata unreadable ({' '.join(str(err).split())})") from None


def spec_difference(found: TaskSpec, expected: TaskSpec) -> str | None:
    """The first way in which two task specs' model-relevant layouts differ, as a phrase; None if they agree."""
    if found.state_columns != expected.state_columns:
        a, b = found.state_columns, expected.state_columns
        if len(a) != len(b):
            return f"state layout has {len(a)} columns, expected {len(b)}"
        i = next(i for i in range(len(a)) if a[i] != b[i])
        return f"state column {i} is {a[i]!r}, expected {b[i]!r}"
    for what, a, b in (
        ("actuator joints", found.actuator.joints, expected.actuator.joints),
        ("contact bodies", found.privileged.contact_bodies, expected.privileged.contact_bodies),
        ("feet", found.privileged.feet, expected.privileged.feet),
    ):
        if a != b:
            return f"{what} are {list(a)}, expected {list(b)}"
    for what, a, b in (
        ("state mean", found.state_mean, expected.state_mean),
        ("state std", found.state_std, expected.state_std),
    ):
        if not np.allclose(a, b):
            i = int(np.flatnonzero(~np.isclose(a, b))[0])
            return f"{what} of column {found.state_columns[i]!r} is {a[i]:g}, expected {b[i]:g}"
    if found.name != expected.name:
        return f"task is {found.name!r}, expected {expected.name!r}"
    return None


def load_checkpoint(
    path: str | os.PathLike, device: str | torch.device = "cpu", expect_spec: TaskSpec | None = None
) -> tuple[WorldModel, CheckpointMeta]:
    """Rebuild the model (in eval mode, on `device`) and its metadata from the file alone.

    Raises CheckpointError (one line naming the file) for a file that is not a safetensors checkpoint or is truncated,
    an unknown format or version, a spec that differs from `expect_spec`, or a tensor of the wrong shape.
    """
    path = Path(path)
    header, tensors = _read(path, device)
    meta = _meta(path, header, tensors)
    if expect_spec is not None and (difference := spec_difference(meta.spec, expect_spec)):
        raise CheckpointError(f"{path}: checkpoint is for another task layout: {difference}")
    # The joint limits are the checkpoint's own buffers: no MJCF is read. Shapes first, on the meta device, so a
    # config that asks for more than the file holds allocates nothing before it is refused.
    build_spec = replace(meta.spec, model="")
    with torch.device("meta"):
        expected = build_model(meta.model_config, build_spec).state_dict()
    need = sum(t.numel() * t.element_size() for t in expected.values())
    if need > memory_cap_bytes():
        raise CheckpointError(
            f"{path}: its model config asks for {need / 1e9:.1f} GB of weights, over half this machine's memory"
        )
    stored = {name[len("model/") :]: t for name, t in tensors.items() if name.startswith("model/")}
    for name, tensor in expected.items():
        if name not in stored:
            raise CheckpointError(f"{path}: tensor 'model/{name}' missing for a {meta.model_config.kind} model")
        if stored[name].shape != tensor.shape:
            raise CheckpointError(
                f"{path}: tensor 'model/{name}' has shape {tuple(stored[name].shape)}, the model "
                f"config expects {tuple(tensor.shape)}"
            )
    if extra := sorted(set(stored) - set(expected)):
        raise CheckpointError(f"{path}: tensor 'model/{extra[0]}' is not part of a {meta.model_config.kind} model")
    check_finite(path, stored, meta.normalizer)
    model = build_model(meta.model_config, build_spec).to(device)
    model.load_state_dict(stored)
    return model.eval(), meta


def check_finite(path: Path, weights: dict[str, torch.Tensor], normalizer) -> None:
    """CheckpointError for NaN or inf weights or a normalisation std that is not positive and finite: such a model
    only predicts nan, so it is refused at load rather than found in a table of nan."""
    for name, tensor in weights.items():
        if tensor.is_floating_point() and not bool(torch.isfinite(tensor).all()):
            raise CheckpointError(f"{path}: tensor 'model/{name}' holds NaN or inf")
    std = np.asarray(normalizer.state_std, dtype=np.float64)
    if not (np.all(np.isfinite(std)) and np.all(std > 0)) or not np.all(np.isfinite(normalizer.state_mean)):
        raise CheckpointError(
            f"{path}: normalisation statistics are not finite with std > 0 (tensor 'norm/state_std' "
            f"or 'norm/state_mean')"
        )


def load_training_state(
    path: str | os.PathLike, model: WorldModel, optimizer: torch.optim.Optimizer | None
) -> tuple[CheckpointMeta, dict[str, torch.Tensor]]:
    """Load weights and optimizer state of a checkpoint into existing objects (for --resume); returns its metadata and
    the `train/` tensors (RNG states)."""
    path = Path(path)
    loaded, meta = load_checkpoint(path, device=model.device)
    if loaded.config != model.config:
        raise CheckpointError(
            f"{path}: model config differs from this run's ({config_difference(loaded.config, model.config)})"
        )
    model.load_state_dict(loaded.state_dict())
    _, tensors = _read(path, "cpu")
    if optimizer is not None:
        if meta.optimizer_layout is None:
            raise CheckpointError(f"{path}: no optimizer state saved, cannot resume")
        state: dict[int, dict[str, Any]] = {}
        for name, value in tensors.items():
            if name.startswith("optim/"):
                _, index, key = name.split("/", 2)
                state.setdefault(int(index), {})[key] = value
        for name, value in meta.optimizer_layout["values"].items():
            index, key = name.split("/", 1)
            state.setdefault(int(index), {})[key] = value
        optimizer.load_state_dict({"state": state, "param_groups": meta.optimizer_layout["param_groups"]})
    return meta, {name[len("train/") :]: t for name, t in tensors.items() if name.startswith("train/")}

"""Option groups several `rwm-gym` commands share: one dataclass per group, so a flag that means the same in every
command (`--overwrite`, `--device`, `--tensorboard`, `--run-dir`, ...) is written once. A command adds a group with
`add_group`; its own options are dataclasses in its module, listed with these in its `OPTIONS`."""

from __future__ import annotations

import argparse
import json
from collections.abc import Iterable
from dataclasses import dataclass, fields
from pathlib import Path

from rwm_gym.options import add_dataclass_options, option, torch_device
from rwm_gym.workers import BACKENDS


@dataclass(frozen=True)
class OverwriteOption:
    """Whether an existing output is replaced."""

    overwrite: bool = False
    """replace an existing output (without it, the command stops before writing over one)"""


@dataclass(frozen=True)
class TorchOptions:
    """Where torch runs a command's networks."""

    device: str = option("cpu", parse=torch_device)
    """torch device of the policy and of the world model"""
    threads: int | None = option(None, ge=1)
    """torch CPU threads (default: torch's; 1 is fastest on a machine shared with other jobs)"""


@dataclass(frozen=True)
class WorldModelOptions:
    """The world model an imagined env runs, and the real histories its episodes restart from."""

    checkpoint: str | None = None
    """world-model checkpoint (default: the shipped one)"""
    reset_data: Path | None = None
    """dataset of real histories imagined episodes restart from (default: the checkpoint's)"""


@dataclass(frozen=True)
class TensorBoardOption:
    """Where a training run writes its TensorBoard scalars."""

    tensorboard: str | None = option(None, metavar="DIR")
    """write the run's TensorBoard scalars here (docs/guides/ppo-in-imagination.md lists each command's; needs the
    [tensorboard] extra)"""


@dataclass(frozen=True)
class RunFolderOptions:
    """A policy-training run in a resumable folder (`rwm_gym.rl.training_run`)."""

    run_dir: Path | None = None
    """resumable run folder (rwm_gym.rl.training_run): resume point, snapshots, log.csv, experience; running the
    same command again continues to the same --timesteps total"""
    save_every: int = option(10, ge=1)
    """with --run-dir: updates (PPO: rollouts) between resume points"""
    snapshot_every: int = option(25, ge=1)
    """with --run-dir: updates (PPO: rollouts) between policy snapshots"""


@dataclass(frozen=True)
class WorkerOptions:
    """Workers a command's physics episodes are split over (`rwm_gym.workers`): the same results as one."""

    workers: int = option(1, ge=1)
    """workers the episodes are split over, each a batched core of a block of them; the same results as one"""
    backend: str = option("processes", choices=BACKENDS)
    """where the workers run: spawned processes on this machine, or Ray tasks on the cluster `ray start` made (else
    a local one; needs pip install 'rwm-gym[ray]')"""


def add_group(
    parser: argparse.ArgumentParser,
    cls: type,
    title: str | None = None,
    *,
    only: Iterable[str] | None = None,
    **options,
) -> None:
    """The flags of the dataclass `cls` in `parser` (in an argument group `title` if given, described by the class
    docstring): of the fields named in `only` if given (a library config whose other fields the command leaves at
    their defaults); `options` go to `add_dataclass_options`."""
    target = parser if title is None else parser.add_argument_group(title, cls.__doc__)
    if only is not None:
        options["skip"] = {f.name for f in fields(cls)} - set(only)
    add_dataclass_options(target, cls, **options)


@dataclass(frozen=True)
class PhysicsEnvOptions:
    """The physics env a command runs: an id or a spec, and the robot's MJCF."""

    env: str = "AnymalD-MuJoCo-v0"
    """registered physics env id, or the path of a task spec (.toml)"""
    xml_file: Path | None = None
    """another MJCF of the robot"""


def parse_physics(text: str, flag: str = "--physics") -> dict:
    """A robot's physical parameters from a flag: a JSON dict of `PhysicsParams` fields, or the path of a JSON file
    holding one, bare or as env kwargs `{"physics": {...}}` (`rwm-gym gap`'s corrected_physics.json). Checked here:
    ValueError (one line) for bad JSON, unknown names or values that are not finite numbers."""
    from rwm_gym.physics.params import PhysicsParams

    def no_constant(name: str):
        raise ValueError(f"{flag}: {name} is not a physics value (give finite numbers)")

    source = Path(text)
    try:
        is_file = not text.lstrip().startswith("{") and source.is_file()
    except OSError:  # a name too long for a path: JSON text
        is_file = False
    try:
        values = json.loads(source.read_text() if is_file else text, parse_constant=no_constant)
    except json.JSONDecodeError as err:
        where = f"{source} is" if is_file else "is"
        raise ValueError(f"{flag} {where} not valid JSON ({err})") from None
    except RecursionError:
        where = f"{source} is" if is_file else "is"
        raise ValueError(f"{flag} {where} nested too deeply (a physics dict is two levels deep)") from None
    except OSError as err:
        raise ValueError(f"{flag}: {source}: {err.strerror}") from None
    if isinstance(values, dict) and set(values) == {"physics"}:
        values = values["physics"]
    if not isinstance(values, dict):
        raise ValueError(f"{flag} must be a JSON object of physics parameters, got {type(values).__name__}")
    try:
        PhysicsParams.from_dict(values)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{flag}: {err}") from None
    return values

"""`rwm-gym mbpo`: the MBPO-PPO loop (`rwm_gym.rl.mbpo`) in a resumable run folder."""

from __future__ import annotations

import argparse
import re
from dataclasses import dataclass
from pathlib import Path

from rwm_gym.commands._imagination import add_imagination_options, imagination_from_args
from rwm_gym.commands._options import OverwriteOption, TensorBoardOption, TorchOptions, add_group
from rwm_gym.imagination.options import ImaginationOptions
from rwm_gym.options import (
    add_dataclass_options,
    dataclass_from_args,
)
from rwm_gym.output_guard import OutputError, check_folder, claim, resolved
from rwm_gym.rl.mbpo import MBPOConfig, mbpo

RUN_FILES = re.compile(r"(data_\d+\.h5|buffer(_base)?\.h5|model_\d+\.safetensors|policy_\d+\.zip|mbpo\.(json|png))")
"""The files the loop writes in its folder (`--out`)."""


def is_run_folder(folder: Path) -> bool:
    """Whether every file in `folder` is one the loop writes (or a hidden temp file, or a dataset a killed write
    left): the folder of a run, finished or killed, that the same command continues."""
    return all(p.name.startswith(".") or RUN_FILES.fullmatch(p.name.split(".partial-")[0]) for p in folder.iterdir())


def check_run_folder(out: Path, inputs, overwrite: bool = False) -> None:
    """A one-line OutputError for an input that the loop would overwrite in its folder, or the folder itself; for an
    input inside the folder; and for a folder of other files, unless `overwrite`."""
    folder = resolved(out)
    for source in (s for s in inputs if s is not None):
        path = resolved(source)
        if path == folder or (path.parent == folder and RUN_FILES.fullmatch(path.name)):
            raise OutputError(
                f"--out {out}: the run writes {path.name if path != folder else 'into it'}, which is "
                f"the input {source}; copy the input elsewhere first"
            )
    check_folder(out, inputs=inputs, overwrite=overwrite, continues=folder.is_dir() and is_run_folder(folder))


@dataclass(frozen=True)
class RunOptions:
    """The loop's inputs and its run folder."""

    data: Path
    """initial physics dataset (HDF5)"""
    out: Path
    """run folder: models, data, policies and the report; the same command resumes it"""
    checkpoint: str | None = None
    """world model to start from (default: train one on --data)"""
    model: str = "rwm"
    """world-model kind to (re)train"""
    init_policy: Path | None = None
    """SB3 PPO zip to start from, e.g. a behaviour-cloned actor (default: a fresh policy)"""
    model_free_curve: Path | None = None
    """CSV (timesteps, tracking) of a model-free PPO run, drawn beside the loop's curve, e.g.
    assets/policies/anymal_d_ppo_physics_curve.csv (default: none)"""


OPTIONS = (RunOptions, OverwriteOption, TensorBoardOption, TorchOptions, MBPOConfig, ImaginationOptions)
"""The dataclasses the flags of `rwm-gym mbpo` come from."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `rwm-gym mbpo`: the run's files, then one flag per `MBPOConfig` and `ImaginationOptions` field."""
    for group in (RunOptions, OverwriteOption, TensorBoardOption, TorchOptions):
        add_group(parser, group)
    add_dataclass_options(parser, MBPOConfig, skip={"imagination"})
    add_imagination_options(
        parser,
        defaults=MBPOConfig().imagination,
        aliases={"episode_steps": ["--imagined-episode-steps"]},
    )


def run(args: argparse.Namespace) -> int:
    """`rwm-gym mbpo`: refuse a run folder that would overwrite an input, then run (or resume) the loop in it."""
    from rwm_gym.tensorboard import check_tensorboard

    check_tensorboard(args.tensorboard, "rwm-gym mbpo")
    if args.threads:
        import torch

        torch.set_num_threads(args.threads)
    config = dataclass_from_args(
        MBPOConfig, args, skip={"imagination"}, imagination=imagination_from_args(args, MBPOConfig().imagination)
    )
    try:
        inputs = [args.data, args.checkpoint, args.init_policy, args.model_free_curve]
        check_run_folder(args.out, inputs, overwrite=args.overwrite)
        with claim(args.out):
            report = mbpo(
                args.data,
                args.out,
                config,
                checkpoint=args.checkpoint,
                init_policy=args.init_policy,
                model_kind=args.model,
                device=args.device,
                model_free_curve=args.model_free_curve,
                tensorboard=args.tensorboard,
            )
    except ValueError as error:
        raise SystemExit(f"rwm-gym mbpo: {error}") from None
    print(
        f"best physics tracking {report['best_tracking']:.3f} at iteration {report['best_iteration']}; "
        f"report {args.out / 'mbpo.json'}, curve {args.out / 'mbpo.png'}"
    )
    return 0

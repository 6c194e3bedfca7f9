"""`rwm-gym train`: one option per `TrainConfig` and `ModelConfig` field, then `rwm_gym.model.train.train`; bad input
is one line on stderr and exit 2, Ctrl-C exit 130 after a resumable checkpoint."""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import time
from dataclasses import dataclass, fields, replace
from pathlib import Path

from safetensors import SafetensorError

from rwm_gym.commands._options import OverwriteOption, TensorBoardOption, add_group
from rwm_gym.data.dataset import Dataset, DatasetError
from rwm_gym.model import distributed
from rwm_gym.model.checkpoint import CheckpointError, read_meta
from rwm_gym.model.config import LOSSES, MODEL_KINDS, SCHEDULES, ModelConfig, TrainConfig
from rwm_gym.model.factory import model_config_for
from rwm_gym.model.train import train
from rwm_gym.options import add_dataclass_options, option

_MODEL_OPTIONS = tuple(
    f for f in fields(ModelConfig) if f.name not in ("kind", "state_dim", "action_dim", "contact_dim", "foot_dim")
)


@dataclass(frozen=True, kw_only=True)
class TrainOptions:
    """The run: its data, where it starts from, and its checkpoint."""

    data: str
    """HDF5 dataset to train on"""
    model: str | None = option(None, choices=(*MODEL_KINDS, "auto"))
    """model family (default rwm, or --init's); auto: the kind with the lowest measured error for this data size and
    --cpu-minutes budget in the shipped table of benchmarks/budget_curve.py (rwm_gym.model.choice)"""
    cpu_minutes: float | None = option(None, gt=0)
    """budget in this process's CPU minutes (time.process_time: other jobs on the machine do not count), in place
    of --minutes"""
    out: str
    """checkpoint to write (.safetensors)"""
    resume: bool = False
    """continue the run saved at --out"""
    init: str | None = option(None, metavar="CKPT")
    """start from this checkpoint's weights (fine-tuning); its model config is the default of every model option"""
    teacher_forcing: bool = False
    """same as --forecast 1"""
    quiet: bool = False
    """no progress bar"""


OPTIONS = (TrainOptions, OverwriteOption, TensorBoardOption, TrainConfig, ModelConfig)
"""The dataclasses the flags of `rwm-gym train` come from."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `rwm-gym train`: the run, then one flag per TrainConfig and ModelConfig field."""
    for group in (TrainOptions, OverwriteOption, TensorBoardOption):
        add_group(parser, group)
    add_dataclass_options(
        parser.add_argument_group("training options"),
        TrainConfig,
        defaults_none=True,
        choices={"loss": LOSSES, "schedule": SCHEDULES},
        nargs={"forecast_curriculum": "+"},
    )
    add_dataclass_options(
        parser.add_argument_group("model options"),
        ModelConfig,
        defaults_none=True,
        skip=("kind", "state_dim", "action_dim", "contact_dim", "foot_dim"),
    )


def summary_text(stats: dict) -> str:
    """The end-of-run line's figures, each to a sensible precision ('none' where a figure is missing)."""

    def figure(value, form: str) -> str:
        return "none" if value is None else format(value, form)

    return (
        f"{stats['iterations']:,} iterations in {stats['wall_s']:.1f} s, train loss "
        f"{figure(stats.get('train_loss'), '.4f')}, val error {figure(stats.get('val_error'), '.4f')}"
    )


def _given(args: argparse.Namespace, options) -> dict:
    return {f.name: getattr(args, f.name) for f in options if getattr(args, f.name, None) is not None}


def _model_config(args: argparse.Namespace, dataset: Dataset) -> ModelConfig:
    """The options given, on top of `--init`'s model config when fine-tuning (else the family's defaults)."""
    given = _given(args, _MODEL_OPTIONS)
    if args.init is None:
        return model_config_for(args.model or "rwm", dataset.spec(), **given)
    start = read_meta(args.init).model_config
    if args.model is not None and args.model != start.kind:
        raise ValueError(f"{args.init}: cannot start a {args.model} model from a {start.kind} checkpoint")
    return replace(start, **given)


def _auto_kind(args: argparse.Namespace, dataset: Dataset) -> str:
    """`--model auto`: the kind the shipped table picks for the data's rows and the --cpu-minutes budget (one line
    printed saying which and why); on --resume, the kind of the run being resumed."""
    from rwm_gym.model.choice import choose_kind, shipped_table

    if args.init is not None:
        raise ValueError("--model auto picks a kind to train from scratch; with --init the kind is the checkpoint's")
    if args.resume:
        kind = read_meta(args.out).model_config.kind
        print(f"--model auto: {kind}, the kind of the run resumed at {args.out}")
        return kind
    if args.cpu_minutes is None:
        raise ValueError("--model auto picks for a compute budget: give --cpu-minutes")
    choice = choose_kind(shipped_table(), dataset.num_steps, args.cpu_minutes)
    if distributed.current_world().is_main:
        print(choice.reason(args.cpu_minutes, dataset.num_steps))
    return choice.kind


def memory_estimate(model_config: ModelConfig, config: TrainConfig, spec) -> float:
    """Bytes a run needs, roughly: weights, gradients and Adam's two moments (float32), plus the activations of one
    batch (every window's rows through every layer, a few tensors each). Sized on torch's meta device, so a model too
    big to build is measured without allocating it."""
    import torch

    from rwm_gym.model.factory import build_model

    with torch.device("meta"):
        params = sum(p.numel() for p in build_model(model_config, spec).parameters())
    width = max(model_config.hidden_size, model_config.head_hidden)
    activations = (
        config.batch_size * (config.history + max(config.forecasts)) * width * (model_config.num_layers + 1) * 8
    )
    return 4.0 * (4 * params + activations)


def check_memory(model_config: ModelConfig, config: TrainConfig, spec) -> None:
    """A one-line ValueError for a model and batch that cannot fit in this machine's memory."""
    need = memory_estimate(model_config, config, spec)
    have = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    if config.device.startswith("cuda"):
        import torch

        if torch.cuda.is_available():
            have = torch.cuda.get_device_properties(0).total_memory
    if need > have:
        raise ValueError(
            f"the model and batch need about {need / 2**30:.0f} GiB (hidden size "
            f"{model_config.hidden_size}, batch size {config.batch_size}), more than the "
            f"{have / 2**30:.0f} GiB this machine has"
        )


def run(args: argparse.Namespace) -> int:
    """`rwm-gym train`: train, print a summary line, write the checkpoint; 2 on bad input, 130 on Ctrl-C."""
    from rwm_gym.output_guard import check_output, claim
    from rwm_gym.tensorboard import check_tensorboard

    check_tensorboard(args.tensorboard, "rwm-gym train")
    try:
        if args.resume and not Path(args.out).exists():
            raise ValueError(f"--resume: {args.out} does not exist, nothing to resume (leave out --resume to start)")
        options = _given(args, fields(TrainConfig))
        if args.teacher_forcing:
            options["forecast"] = 1
        if args.cpu_minutes is not None:
            if "minutes" in options:
                raise ValueError("give --minutes (wall clock) or --cpu-minutes (this process's CPU time), not both")
            options["minutes"] = args.cpu_minutes
        if options.get("minutes") and "iterations" not in options:
            options["iterations"] = 0
        config = TrainConfig(**options)
        dataset = Dataset.load(args.data)  # a missing input is named before anything about the output
        check_output(args.out, inputs=[args.data, args.init], overwrite=args.overwrite or args.resume)
        if args.model == "auto":
            args.model = _auto_kind(args, dataset)
        model_config = _model_config(args, dataset)
        check_memory(model_config, config, dataset.spec())
        main_rank = os.environ.get("RANK", "0") == "0"  # only rank 0 writes, so only it holds the lock
        with claim(args.out) if main_rank else contextlib.nullcontext():
            result = train(
                dataset,
                model_config,
                config,
                args.out,
                resume=args.resume,
                progress=not args.quiet,
                tensorboard=args.tensorboard,
                init=args.init,
                overwrite=args.overwrite,
                clock=time.process_time if args.cpu_minutes is not None else time.monotonic,
            )
    except KeyboardInterrupt:
        if distributed.current_world().is_main:
            kept = f"{args.out} holds a resumable checkpoint (--resume continues it)" if Path(args.out).exists() else ""
            print(f"rwm-gym train: interrupted{'; ' + kept if kept else ''}", file=sys.stderr)
        return 130
    except (ValueError, OSError, DatasetError, CheckpointError, SafetensorError) as err:
        if isinstance(err, SafetensorError):  # safetensors' own error for a write that failed (a full disk)
            err = f"--out {args.out}: cannot write the checkpoint ({err})"
        if distributed.current_world().is_main:
            print(f"rwm-gym train: {' '.join(str(err).split())}", file=sys.stderr)
        return 2
    finally:
        distributed.close_world()
    if result.path is not None:  # rank 0
        print(f"{model_config.kind}: wrote {result.path} ({summary_text(result.stats)})")
    return 0

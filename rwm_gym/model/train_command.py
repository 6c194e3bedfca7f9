"""`rwm-gym train`: one option per `TrainConfig` and `ModelConfig` field, then `rwm_gym.model.train.train`; bad input
is one line on stderr and exit 2, Ctrl-C exit 130 after a resumable checkpoint."""

from __future__ import annotations

import argparse
import sys
from dataclasses import fields, replace

from rwm_gym.data.dataset import Dataset, DatasetError
from rwm_gym.model import distributed
from rwm_gym.model.checkpoint import CheckpointError, read_meta
from rwm_gym.model.config import LOSSES, MODEL_KINDS, SCHEDULES, ModelConfig, TrainConfig
from rwm_gym.model.factory import model_config_for
from rwm_gym.model.train import train
from rwm_gym.options import add_dataclass_options

_MODEL_OPTIONS = tuple(f for f in fields(ModelConfig)
                       if f.name not in ("kind", "state_dim", "action_dim", "contact_dim", "foot_dim"))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `rwm-gym train`: the run, then one flag per TrainConfig and ModelConfig field."""
    parser.add_argument("--data", required=True, help="HDF5 dataset to train on")
    parser.add_argument("--model", choices=MODEL_KINDS,
                        help="model family (default rwm, or --init's)")
    parser.add_argument("--out", required=True, help="checkpoint to write (.safetensors)")
    parser.add_argument("--resume", action="store_true", help="continue the run saved at --out")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    parser.add_argument("--init", metavar="CKPT", help="start from this checkpoint's weights (fine-tuning); its model "
                        "config is the default of every model option")
    parser.add_argument("--teacher-forcing", action="store_true", help="same as --forecast 1")
    parser.add_argument("--tensorboard", metavar="DIR", help="write TensorBoard scalars here (needs tensorboard)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    add_dataclass_options(parser.add_argument_group("training options"), TrainConfig, defaults_none=True,
                          choices={"loss": LOSSES, "schedule": SCHEDULES})
    add_dataclass_options(parser.add_argument_group("model options"), ModelConfig, defaults_none=True,
                          skip=("kind", "state_dim", "action_dim", "contact_dim", "foot_dim"))


def summary_text(stats: dict) -> str:
    """The end-of-run line's figures, each to a sensible precision ('none' where a figure is missing)."""
    def figure(value, form: str) -> str:
        return "none" if value is None else format(value, form)

    return (f"{stats['iterations']:,} iterations in {stats['wall_s']:.1f} s, train loss "
            f"{figure(stats.get('train_loss'), '.4f')}, val error {figure(stats.get('val_error'), '.4f')}")


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


def run(args: argparse.Namespace) -> int:
    """`rwm-gym train`: train, print a summary line, write the checkpoint; 2 on bad input, 130 on Ctrl-C."""
    try:
        options = _given(args, fields(TrainConfig))
        if args.teacher_forcing:
            options["forecast"] = 1
        if options.get("minutes") and "iterations" not in options:
            options["iterations"] = 0
        config = TrainConfig(**options)
        dataset = Dataset.load(args.data)
        model_config = _model_config(args, dataset)
        result = train(dataset, model_config, config, args.out, resume=args.resume, progress=not args.quiet,
                       tensorboard=args.tensorboard, init=args.init, overwrite=args.overwrite)
    except KeyboardInterrupt:
        return 130
    except (ValueError, FileNotFoundError, FileExistsError, DatasetError, CheckpointError) as err:
        if distributed.current_world().is_main:
            print(f"rwm-gym train: {err}", file=sys.stderr)
        return 2
    finally:
        distributed.close_world()
    if result.path is not None:  # rank 0
        print(f"{model_config.kind}: wrote {result.path} ({summary_text(result.stats)})")
    return 0

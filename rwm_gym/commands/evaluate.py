"""`rwm-gym evaluate`: long-horizon prediction error of a checkpoint on datasets (`rwm_gym.model.evaluate`)."""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path

from rwm_gym.atomic import write_json
from rwm_gym.commands._options import OverwriteOption, add_group
from rwm_gym.data.dataset import DatasetError
from rwm_gym.model.checkpoint import CheckpointError
from rwm_gym.model.evaluate import (
    EvalConfig,
    evaluate_checkpoint,
    format_table,
    plot_running_mean,
)
from rwm_gym.options import dataclass_from_args, option


@dataclass(frozen=True)
class EvaluateOptions:
    """The checkpoint, the data it is evaluated on, and what is written (how: `EvalConfig`)."""

    checkpoint: str
    """world-model checkpoint (.safetensors)"""
    data: tuple[str, ...] = option(nargs="+")
    """HDF5 datasets of the same task (held-out episodes), each evaluated on its own"""
    out: str | None = None
    """folder for evaluation.json and error_vs_horizon.png"""
    all_episodes: bool = False
    """use every episode, even of the checkpoint's training file or repeating its episodes"""
    training_data: tuple[str, ...] = option((), nargs="+", metavar="FILE")
    """data the model trained on besides its recorded file (e.g. an --init checkpoint's): evaluated episodes that
    repeat one of theirs are left out (default: none)"""
    quiet: bool = False
    """no progress bar"""


OPTIONS = (EvaluateOptions, OverwriteOption, EvalConfig)
"""The dataclasses the flags of `rwm-gym evaluate` come from."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `rwm-gym evaluate`: what is evaluated, then one flag per `EvalConfig` field but its batch size."""
    add_group(parser, EvaluateOptions)
    add_group(parser, OverwriteOption)
    add_group(
        parser,
        EvalConfig,
        "evaluation",
        skip={"batch_size"},
        flags={"noise_levels": ["--noise"]},
        nargs={"horizons": "+", "noise_levels": "*"},
    )


def run(args: argparse.Namespace) -> int:
    """`rwm-gym evaluate`: 0, or 2 with one line on stderr on bad input."""
    from rwm_gym.output_guard import check_output

    results = {}
    try:
        if args.max_horizon is not None and max(args.horizons) > args.max_horizon:
            raise ValueError(f"--horizons {max(args.horizons)} is above --max-horizon {args.max_horizon}")
        if args.out:
            inputs = [args.checkpoint, *args.data, *args.training_data]
            check_output(args.out, inputs=inputs, overwrite=True, folder=True)  # not a folder holding an input
            for name in ("evaluation.json", "error_vs_horizon.png"):
                check_output(Path(args.out) / name, inputs=inputs, overwrite=args.overwrite)
        config = dataclass_from_args(EvalConfig, args)
        for data in args.data:
            results[Path(data).stem] = evaluate_checkpoint(
                args.checkpoint, data, config, args.all_episodes, not args.quiet, args.training_data
            )
    except (ValueError, FileNotFoundError, DatasetError, CheckpointError) as err:
        print(f"rwm-gym evaluate: {err}", file=sys.stderr)
        return 2
    for result in results.values():
        if cut := [n for n in args.horizons if n not in result["horizons"]]:  # said, not done quietly
            print(
                f"rwm-gym evaluate: {result['data']}: horizons {cut} are longer than its evaluated episodes allow; "
                f"reported up to {result['longest']} steps",
                file=sys.stderr,
            )
        print(f"{result['model']} on {result['data']} ({result['episode_set']}, {result['episodes']} episodes)")
        print(format_table(result) + "\n")
    if args.out:
        out = Path(args.out)
        first = next(iter(results.values()))
        write_json(out / "evaluation.json", first if len(results) == 1 else {"sources": results})
        plot_running_mean(
            results if len(results) > 1 else {first["model"]: first},
            out / "error_vs_horizon.png",
            title=f"{first['model']}: error against the open-loop horizon",
        )
        print(f"wrote {out / 'evaluation.json'} and {out / 'error_vs_horizon.png'}")
    return 0

"""`rwm-gym evaluate`: long-horizon prediction error of a checkpoint on datasets (`rwm_gym.model.evaluate`)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from rwm_gym.atomic import write_json
from rwm_gym.data.dataset import DatasetError
from rwm_gym.model.checkpoint import CheckpointError
from rwm_gym.model.evaluate import (
    EvalConfig,
    evaluate_checkpoint,
    format_table,
    plot_running_mean,
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `rwm-gym evaluate`."""
    d = EvalConfig()
    parser.add_argument("--checkpoint", required=True, help="world-model checkpoint (.safetensors)")
    parser.add_argument(
        "--data",
        required=True,
        nargs="+",
        help="HDF5 datasets of the same task (held-out episodes), each evaluated on its own",
    )
    parser.add_argument("--out", help="folder for evaluation.json and error_vs_horizon.png")
    parser.add_argument("--history", type=int, default=d.history, help=f"warm-up rows (default {d.history})")
    parser.add_argument("--horizons", type=int, nargs="+", default=list(d.horizons), help="horizons to report")
    parser.add_argument("--max-horizon", type=int, default=d.max_horizon, help="cap of the longest horizon")
    parser.add_argument(
        "--noise",
        type=float,
        nargs="*",
        default=list(d.noise_levels),
        help="noise stds for the robustness test (none: skip)",
    )
    parser.add_argument("--max-windows", type=int, default=d.max_windows, help="windows per horizon")
    parser.add_argument("--device", default=d.device, help="torch device")
    parser.add_argument("--seed", type=int, default=d.seed, help="seed of window choice and noise")
    parser.add_argument(
        "--all-episodes",
        action="store_true",
        help="use every episode, even of the checkpoint's training file or repeating its episodes",
    )
    parser.add_argument(
        "--training-data",
        nargs="+",
        default=[],
        metavar="FILE",
        help="data the model trained on besides its recorded file (e.g. an --init checkpoint's): "
        "evaluated episodes that repeat one of theirs are left out (default: none)",
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing OUT/evaluation.json")


def run(args: argparse.Namespace) -> int:
    """`rwm-gym evaluate`: 0, or 2 with one line on stderr on bad input."""
    from rwm_gym.output_guard import check_output

    results = {}
    try:
        if max(args.horizons) > args.max_horizon:
            raise ValueError(f"--horizons {max(args.horizons)} is above --max-horizon {args.max_horizon}")
        if args.out:
            inputs = [args.checkpoint, *args.data, *args.training_data]
            check_output(Path(args.out) / "error_vs_horizon.png", inputs=inputs, overwrite=True)
            check_output(Path(args.out) / "evaluation.json", inputs=inputs, overwrite=args.overwrite)
        config = EvalConfig(
            history=args.history,
            horizons=tuple(args.horizons),
            max_horizon=args.max_horizon,
            noise_levels=tuple(args.noise),
            max_windows=args.max_windows,
            seed=args.seed,
            device=args.device,
        )
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

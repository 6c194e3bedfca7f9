"""The `rwm-gym` command: one subcommand per job, each implemented in the module that owns the job.

Each module listed in `COMMANDS` defines `add_arguments(parser)` and `run(args) -> int | None`; it is imported only
when its subcommand runs, so `rwm-gym --help` stays fast.
"""

from __future__ import annotations

import argparse
import importlib
import sys

COMMANDS: dict[str, tuple[str, str]] = {
    "collect": ("rwm_gym.data.collect", "collect episodes from a physics env into an HDF5 dataset"),
    "train": ("rwm_gym.model.train", "train a world model (RWM or a baseline) on a dataset"),
    "evaluate": ("rwm_gym.model.evaluate", "long-horizon prediction error of a checkpoint on a dataset"),
    "ppo": ("rwm_gym.rl.ppo", "train PPO in imagination (or physics) and evaluate it in physics"),
    "score": ("rwm_gym.rl.score", "tracking score of a policy in physics (or a world model) beside the zero-action floor"),
    "mbpo": ("rwm_gym.rl.mbpo", "MBPO-PPO loop: collect, retrain the model, PPO in imagination, repeat"),
    "make-measured": ("rwm_gym.gap.measured", "make 'measured' data from a simulator with a hidden physical effect"),
    "gap": ("rwm_gym.gap.workflow", "find, name and correct the gap between a simulator and measured data"),
}


def build_parser(selected: str | None = None) -> argparse.ArgumentParser:
    """The parser; only the `selected` subcommand's module is imported to add its options."""
    parser = argparse.ArgumentParser(prog="rwm-gym", description="Learned robot simulators as Gymnasium envs.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (module, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.set_defaults(_module=module)
        if name != selected:
            continue
        try:
            importlib.import_module(module).add_arguments(p)
        except ModuleNotFoundError as err:
            if err.name is None or not module.startswith(err.name):
                raise
            p.set_defaults(_missing=module)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    selected = next((a for a in argv if not a.startswith("-")), None)
    args = build_parser(selected).parse_args(argv)
    if getattr(args, "_missing", None):
        print(f"rwm-gym {args.command}: not available in this build ({args._missing} missing)", file=sys.stderr)
        return 2
    return int(importlib.import_module(args._module).run(args) or 0)


if __name__ == "__main__":
    sys.exit(main())

"""The `rwm-gym` command: one subcommand per job, each a module of `rwm_gym.commands`.

Each module listed in `COMMANDS` defines `OPTIONS` (the dataclasses its flags are generated from, one per group of
options, with `rwm_gym.options`), `add_arguments(parser)` and `run(args) -> int | None`; it is imported only when its
subcommand runs, so `rwm-gym --help` stays fast.
"""

from __future__ import annotations

import argparse
import copy
import importlib
import sys

COMMANDS: dict[str, tuple[str, str]] = {
    "spec": ("rwm_gym.commands.spec", "write a task spec for a dm_control task or a legged robot's MJCF"),
    "collect": ("rwm_gym.commands.collect", "collect episodes from a physics env into an HDF5 dataset"),
    "train": ("rwm_gym.commands.train", "train a world model (RWM or a baseline) on a dataset"),
    "evaluate": ("rwm_gym.commands.evaluate", "long-horizon prediction error of a checkpoint on a dataset"),
    "ppo": ("rwm_gym.commands.ppo", "train PPO in imagination (or physics) and evaluate it in physics"),
    "shac": ("rwm_gym.commands.shac", "train a policy by SHAC: gradients through the world model's imagined rollouts"),
    "dreamer": (
        "rwm_gym.commands.dreamer",
        "train a Dreamer-style actor-critic on lambda-returns through the world model's imagined rollouts",
    ),
    "score": (
        "rwm_gym.commands.score",
        "tracking score of a policy in physics (or a world model) beside the zero-action floor",
    ),
    "mbpo": ("rwm_gym.commands.mbpo", "MBPO-PPO loop: collect, retrain the model, PPO in imagination, repeat"),
    "make-measured": (
        "rwm_gym.commands.make_measured",
        "make 'measured' data from a simulator with a hidden physical effect",
    ),
    "gap": ("rwm_gym.commands.gap", "find, name and correct the gap between a simulator and measured data"),
    "export": ("rwm_gym.commands.export", "write a dataset as a Minari dataset (needs rwm-gym[minari])"),
    "import": ("rwm_gym.commands.import_", "read a Minari dataset written by `export` back into a dataset"),
}


class DefaultsHelpFormatter(argparse.HelpFormatter):
    """`--help` names every option's default, unless its help already does or there is none to name."""

    @staticmethod
    def _names_a_default(action: argparse.Action) -> bool:
        default = action.default
        unnamed = default is None or default is False or default == [] or default == () or default == argparse.SUPPRESS
        return bool(action.option_strings) and not unnamed

    def _format_action(self, action: argparse.Action) -> str:
        if not action.help and self._names_a_default(action):  # argparse prints nothing for an option without help
            action = copy.copy(action)
            action.help = "(default %(default)s)"
        return super()._format_action(action)

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if "default" in text or not self._names_a_default(action):
            return text
        return f"{text} (default %(default)s)".strip()


class OneLineParser(argparse.ArgumentParser):
    """An argparse parser whose errors are one line (the usage of a command with many options fills a screen):
    the option and what is wrong with its value, then where the usage is; exit status 2."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: {' '.join(message.split())} (see {self.prog} --help)\n")


def _entry(module: str, what: str):
    """The `add_arguments` or `run` function ("what") of a command module."""
    return getattr(importlib.import_module(module), what)


def build_parser(selected: str | None = None) -> argparse.ArgumentParser:
    """The parser; only the `selected` subcommand's module is imported to add its options."""
    parser = OneLineParser(prog="rwm-gym", description="Learned robot simulators as Gymnasium envs.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND", parser_class=OneLineParser)
    for name, (module, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text, formatter_class=DefaultsHelpFormatter)
        p.set_defaults(_module=module)
        if name != selected:
            continue
        try:
            _entry(module, "add_arguments")(p)
        except ModuleNotFoundError as err:
            if err.name is None or not module.startswith(err.name):
                raise
            p.set_defaults(_missing=module)
    return parser


EXIT_OK, EXIT_FAILED, EXIT_BAD_INPUT, EXIT_INTERRUPTED = 0, 1, 2, 130
"""Exit statuses of every command (docs/reference/cli.md): 2 for bad input (an option's value, an input file, an
output that cannot or may not be written), 1 for a failure while running, 130 when interrupted (Ctrl-C)."""


def main(argv: list[str] | None = None) -> int:
    """Run `rwm-gym ARGV`; the exit status (`EXIT_*`), with one line on stderr for an error.

    A bad option (the parser's one line) and what a command did not word itself (ValueError, OSError) are bad input:
    one line, 2. What a command words itself (`SystemExit` carrying its message) is printed in one line and exits 2,
    by raising it, as `sys.exit` does. Ctrl-C is 130. A command's own status stands (1: a failure while running)."""
    argv = sys.argv[1:] if argv is None else argv
    selected = next((a for a in argv if not a.startswith("-")), None)
    try:
        args = build_parser(selected).parse_args(argv)
    except SystemExit as stop:  # --help exits 0 as argparse does; a bad option is a status like any bad input
        if stop.code in (0, None):
            raise
        return int(stop.code)
    if getattr(args, "_missing", None):
        print(f"rwm-gym {args.command}: not available in this build ({args._missing} missing)", file=sys.stderr)
        return EXIT_BAD_INPUT
    try:
        return int(_entry(args._module, "run")(args) or 0)
    except SystemExit as stop:  # raise SystemExit("rwm-gym CMD: ...") in a command: its one line, exit 2
        if isinstance(stop.code, str):
            print(" ".join(stop.code.split()), file=sys.stderr)
            stop.code = EXIT_BAD_INPUT  # str(stop) keeps the message
        raise
    except KeyboardInterrupt:
        print(f"rwm-gym {args.command}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except (ValueError, OSError) as err:  # what a command did not word itself: one line, not a traceback
        text = " ".join(str(err).split()) or type(err).__name__
        print(f"rwm-gym {args.command}: {text}", file=sys.stderr)
        return EXIT_BAD_INPUT


if __name__ == "__main__":
    sys.exit(main())

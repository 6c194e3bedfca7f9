"""The `rwm-gym` subcommands: one module per command, each with `OPTIONS`, `add_arguments(parser)` and `run(args)`.

No flag is written by hand: each comes from a field of a dataclass in `OPTIONS` (the command's own, in its module;
groups several commands share, in `_options.py`; library configs such as `PPOConfig`), its docstring the help.

A command module holds the command line only (options, output guards, printing); the work is done by the library
module it names, which knows nothing of argparse. `rwm_gym.cli.COMMANDS` lists them.
"""

"""The `rwm-gym` subcommands: one module per command, each with `add_arguments(parser)` and `run(args)`.

A command module holds the command line only (options, output guards, printing); the work is done by the library
module it names, which knows nothing of argparse. `rwm_gym.cli.COMMANDS` lists them.
"""

"""The imagination flags of the commands that train in a world model (`ppo`, `mbpo`, `shac`): generated from the
fields of `ImaginationOptions`, so a flag's name, type, default and help are written once, in that dataclass."""

from __future__ import annotations

import argparse
from collections.abc import Callable, Iterable, Mapping, Sequence

from rwm_gym.imagination.options import MATMUL_PRECISION_NAMES, ImaginationOptions
from rwm_gym.options import add_dataclass_options, dataclass_from_args


def add_imagination_options(
    parser: argparse.ArgumentParser,
    *,
    skip: Iterable[str] = (),
    defaults: ImaginationOptions | None = None,
    aliases: Mapping[str, Sequence[str]] | None = None,
    types: Mapping[str, Callable[[str], object]] | None = None,
    defaults_none: bool = False,
) -> None:
    """One flag per `ImaginationOptions` field but those in `skip`, in an "imagination" group of `parser`;
    `defaults`: the command's own default options (default `ImaginationOptions()`); `defaults_none`: every flag
    defaults to None, so the flags given can be told from those left out (a recipe's values stand for the others)."""
    group = parser.add_argument_group("imagination", "how imagined episodes run (rwm_gym.ImaginationOptions)")
    add_dataclass_options(
        group,
        ImaginationOptions,
        skip=skip,
        defaults=defaults,
        aliases=aliases,
        types=types,
        defaults_none=defaults_none,
        choices={"matmul_precision": MATMUL_PRECISION_NAMES},
    )


def imagination_from_args(args: argparse.Namespace, base: ImaginationOptions | None = None) -> ImaginationOptions:
    """The options the flags of `add_imagination_options` give (a skipped field keeps `base`'s value)."""
    return dataclass_from_args(ImaginationOptions, args, base=base or ImaginationOptions())


def non_default(options: ImaginationOptions) -> dict:
    """The fields of `options` that differ from `ImaginationOptions()`: what a run records of its imagined env."""
    default = ImaginationOptions()
    return {k: v for k, v in vars(options).items() if v != getattr(default, k)}

"""`rwm-gym import`: read a Minari dataset written by `rwm-gym export` back into an rwm-gym dataset
(`rwm_gym.data.minari_io`; needs rwm-gym[minari]). The module's name has a trailing underscore: `import` is a
keyword."""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path

from rwm_gym.commands._options import OverwriteOption, add_group
from rwm_gym.data.dataset import DatasetError
from rwm_gym.data.minari_io import import_minari
from rwm_gym.options import option


@dataclass(frozen=True)
class ImportOptions:
    """The Minari dataset read and the dataset written."""

    minari: Path = option(metavar="DIR")
    """Minari dataset folder"""
    out: Path
    """rwm-gym dataset (.h5) to write"""


OPTIONS = (ImportOptions, OverwriteOption)
"""The dataclasses the flags of `rwm-gym import` come from."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `rwm-gym import`."""
    for group in OPTIONS:
        add_group(parser, group)


def run(args: argparse.Namespace) -> int:
    """`rwm-gym import`: the written file, or one line on stderr and exit 2."""
    try:
        path = import_minari(args.minari, args.out, overwrite=args.overwrite)
    except (ValueError, OSError, DatasetError) as err:
        print(f"rwm-gym import: {' '.join(str(err).split())}", file=sys.stderr)
        return 2
    print(f"wrote {path}")
    return 0

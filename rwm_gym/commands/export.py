"""`rwm-gym export`: write an rwm-gym dataset as a Minari dataset (`rwm_gym.data.minari_io`; needs rwm-gym[minari])."""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path

from rwm_gym.commands._options import OverwriteOption, add_group
from rwm_gym.data.dataset import DatasetError
from rwm_gym.data.minari_io import export_minari
from rwm_gym.options import option


@dataclass(frozen=True)
class ExportOptions:
    """The dataset exported and where."""

    minari: Path = option(metavar="DATA.h5")
    """rwm-gym dataset to export"""
    out: Path
    """folder to write the Minari dataset into"""
    dataset_id: str | None = None
    """Minari dataset id (default rwm-gym/TASK/FILE-v0)"""


OPTIONS = (ExportOptions, OverwriteOption)
"""The dataclasses the flags of `rwm-gym export` come from."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `rwm-gym export`."""
    for group in OPTIONS:
        add_group(parser, group)


def run(args: argparse.Namespace) -> int:
    """`rwm-gym export`: the written folder, or one line on stderr and exit 2."""
    try:
        path = export_minari(args.minari, args.out, dataset_id=args.dataset_id, overwrite=args.overwrite)
    except (ValueError, OSError, DatasetError) as err:
        print(f"rwm-gym export: {' '.join(str(err).split())}", file=sys.stderr)
        return 2
    print(f"wrote {path}")
    return 0

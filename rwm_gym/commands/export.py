"""`rwm-gym export`: write an rwm-gym dataset as a Minari dataset (`rwm_gym.data.minari_io`; needs rwm-gym[minari])."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from rwm_gym.data.dataset import DatasetError
from rwm_gym.data.minari_io import export_minari


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `rwm-gym export`."""
    parser.add_argument("--minari", required=True, type=Path, metavar="DATA.h5", help="rwm-gym dataset to export")
    parser.add_argument("--out", required=True, type=Path, help="folder to write the Minari dataset into")
    parser.add_argument("--dataset-id", help="Minari dataset id (default rwm-gym/TASK/FILE-v0)")
    parser.add_argument("--overwrite", action="store_true")


def run(args: argparse.Namespace) -> int:
    """`rwm-gym export`: the written folder, or one line on stderr and exit 2."""
    try:
        path = export_minari(args.minari, args.out, dataset_id=args.dataset_id, overwrite=args.overwrite)
    except (ValueError, OSError, DatasetError) as err:
        print(f"rwm-gym export: {' '.join(str(err).split())}", file=sys.stderr)
        return 2
    print(f"wrote {path}")
    return 0

"""Atomic file writes: everything the package saves goes to a temp file in the destination folder first and is then
renamed over the destination, so an interrupted save never leaves a half-written file behind."""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Callable
from pathlib import Path


def atomic_write(path: str | os.PathLike, write: Callable[[str], object]) -> Path:
    """Call `write(temp_path)`, then rename the temp file onto `path` (created with the usual umask permissions).
    Holds `path`'s lock meanwhile (`rwm_gym.output_guard.claim`) and removes temp files a killed save left."""
    from rwm_gym.output_guard import claim, remove_orphans

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with claim(path):
        remove_orphans(path, f".{path.name}.*.tmp*")
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
        os.close(fd)
        try:
            write(tmp)
            umask = os.umask(0)
            os.umask(umask)
            os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600 files; saved results are ordinary files
            os.replace(tmp, path)
        finally:
            if os.path.exists(tmp):
                os.remove(tmp)
    return path


def write_text(path: str | os.PathLike, text: str) -> Path:
    """Write `text` to `path` atomically (UTF-8); returns the path."""
    return atomic_write(path, lambda tmp: Path(tmp).write_text(text))


def write_json(path: str | os.PathLike, data: object) -> Path:
    """Write `data` as indented JSON to `path` atomically; returns the path."""
    return write_text(path, json.dumps(data, indent=2))


def save_png(fig, path: str | os.PathLike, dpi: int = 120, **savefig) -> Path:
    """Save a matplotlib figure as a PNG atomically and close it (a figure left open keeps its memory)."""
    import matplotlib.pyplot as plt

    try:
        return atomic_write(path, lambda tmp: fig.savefig(tmp, format="png", dpi=dpi, **savefig))
    finally:
        plt.close(fig)

"""Writing an SB3 policy zip so that an interrupted save never leaves a broken file behind."""

from __future__ import annotations

import os
from pathlib import Path


def save_policy(model, path: str | os.PathLike) -> Path:
    """`model.save` to a temp file in the same folder, then rename (an interrupted save leaves no broken zip)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp.zip")
    model.save(tmp)
    os.replace(tmp, path)
    return path

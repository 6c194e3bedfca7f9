"""Where the shipped task specs (`envs/`) and robot models (`assets/`) live.

In a wheel they are installed inside the package as `rwm_gym/_data/{envs,assets}`; in a source checkout they are the
top-level `envs/` and `assets/` folders. Code never builds these paths from strings elsewhere.
"""

from __future__ import annotations

from pathlib import Path

_PACKAGE = Path(__file__).resolve().parent


def _data_dir(name: str) -> Path:
    installed = _PACKAGE / "_data" / name
    if installed.is_dir():
        return installed
    checkout = _PACKAGE.parent / name
    if checkout.is_dir():
        return checkout
    raise FileNotFoundError(f"rwm_gym data folder {name!r} not found in {installed} or {checkout}")


def specs_dir() -> Path:
    """Folder of the task specs (`*.toml`)."""
    return _data_dir("envs")


def assets_dir() -> Path:
    """Folder of the robot models and shipped checkpoints."""
    return _data_dir("assets")


def shipped_file(repository_path: str) -> Path:
    """A shipped file named by its path in the repository, as the shipped JSON files record it
    ("assets/checkpoints/x.safetensors"), wherever the data folders live."""
    folder, _, rest = repository_path.partition("/")
    if folder not in ("assets", "envs") or not rest:
        raise ValueError(f"{repository_path!r} is not a path under assets/ or envs/")
    return _data_dir(folder) / rest

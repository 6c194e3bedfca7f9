"""Where the shipped task specs (`envs/`) and robot models (`assets/`) live.

In a wheel they are installed inside the package as `rwm_gym/_data/{envs,assets}`; in a source checkout they are the
top-level `envs/` and `assets/` folders. Code never builds these paths from strings elsewhere.
"""

from __future__ import annotations

import os
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


def model_file(model: str, spec_dir: str | os.PathLike | None = None, task: str = "") -> Path:
    """The MJCF file a task spec's `model` names, checked before anything opens it.

    `model` resolves inside the package's assets (`assets_dir()`, relative paths there first) or, for a spec the user
    gave as a file (`spec_dir`: that file's folder), inside the spec's own folder (the spec generator writes
    `robot.rwm.xml` beside `robot.toml`). A spec read from a dataset or checkpoint has no `spec_dir`, so it names only
    the package's own models. Absolute paths are taken only where they land in one of those folders; `..` never
    leaves them; the file must be a regular file whose includes and asset files stay in its folder
    (`rwm_gym.untrusted.check_mjcf`). ValueError (FileNotFoundError when missing), one line.
    """
    from rwm_gym.untrusted import check_mjcf

    if not model:
        raise ValueError(f"task {task or '?'}: names no MJCF model (its simulator ships its own)")
    roots = [assets_dir()] + ([Path(spec_dir)] if spec_dir is not None else [])
    given = Path(model)
    candidates = [given] if given.is_absolute() else [root / given for root in roots]
    allowed = [root.resolve() for root in roots]
    inside = [c for c in candidates if any(c.resolve().is_relative_to(root) for root in allowed)]
    where = "rwm-gym's assets" + (f" or the spec's folder {spec_dir}" if spec_dir is not None else "")
    if not inside:
        raise ValueError(
            f"task {task or '?'}: model {model!r} lies outside {where}; a spec names only those models "
            "(one read from a dataset or checkpoint: only the package's own)"
        )
    path = next((c for c in inside if c.exists()), None)
    if path is None:
        raise FileNotFoundError(f"task {task or '?'}: model {model!r} not found in {where}")
    check_mjcf(path)
    return path

"""What every writing command checks before it starts, so a run never destroys an input or another run's result.

`check_output` refuses (one line, `OutputError`) an output that is one of the command's inputs, lies inside an input
folder or holds an input, exists without `overwrite`, or cannot be written (checked before a long run, not after it).
`check_folder` does the same for an output folder, which a command writes into only to continue its own run or with
`overwrite`. `claim` holds an exclusive lock on the output for the whole run: a second run writing the same path
fails at once; a folder it made for the lock and that stays empty (a run refused before writing) is removed again.
The lock is a `flock` on a hidden `.NAME.lock` file beside the output, released by the kernel if the process dies,
so a killed run never blocks the next one.
"""

from __future__ import annotations

import errno
import fcntl
import os
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path


class OutputError(ValueError):
    """An output a command refuses to write (one line)."""


def resolved(path: str | os.PathLike) -> Path:
    """The absolute path with links resolved, so two spellings of one file compare equal."""
    return Path(path).expanduser().resolve()


def _clash(out: Path, source: Path) -> str | None:
    """How writing `out` would touch the input `source`, or None."""
    if out == source or (out.exists() and source.exists() and os.path.samefile(out, source)):
        return "is"
    if source in out.parents:
        return "is inside"
    if out in source.parents:
        return "holds"
    return None


def check_output(
    out: str | os.PathLike,
    *,
    inputs: Iterable[str | os.PathLike | None] = (),
    overwrite: bool = False,
    folder: bool = False,
    flag: str = "--out",
) -> Path:
    """The resolved `out` (a file, or a folder if `folder`), after refusing what would destroy data or fail only at
    the end of the run."""
    path = resolved(out)
    for source in inputs:
        if source is None or str(source) in ("", "-"):
            continue
        how = _clash(path, resolved(source))
        if how is not None:
            raise OutputError(f"{flag} {out} {how} the input {source}: write the result elsewhere")
    if path.is_dir() != folder and path.exists():
        raise OutputError(
            f"{flag} {out} is a {'file' if folder else 'folder'}; give the path of a {'folder' if folder else 'file'}"
        )
    if path.exists() and not overwrite:
        raise OutputError(f"{flag} {out} exists (pass --overwrite to replace it)")
    parent = next(p for p in (path.parent, *path.parent.parents) if p.exists())
    if not parent.is_dir():
        raise OutputError(f"{flag} {out}: {parent} is a file, not a folder")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise OutputError(f"{flag} {out}: cannot write in {parent} (permission denied)")
    return path


def check_folder(
    folder: str | os.PathLike,
    *,
    inputs: Iterable[str | os.PathLike | None] = (),
    overwrite: bool = False,
    continues: bool = False,
    flag: str = "--out",
) -> Path:
    """The resolved output folder `folder` (a run folder or a report folder), after `check_output`'s checks: a folder
    that already holds files is written into only if the command `continues` the run it holds (its own resume point)
    or with `overwrite`."""
    path = check_output(folder, inputs=inputs, overwrite=True, folder=True, flag=flag)
    if path.is_dir() and not continues and not overwrite and any(path.iterdir()):
        raise OutputError(f"{flag} {folder} holds files and no run to continue (pass --overwrite to write over them)")
    return path


_HELD: dict[Path, list[int]] = {}
"""Locks this process holds: path -> [fd, depth] (a writer nested in a command claims the same path again)."""

_MADE: dict[Path, list[Path]] = {}
"""Folders a claim created for its lock, deepest first: removed again if still empty when the claim ends, so a run
refused after its claim leaves no empty output folder behind."""


def lock_path(out: Path) -> Path:
    """The lock file beside `out` that a run holds while it writes `out`."""
    return out.with_name(f".{out.name}.lock")


@contextmanager
def claim(out: str | os.PathLike) -> Iterator[Path]:
    """Hold an exclusive lock on `out` for the block; OutputError at once if another process is writing it. Within
    one process claims nest (a command's writer claims the path its command holds); the last to leave releases."""
    path = resolved(out)
    if path not in _HELD:
        made = [p for p in (path.parent, *path.parent.parents) if not p.exists()]
        path.parent.mkdir(parents=True, exist_ok=True)
        try:
            _HELD[path] = [_lock(lock_path(path), out), 0]
        except BaseException:
            _remove_empty(made)
            raise
        _MADE[path] = made
    _HELD[path][1] += 1
    try:
        yield path
    finally:
        _HELD[path][1] -= 1
        if _HELD[path][1] == 0:
            fd = _HELD.pop(path)[0]
            try:
                os.remove(lock_path(path))
            except OSError:
                pass
            os.close(fd)
            _remove_empty(_MADE.pop(path, []))


@contextmanager
def no_empty_folder(folder: str | os.PathLike) -> Iterator[None]:
    """For a command whose output is a folder it creates: if the block fails, the folder (and the parents made with
    it) is removed again where it is still empty, so a refused run leaves nothing behind."""
    path = resolved(folder)
    made = [p for p in (path, *path.parents) if not p.exists()]
    try:
        yield
    except BaseException:
        _remove_empty(made)
        raise


def _remove_empty(folders: list[Path]) -> None:
    """Remove each of `folders` (deepest first) that is empty; stop at the first that is not."""
    for folder in folders:
        try:
            folder.rmdir()
        except OSError:
            return


def _lock(lock: Path, out: str | os.PathLike) -> int:
    """An fd holding the flock of `lock`; the file a finishing run unlinks is not the one the next run locks."""
    while True:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as err:
            os.close(fd)
            if err.errno in (errno.EAGAIN, errno.EACCES):
                raise OutputError(
                    f"{out} is being written by another run (lock {lock}); wait for it or write elsewhere"
                ) from None
            raise
        try:
            if os.stat(lock).st_ino == os.fstat(fd).st_ino:
                return fd
        except FileNotFoundError:
            pass
        os.close(fd)  # the holder removed the file between our open and our lock: lock the new one


def remove_orphans(out: Path, pattern: str) -> None:
    """Delete temp files beside `out` (`pattern`, a glob) left by a killed run; call while holding `claim(out)`."""
    for orphan in out.parent.glob(pattern):
        try:
            orphan.unlink()
        except OSError:
            pass

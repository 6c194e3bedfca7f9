"""Checks every reader of a file someone else wrote applies before it opens, inflates or allocates anything.

A file handed to rwm-gym (a policy zip, a dataset, a checkpoint, a task spec and its model) is data: reading it must
not run code from it, read another file it names, wait forever on a pipe, or let a few kilobytes ask for gigabytes.
The readers call these helpers; each refusal is a `ValueError` (or `FileNotFoundError`) of one line naming the file.
"""

from __future__ import annotations

import os
import stat
import zipfile
from pathlib import Path

ZIP_RATIO_LIMIT = 200
"""Most a zip member may inflate (uncompressed / compressed bytes) once it is over `ZIP_SMALL_BYTES`; deflate reaches
about 1000 only on runs of one byte, real weights and JSON stay well below 20."""
ZIP_SMALL_BYTES = 1 << 20
"""Members up to 1 MiB may inflate by any ratio."""


def memory_cap_bytes() -> int:
    """Most one file may ask to hold in memory: half of this machine's physical memory (8 GiB where unknown)."""
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") // 2
    except (ValueError, OSError, AttributeError):
        return 8 << 30


def regular_file(path: str | os.PathLike, what: str = "file") -> Path:
    """`path` if it is a regular file (links followed); otherwise one line: missing, a folder, or a FIFO, socket or
    device, which opening could block on or read without end."""
    path = Path(path)
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        raise FileNotFoundError(f"{what} {path}: no such file") from None
    except OSError as err:
        raise ValueError(f"{what} {path}: cannot be read ({err.strerror or type(err).__name__})") from None
    if stat.S_ISDIR(mode):
        raise IsADirectoryError(f"{what} {path}: is a folder, not a file")
    if not stat.S_ISREG(mode):
        kind = "a FIFO" if stat.S_ISFIFO(mode) else "a socket" if stat.S_ISSOCK(mode) else "a device"
        raise ValueError(f"{what} {path}: is {kind}, not a regular file; rwm-gym reads only regular files")
    return path


def read_zip_member(archive: zipfile.ZipFile, info: zipfile.ZipInfo, limit: int) -> bytes:
    """The bytes of one member, refused (ValueError naming it) before inflating when its declared size is over
    `limit` or it would inflate more than `ZIP_RATIO_LIMIT`, and read with a bound so a member that inflates past
    its declared size stops there."""
    declared = info.file_size
    if declared > limit:
        raise ValueError(f"member {info.filename!r} declares {declared} bytes, over the {limit}-byte limit")
    if declared > ZIP_SMALL_BYTES and declared > ZIP_RATIO_LIMIT * max(info.compress_size, 1):
        raise ValueError(
            f"member {info.filename!r} would inflate {info.compress_size} bytes to {declared} "
            f"(over {ZIP_RATIO_LIMIT} times): a zip bomb, not a policy"
        )
    chunks, size = [], 0
    with archive.open(info) as member:
        while chunk := member.read(min(1 << 20, declared - size + 1)):
            size += len(chunk)
            if size > declared:
                raise ValueError(f"member {info.filename!r} inflates past its declared {declared} bytes")
            chunks.append(chunk)
    return b"".join(chunks)


MJCF_LIMIT_BYTES = 64 << 20
"""Largest MJCF file (model or include) read."""
_MJCF_DIRS = ("meshdir", "texturedir", "assetdir")


def check_mjcf(path: str | os.PathLike, *, max_files: int = 64) -> None:
    """Refuse (one line) an MJCF that pulls in XML from outside its own folder or names a file that is not a regular
    file, read before MuJoCo opens anything: every `<include file=...>` (read recursively) and `<model file=...>`
    must be a relative path that stays in the model's folder (links followed); every file read must be a regular
    file under `MJCF_LIMIT_BYTES`. Asset files (meshes, textures, height fields, skins) may lie elsewhere (a
    generated copy points at its robot's meshes with an absolute `meshdir`), but must be regular files: a FIFO would
    block MuJoCo."""
    import xml.etree.ElementTree as ElementTree

    main = Path(path)
    root = main.parent.resolve()
    queue, seen, dirs = [main], set(), {}

    def xml_inside(value: str, what: str, where: Path) -> Path:
        relative = Path(value)
        if relative.is_absolute():
            raise ValueError(f"MJCF {where}: {what} {value!r} is an absolute path; a model includes only its own files")
        candidates = [(base / relative).resolve() for base in (root, where.parent.resolve())]
        if not all(c.is_relative_to(root) for c in candidates):
            raise ValueError(f"MJCF {where}: {what} {value!r} leads out of the model's folder {root}")
        return next((c for c in candidates if c.exists()), candidates[0])

    def asset_files(tag: str, value: str) -> list[Path]:
        own = {"mesh": "meshdir", "texture": "texturedir"}.get(tag, "assetdir")
        folder = dirs.get(own, dirs.get("assetdir"))
        bases = [root / folder] if folder else []
        return [base / value for base in [*bases, root]] if not Path(value).is_absolute() else [Path(value)]

    while queue:
        current = queue.pop(0)
        if len(seen) >= max_files:
            raise ValueError(f"MJCF {main}: includes more than {max_files} files")
        seen.add(current)
        regular_file(current, "MJCF")
        if current.stat().st_size > MJCF_LIMIT_BYTES:
            raise ValueError(f"MJCF {current}: over {MJCF_LIMIT_BYTES >> 20} MiB")
        try:
            tree = ElementTree.parse(current)
        except ElementTree.ParseError as err:
            raise ValueError(f"MJCF {current}: not readable XML ({err})") from None
        for element in tree.iter("compiler"):
            dirs.update({k: v for k, v in element.attrib.items() if k in _MJCF_DIRS})
        for element in tree.iter():
            for name, value in element.attrib.items():
                if not name.startswith("file"):
                    continue
                if element.tag in ("include", "model"):
                    target = xml_inside(value, f"<{element.tag} {name}>", current)
                    if target not in seen:
                        queue.append(target)
                    continue
                for candidate in asset_files(element.tag, value):
                    if candidate.exists():
                        regular_file(candidate, f"MJCF {current}: <{element.tag} {name}>")
                        break

"""An HDF5 file holds its own data: checks made before reading one that someone else wrote.

HDF5 lets a dataset keep its bytes in other files (external raw storage: `dataset.external`), a link point into another
file (`h5py.ExternalLink`), a virtual dataset map regions of other files (`dataset.is_virtual`), and a chunked dataset
declare any shape while storing nothing, which reading fills in. A filter id names a plugin that HDF5 loads from the
plugin path. Each could make reading a dataset read a file it names (`/etc/passwd`), load a library, or allocate
gigabytes from kilobytes. `check_self_contained` walks every link and dataset of an open file and refuses all of them
before a value is read, in one line naming the file and field.
"""

from __future__ import annotations

import os
from pathlib import Path

import h5py

from rwm_gym.untrusted import memory_cap_bytes

COMPRESSION_BOUND = 1100
"""Most a dataset's bytes may exceed the whole file's size: deflate inflates at most about 1032 times."""
SMALL_BYTES = 16 << 20
"""A dataset of up to 16 MiB passes the compression bound whatever the file's size."""
FILTERS = {
    h5py.h5z.FILTER_DEFLATE,
    h5py.h5z.FILTER_SHUFFLE,
    h5py.h5z.FILTER_FLETCHER32,
    h5py.h5z.FILTER_SZIP,
    h5py.h5z.FILTER_NBIT,
    h5py.h5z.FILTER_SCALEOFFSET,
    h5py.h5z.FILTER_LZF,
}
"""Filters built into HDF5 or h5py; any other id would make HDF5 look for a plugin library to load."""


class NotSelfContainedError(ValueError):
    """An HDF5 file that refers to other files or declares more data than it can hold (one line)."""


def _field(name: str) -> str:
    return name.removeprefix("steps/")


def check_self_contained(
    f: h5py.File, path: str | os.PathLike, error: type[ValueError] = NotSelfContainedError
) -> None:
    """Refuse (raise `error`, one line naming `path` and the field) external links, links of unknown kinds, external
    raw storage, virtual datasets, filters that would load a plugin, and datasets declaring more bytes than the file
    could inflate to (`COMPRESSION_BOUND`) or, all together, more than half the machine's memory."""
    path = Path(path)
    links: list[tuple[str, object]] = []
    f.visititems_links(lambda name, link: links.append((name, link)))
    for name, link in links:
        if isinstance(link, h5py.ExternalLink):
            raise error(
                f"{path}: field '{_field(name)}': links to {link.path!r} in the file {link.filename!r}; "
                "a dataset must hold its own data"
            )
        if not isinstance(link, (h5py.HardLink, h5py.SoftLink)):
            raise error(f"{path}: field '{_field(name)}': a link of unknown kind; a dataset must hold its own data")
    limit, total = os.path.getsize(path) * COMPRESSION_BOUND + SMALL_BYTES, 0
    for name, link in links:
        if not isinstance(link, h5py.HardLink):
            continue  # a soft link names a path in this file, and every link here was checked above
        item = f.get(name)
        if not isinstance(item, h5py.Dataset):
            continue
        where = f"{path}: field '{_field(name)}'"
        if item.external:
            raise error(f"{where}: its data lie in another file ({item.external[0][0]!r}); datasets are self-contained")
        if item.is_virtual:
            raise error(f"{where}: a virtual dataset mapping other files; datasets are self-contained")
        plist = item.id.get_create_plist()
        for i in range(plist.get_nfilters()):
            code = plist.get_filter(i)[0]
            if code not in FILTERS:
                raise error(f"{where}: compressed with filter {code}, which would load a plugin; rwm-gym reads none")
        declared = int(item.size) * item.dtype.itemsize
        if declared > limit:
            raise error(
                f"{where}: declares {declared / 2**20:.0f} MiB of data in a file of "
                f"{os.path.getsize(path) / 2**20:.1f} MiB (more than any compression holds)"
            )
        total += declared
        if total > memory_cap_bytes():
            raise error(f"{where}: the fields declare {total / 2**30:.1f} GiB, over half of this machine's memory")

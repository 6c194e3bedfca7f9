"""Writing an SB3 policy zip so that an interrupted save never leaves a broken file behind."""

from __future__ import annotations

import json
import os
import zipfile
from pathlib import Path

from rwm_gym.atomic import atomic_write


def save_policy(model, path: str | os.PathLike) -> Path:
    """`model.save` to a temp file in the same folder, then rename (an interrupted save leaves no broken zip)."""

    def write(tmp: str) -> None:
        try:
            model.save(tmp + ".zip")  # SB3 adds ".zip" to a name without it
            os.replace(tmp + ".zip", tmp)
        finally:  # a failed save (a full disk) leaves no half-written .tmp.zip beside the policy
            if os.path.exists(tmp + ".zip"):
                os.remove(tmp + ".zip")

    return atomic_write(path, write)


# Per-run state in an SB3 zip's `data`: the last observations of every training env (1 MB at 4096 envs) and episode
# statistics. A policy handed to users does not need it; loading sets only what the file holds.
RUN_STATE_KEYS = ("_last_obs", "_last_episode_starts", "_last_original_obs", "ep_info_buffer", "ep_success_buffer")


def compact_policy(src: str | os.PathLike, dst: str | os.PathLike, *, overwrite: bool = False) -> Path:
    """Copy an SB3 policy zip without its training envs' run state (`RUN_STATE_KEYS`): the weights, the optimizer and
    every setting stay, so it loads and predicts exactly as before (training on starts from fresh env resets).
    Rewrites the zip's JSON entry only (nothing in the file is unpickled); refuses to overwrite `dst` unless asked."""
    src, dst = Path(src), Path(dst)
    if dst.exists() and not overwrite:
        raise FileExistsError(f"{dst} exists (pass overwrite=True to replace it)")
    from rwm_gym.untrusted import memory_cap_bytes, read_zip_member, regular_file

    regular_file(src, "policy")
    with zipfile.ZipFile(src) as archive:  # each member capped by its declared size and ratio before inflating
        entries = {info: read_zip_member(archive, info, memory_cap_bytes() // 4) for info in archive.infolist()}
    if not any(info.filename == "data" for info in entries):
        raise ValueError(f"{src} is not an SB3 policy zip (no 'data' entry)")

    def write(tmp: str) -> None:
        with zipfile.ZipFile(tmp, "w") as out:
            for info, payload in entries.items():
                if info.filename == "data":
                    data = json.loads(payload)
                    payload = json.dumps({k: v for k, v in data.items() if k not in RUN_STATE_KEYS}, indent=4)
                out.writestr(info, payload)

    return atomic_write(dst, write)

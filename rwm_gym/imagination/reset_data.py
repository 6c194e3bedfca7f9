"""Real history windows that imagined episodes start from.

An imagined episode replays the last H steps of a real trajectory through the world model before the policy acts
(RWM's warm-up: a cold GRU state predicts poorly). The windows come from a small dataset in the ordinary HDF5 format,
named by the checkpoint (`extras["reset_data"]`, relative to the checkpoint's folder) or given by the user.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from rwm_gym.data.dataset import Dataset, DatasetInfo, write_dataset
from rwm_gym.data.lineage import SOURCES_KEY, physics_sources


@dataclass
class ResetWindow:
    """One real history: H rows ending at the row the imagined episode continues from."""

    states: np.ndarray
    """(H, S) physical units, rows t-H+1 .. t."""
    actions: np.ndarray
    """(H - 1, A) actions of rows t-H+1 .. t-1 (the policy picks the action of row t)."""
    contact: np.ndarray
    """(C,) bool, contact flags at row t."""
    foot_height: np.ndarray
    """(F,) m, at row t."""


class ResetWindows:
    """All windows of `history` rows that fit inside one episode of a dataset, sampled uniformly."""

    def __init__(self, dataset: Dataset, history: int):
        self.dataset, self.history = dataset, history
        starts, lengths = dataset.episode_starts, dataset.episode_lengths
        # row t can end a window if t - history + 1 >= episode start and row t is not a terminal state
        ends = [np.arange(s + history - 1, s + n) for s, n in zip(starts, lengths) if n >= history]
        self.ends = np.concatenate(ends) if ends else np.zeros(0, dtype=np.int64)
        self.ends = self.ends[~dataset["terminated"][self.ends]]
        if len(self.ends) == 0:
            raise ValueError(f"{dataset.path}: no episode has the {history} rows a reset window needs")
        self.states, self.actions = dataset["state"], dataset["action"]
        self.contact, self.foot_height = dataset["contact"], dataset["foot_height"]

    def sample(self, rng: np.random.Generator) -> ResetWindow:
        t = self.draw(rng)
        rows = slice(t - self.history + 1, t + 1)
        return ResetWindow(
            self.states[rows], self.actions[t - self.history + 1 : t], self.contact[t], self.foot_height[t]
        )

    def draw(self, rng: np.random.Generator) -> int:
        """The last row of a uniformly drawn window (one draw from `rng`, the same `sample` makes)."""
        return int(self.ends[rng.integers(len(self.ends))])

    def gather(self, ends: np.ndarray) -> ResetWindow:
        """The windows ending at rows `ends` (n,), stacked in one gather: states (n, H, S), actions (n, H - 1, A),
        contact (n, C), foot_height (n, F)."""
        rows = ends[:, None] + np.arange(1 - self.history, 1)
        return ResetWindow(self.states[rows], self.actions[rows[:, :-1]], self.contact[ends], self.foot_height[ends])


class WarmUpCache:
    """The model's hidden state after each window's warm-up, computed the first time the window is drawn and reused:
    a restart then costs a gather instead of H - 1 GRU steps (on short imagined episodes the warm-ups are a third of
    the work or more). For models whose warm-up ignores the ensemble member (`warm_hidden_reads_member` False); the
    storage, (windows, hidden size) floats, is reserved only if it fits in `max_bytes`.

    A warm-up is H - 1 sequential GRU steps, so a call costs about the same for 1 window as for 30: filling the cache
    one restart at a time kept a call on most steps of 1024 envs for the first hundred rollouts. Each call that
    misses therefore also warms up `prefetch` windows not drawn yet (the first in index order), and the cache fills
    in a few calls.
    """

    def __init__(self, windows: ResetWindows, template: tuple[torch.Tensor, ...], prefetch: int = 0):
        """template: a hidden state of batch 1 (its shapes, dtype and device); prefetch: extra windows per miss."""
        self.windows, self.prefetch = windows, prefetch
        count = len(windows.ends)
        self.hidden = tuple(torch.empty((count, *h.shape[1:]), dtype=h.dtype, device=h.device) for h in template)
        self.filled = torch.zeros(count, dtype=torch.bool, device=template[0].device)

    @staticmethod
    def nbytes(windows: ResetWindows, template: tuple[torch.Tensor, ...]) -> int:
        return len(windows.ends) * sum(h[0].numel() * h.element_size() for h in template)

    def get(
        self, ends: np.ndarray, compute: Callable[[np.ndarray], tuple[torch.Tensor, ...]]
    ) -> tuple[torch.Tensor, ...]:
        """The warm hidden states of the windows ending at rows `ends`; `compute(ends)` warms up the ones not cached
        yet and the `prefetch` next (each once, in one batch)."""
        slots = torch.as_tensor(np.searchsorted(self.windows.ends, ends), device=self.filled.device)
        missing = torch.unique(slots[~self.filled[slots]])
        if missing.numel():
            if self.prefetch:
                pending = ~self.filled
                pending[missing] = False
                ahead = pending.nonzero().squeeze(1)[: self.prefetch]
                missing = torch.cat([missing, ahead])
            for cached, value in zip(self.hidden, compute(self.windows.ends[missing.cpu().numpy()]), strict=True):
                cached[missing] = value.to(cached.dtype)
            self.filled[missing] = True
        return tuple(cached[slots] for cached in self.hidden)


def make_reset_data(
    source: Dataset | str | Path, out: str | Path, *, episodes: int = 32, rows: int = 200, seed: int = 0
) -> Path:
    """Cut a small reset dataset (`episodes` episodes, at most `rows` rows each) out of a collected one."""
    ds = source if isinstance(source, Dataset) else Dataset.load(source)
    rng = np.random.default_rng(seed)
    chosen = np.sort(rng.permutation(ds.num_episodes)[:episodes])

    def cut(i: int) -> dict[str, np.ndarray]:
        ep = {k: v.copy() for k, v in ds.episode(int(i)).items()}
        if len(ep["state"]) > rows:
            ep = {k: v[:rows] for k, v in ep.items()}
            ep["action"][-1], ep["reward"][-1] = 0.0, 0.0
            ep["terminated"][-1], ep["truncated"][-1] = False, True
        return ep

    sha256 = ds.file_hash()
    metadata = {**ds.info.metadata, "reset_data_from": str(ds.path), "sha256": sha256}
    metadata[SOURCES_KEY] = physics_sources(ds, sha256)  # a cut holds rows of its source, no new ones
    info = DatasetInfo(**{**_info_fields(ds.info), "metadata": metadata})
    write_dataset(out, info, (cut(i) for i in chosen))
    return Path(out)


def _info_fields(info: DatasetInfo) -> dict:
    return {k: getattr(info, k) for k in ("env_id", "spec_text", "dt", "columns", "policy", "seed", "physics_params")}

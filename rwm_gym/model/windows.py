"""Training and evaluation windows: runs of consecutive rows inside one episode, gathered as normalised tensors.

A window of `rows` rows starting at row r of an episode holds rows r..r+rows-1; with the dataset's layout (an episode
of L transitions has L+1 rows) it fits when r + rows <= L + 1, so no window ever crosses into the next episode.
A training window has rows = history + forecast: the model warms up on rows 0..H-1 and predicts rows H..H+F-1
with actions 0..H+F-2 (the last row's action is never used).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields

import numpy as np
import torch

from rwm_gym.data.dataset import Dataset
from rwm_gym.model.normalization import Normalizer
from rwm_gym.spec import TaskSpec


@dataclass
class Window:
    """A batch of windows, batch first: (B, rows, ...) tensors, normalised."""

    states: torch.Tensor
    """(B, R, S) normalised states."""
    actions: torch.Tensor
    """(B, R, A) actions applied in each row's state."""
    contacts: torch.Tensor
    """(B, R, C) contact flags as 0/1 floats."""
    foot_heights: torch.Tensor
    """(B, R, F) foot heights / foot_height_std."""
    terminated: torch.Tensor
    """(B, R) 1 where the row is a terminal state."""

    def map(self, fn: Callable[[torch.Tensor], torch.Tensor]) -> Window:
        """A Window with `fn` applied to every tensor (e.g. picking rows)."""
        return Window(*(fn(getattr(self, f.name)) for f in fields(self)))


class WindowMirror:
    """The left-right mirror image of windows (the spec's `[symmetry]`): states through the state mirror, in
    normalised units (an affine map of the normalised state), actions through the action mirror, contact flags and
    foot heights with their bodies' sides swapped. A symmetric robot's mirrored window is as true as the window."""

    def __init__(self, spec: TaskSpec, normalizer: Normalizer, device: torch.device | str = "cpu") -> None:
        from rwm_gym.task.symmetry import action_mirror, contact_mirror, foot_mirror, state_mirror

        state, action = state_mirror(spec), action_mirror(spec)
        mean, std = normalizer.state_mean, normalizer.state_std
        # physical x' = sign * x[index]; normalised n' = n[index] * scale + offset
        scale = state.sign * std[state.index] / std
        offset = (state.sign * mean[state.index] - mean) / std

        def tensor(array: np.ndarray, dtype=torch.float32) -> torch.Tensor:
            return torch.as_tensor(np.asarray(array), dtype=dtype, device=device)

        self.state_index, self.state_scale = tensor(state.index, torch.long), tensor(scale)
        self.state_offset = tensor(offset)
        self.action_index, self.action_sign = tensor(action.index, torch.long), tensor(action.sign)
        self.contact_index = tensor(contact_mirror(spec), torch.long)
        self.foot_index = tensor(foot_mirror(spec), torch.long)

    def __call__(self, window: Window, flip: torch.Tensor) -> Window:
        """`window` with the windows where `flip` (B,) bool is set replaced by their mirror images."""
        mirrored = Window(
            window.states[..., self.state_index] * self.state_scale + self.state_offset,
            window.actions[..., self.action_index] * self.action_sign,
            window.contacts[..., self.contact_index],
            window.foot_heights[..., self.foot_index],
            window.terminated,
        )
        pick = flip.to(window.states.device)

        def choose(mine: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
            return torch.where(pick.view(-1, *([1] * (mine.dim() - 1))), image, mine)

        return Window(*(choose(getattr(window, f.name), getattr(mirrored, f.name)) for f in fields(Window)))


class WindowData:
    """All rows of a dataset as normalised tensors on one device, indexed by episode."""

    def __init__(self, dataset: Dataset, normalizer: Normalizer, device: torch.device | str = "cpu") -> None:
        def tensor(array: np.ndarray) -> torch.Tensor:
            return torch.as_tensor(np.asarray(array, dtype=np.float32), device=device)

        self.path = dataset.path
        self.states = tensor(normalizer.normalize_state(dataset["state"].astype(np.float64)))
        self.actions = tensor(dataset["action"])
        self.contacts = tensor(dataset["contact"])
        self.foot_heights = tensor(normalizer.normalize_foot_height(dataset["foot_height"].astype(np.float64)))
        self.terminated = tensor(dataset["terminated"])
        self.episode_starts = np.asarray(dataset.episode_starts, dtype=np.int64)
        self.episode_rows = np.asarray(dataset.episode_lengths, dtype=np.int64)
        last_rows = np.zeros(len(self.states), dtype=np.int64)
        for start, count in zip(self.episode_starts, self.episode_rows):
            last_rows[start : start + count] = start + count - 1
        self.last_row = torch.as_tensor(last_rows, device=device)
        """(N,) long: the last row of the episode each row belongs to."""

    def window_starts(self, episodes: Sequence[int] | np.ndarray, rows: int) -> torch.Tensor:
        """Global first rows (n,) long of every window of `rows` rows lying wholly inside one of `episodes`."""
        starts = [self.episode_starts[e] + np.arange(self.episode_rows[e] - rows + 1) for e in episodes]
        flat = np.concatenate(starts) if starts else np.zeros(0, dtype=np.int64)
        return torch.as_tensor(flat.astype(np.int64), device=self.states.device)

    def gather(self, starts: torch.Tensor, rows: int) -> Window:
        """The windows beginning at `starts` (B,) long, `rows` rows each."""
        index = starts.to(self.states.device).unsqueeze(1) + torch.arange(rows, device=self.states.device)
        return Window(
            self.states[index],
            self.actions[index],
            self.contacts[index],
            self.foot_heights[index],
            self.terminated[index],
        )

    def gather_clipped(self, starts: torch.Tensor, rows: int) -> tuple[Window, torch.Tensor]:
        """Segments of `rows` rows beginning at `starts` (B,) long that may run past their episode's end: rows beyond
        it repeat the episode's last row. Returns the windows and (B,) long the number of real rows of each."""
        starts = starts.to(self.states.device)
        last = self.last_row[starts]
        index = torch.minimum(starts.unsqueeze(1) + torch.arange(rows, device=starts.device), last.unsqueeze(1))
        real = (last - starts + 1).clamp(max=rows)
        return Window(
            self.states[index],
            self.actions[index],
            self.contacts[index],
            self.foot_heights[index],
            self.terminated[index],
        ), real

    def termination_pos_weight(self, episodes: Sequence[int] | np.ndarray) -> float:
        """Negatives per positive of the termination flag over the rows of `episodes` that can be predicted (all
        but each episode's first), clipped to [1, 1000]; 1 when no episode terminates."""
        flags = np.concatenate(
            [
                self.terminated[s + 1 : s + r].cpu().numpy()
                for s, r in zip(self.episode_starts[episodes], self.episode_rows[episodes])
            ]
        )
        positives = float(flags.sum())
        if positives == 0:
            return 1.0
        return float(np.clip((len(flags) - positives) / positives, 1.0, 1000.0))

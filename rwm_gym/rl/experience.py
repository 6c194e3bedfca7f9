"""A training run's experience as world-model data: the episodes of a subset of a batched physics core's envs.

RWM pretrains its world model on the experience of the PPO run that learnt the task in simulation, so the model sees
the states a learning policy visits, from the first stumbles to the final gait. `RecordingCore` wraps the batched core
that PPO trains on and writes every finished episode of every `every`-th env to an HDF5 dataset
(`rwm_gym.data.dataset`), flushed per episode, with the PPO iteration that chose each action as the per-step field
`ppo_iteration`. Recording does not change what the policy sees or the random streams of the envs.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from rwm_gym.data.collect import ROW_FIELDS, dataset_columns, stack_episode
from rwm_gym.data.dataset import DatasetInfo, DatasetWriter


class RecordingCore:
    """A batched physics core whose envs `0, every, 2 * every, ...` have their episodes written to `path`.

    Behaves as the wrapped core (attributes pass through). Set `iteration` before each PPO rollout. `close()` marks the
    file complete; a killed run leaves every finished episode readable (the writer flushes per episode).
    """

    def __init__(
        self, core, path: str | Path, *, every: int = 8, policy: str = "ppo", seed: int = 0, overwrite: bool = False
    ):
        if every < 1:
            raise ValueError(f"record every {every}-th env: must be >= 1")
        self.core = core
        self.recorded = np.arange(0, core.num_envs, every)
        spec = core.spec
        info = DatasetInfo(
            env_id=spec.physics_env_id,
            spec_text=spec.text,
            dt=spec.policy_dt,
            columns=dataset_columns(core),
            policy=policy,
            seed=seed,
            physics_params=core.params.to_dict(),
            metadata={"source": "PPO training experience", "record_every_env": every},
        )
        self.writer = DatasetWriter(path, info, overwrite=overwrite, in_place=True)  # a killed run resumes from it
        self.iteration = 0
        self._rows: dict[int, list[dict]] = {}

    def __getattr__(self, name):
        return getattr(self.core, name)

    @property
    def episodes_written(self) -> int:
        return self.writer.num_episodes

    def _start(self, ids: np.ndarray) -> None:
        record = self.core.record()
        for i in np.intersect1d(ids, self.recorded):
            self._rows[int(i)] = [{f: record[f][i] for f in ROW_FIELDS}]

    def reset(
        self, ids: np.ndarray, seeds: Sequence[int | None] | None = None, commands: np.ndarray | None = None
    ) -> np.ndarray:
        obs = self.core.reset(ids, seeds, commands)
        self._start(np.asarray(ids))
        return obs

    def step(self, actions: np.ndarray):
        obs, reward, terminated, truncated, info = self.core.step(actions)
        record = self.core.record()
        applied = np.clip(actions, -1.0, 1.0)
        for i, rows in self._rows.items():
            rows[-1].update(action=applied[i], reward=reward[i], ppo_iteration=self.iteration)
            rows.append({f: record[f][i] for f in ROW_FIELDS})
            if terminated[i] or truncated[i]:
                rows[-1]["truncated"] = bool(truncated[i])
                self.writer.append_episode(_episode(rows, self.core.spec.action_dim))
        for i in [i for i in self._rows if terminated[i] or truncated[i]]:
            del self._rows[i]  # restarted by the caller's reset
        return obs, reward, terminated, truncated, info

    def close(self) -> None:
        """Mark the dataset complete (unfinished episodes are dropped)."""
        self.writer.close()


def _episode(rows: list[dict], action_dim: int) -> dict[str, np.ndarray]:
    """Dataset arrays of buffered rows with each row's PPO iteration (the last row repeats its predecessor's)."""
    iterations = [r.get("ppo_iteration", rows[-2]["ppo_iteration"] if len(rows) > 1 else 0) for r in rows]
    episode = stack_episode(rows, action_dim)
    episode["ppo_iteration"] = np.asarray(iterations, dtype=np.int32)
    return episode

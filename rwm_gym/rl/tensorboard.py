"""TensorBoard for SB3 PPO runs (`rwm-gym ppo` and `rwm-gym mbpo --tensorboard DIR`): SB3's own scalars, and beside
them what the env's infos say about each rollout.

`tensorboard_logger(DIR)` is SB3's logger writing TensorBoard event files into DIR; `model.set_logger(...)` sends
SB3's own `train/*`, `rollout/*` and `time/*` scalars there. `RolloutScalars`, a callback, gathers the infos of every
step of a rollout and records into the same logger at the rollout's end, so SB3 writes them with its own, at the step
`num_timesteps`:

- `reward/<term>`: the mean of each reward term over the rollout's env-steps (the infos' `reward/<term>`, before
  weight and dt);
- `episode/length`, `episode/return`, `episode/count`: the episodes that ended in the rollout (mean length in policy
  steps, mean sum of rewards, how many); SB3's `rollout/ep_*_mean` average the last 100 instead;
- `termination/<flag>`: the share of envs for which the flag fired at least once in the rollout, for each of the
  imagined env's `HALT_FLAGS` it reports, and `termination/any` for any of them;
- `uncertainty/mean`, `uncertainty/max`: the ensemble's disagreement over the rollout's env-steps, where the env
  reports it (info `uncertainty`: an uncertainty penalty or halt, or `report_uncertainty`).

Physics envs report reward terms but no halts; each scalar appears where its info does.
"""

from __future__ import annotations

import os

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.logger import Logger

from rwm_gym.tensorboard import require_tensorboard

HALT_FLAGS = ("model_diverged", "uncertainty_halt", "fall_tilt", "torque_halt")
"""Per-env booleans of the imagined env's infos that end an episode (`rwm_gym.imagination.core`)."""


def tensorboard_logger(log_dir: str | os.PathLike) -> Logger:
    """SB3's logger writing TensorBoard event files into `log_dir` (`TensorBoardMissing`, one line, without the
    package); one per run, so every `learn` call of the run appends to the same file."""
    require_tensorboard()
    from stable_baselines3.common.logger import configure

    return configure(str(log_dir), ["tensorboard"])


def tensorboard_callbacks(model, logger: Logger | None) -> tuple[BaseCallback, ...]:
    """Point `model` at `logger` and return the callbacks that add the env's scalars; `()` for no logger."""
    if logger is None:
        return ()
    model.set_logger(logger)
    return (RolloutScalars(),)


class RolloutScalars(BaseCallback):
    """Records the env's per-rollout scalars (the module docstring names them) into the model's logger."""

    def _on_training_start(self) -> None:
        # A logger set on the model outlives `learn`: it still holds the last update's train/* values, which
        # `rwm_gym.rl.ppo`'s KL rule would read as the previous update's. SB3 starts each `learn` with a fresh logger
        # when none is set; emptying this one keeps a run the same with TensorBoard as without.
        for values in (self.logger.name_to_value, self.logger.name_to_count, self.logger.name_to_excluded):
            values.clear()

    def _on_rollout_start(self) -> None:
        self.steps = 0
        self.means: dict[str, float] = {}
        self.flags: dict[str, np.ndarray] = {}
        self.uncertainty_max = -np.inf
        self.lengths: list[int] = []
        self.returns: list[float] = []

    def _on_step(self) -> bool:
        infos, dones = self.locals["infos"], self.locals["dones"]
        self.steps += 1
        for key in infos[0]:
            if key.startswith("reward/") or key == "uncertainty":
                values = np.fromiter((info[key] for info in infos), np.float64, len(infos))
                self.means[key] = self.means.get(key, 0.0) + float(values.mean())
                if key == "uncertainty":
                    self.uncertainty_max = max(self.uncertainty_max, float(values.max()))
            elif key in HALT_FLAGS:
                fired = np.fromiter((info[key] for info in infos), bool, len(infos))
                self.flags[key] = self.flags.get(key, np.zeros(len(infos), dtype=bool)) | fired
        for i in np.flatnonzero(dones):
            episode = infos[i].get("episode")
            if episode is not None:
                self.lengths.append(episode["l"])
                self.returns.append(episode["r"])
        return True

    def _on_rollout_end(self) -> None:
        record, steps = self.logger.record, max(self.steps, 1)
        for key, total in self.means.items():
            record("uncertainty/mean" if key == "uncertainty" else key, total / steps)
        if "uncertainty" in self.means:
            record("uncertainty/max", self.uncertainty_max)
        for key, fired in self.flags.items():
            record(f"termination/{key}", float(fired.mean()))
        if self.flags:
            record("termination/any", float(np.logical_or.reduce(list(self.flags.values())).mean()))
        record("episode/count", len(self.lengths))
        if self.lengths:
            record("episode/length", float(np.mean(self.lengths)))
            record("episode/return", float(np.mean(self.returns)))

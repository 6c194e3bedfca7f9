"""A long PPO run in a folder that survives being killed: resume point, policy snapshots, learning log, experience.

    RUN/latest.zip             SB3 model (policy, optimiser, step count), written atomically every `save_every` rollouts
    RUN/state.json             PPO config, the env trained in (physics or a world model and its imagination
                               options), learning rate, rollouts done, wall time, restarts, experience files
    RUN/snapshots/step_N.zip   the policy that collected the rollout starting at env step N, every `snapshot_every`
    RUN/log.csv                one row per rollout (the `learn` log: step reward, episode return, lr, KL, std, wall)
    RUN/experience/part_K.h5   episodes of every `record_every`-th env (`RecordingCore`), one file per process start

Starting the same command again continues from `latest.zip` to the same total budget. A resumed run is not
bit-identical to an uninterrupted one (the envs restart from fresh episodes); at most `save_every` rollouts are lost.
"""

from __future__ import annotations

import csv
import json
import time
from dataclasses import asdict
from pathlib import Path

from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import BaseCallback

from rwm_gym.atomic import write_json
from rwm_gym.rl.policy_file import save_policy


class TrainingRun:
    """The folder of one resumable run."""

    def __init__(self, folder: str | Path):
        self.folder = Path(folder)
        self.latest = self.folder / "latest.zip"
        self.state_path = self.folder / "state.json"
        self.snapshots = self.folder / "snapshots"
        self.log_path = self.folder / "log.csv"
        self.experience = self.folder / "experience"

    @property
    def resumable(self) -> bool:
        return self.latest.is_file() and self.state_path.is_file()

    OWN_FILES = (
        "latest.zip",
        "state.json",
        "snapshots",
        "log.csv",
        "experience",
        "latest_shac.pt",
        "latest_dreamer.pt",
    )
    """What a training run writes in its folder (SHAC's and the Dreamer-style learner's optimiser state included)."""

    def holds_only_a_run(self) -> bool:
        """Whether every file in the folder is one a training run writes (or a hidden temp or lock file): a run's
        folder, resumable or killed before its first resume point, that the same command continues."""
        return all(p.name.startswith(".") or p.name in self.OWN_FILES for p in self.folder.iterdir())

    def state(self) -> dict:
        return json.loads(self.state_path.read_text()) if self.state_path.is_file() else {}

    def next_experience_file(self) -> Path:
        self.experience.mkdir(parents=True, exist_ok=True)
        k = len(list(self.experience.glob("part_*.h5")))
        return self.experience / f"part_{k:03d}.h5"

    def snapshot_files(self) -> list[Path]:
        """Snapshots in order of env steps."""
        return sorted(self.snapshots.glob("step_*.zip"), key=lambda p: int(p.stem.split("_")[1]))


class RunCheckpoint(BaseCallback):
    """Saves the resume point, snapshots and the log of `run`; tells a `RecordingCore` the current rollout index.

    `log_row` is meant for `learn(on_rollout=...)`: it appends each rollout's log row to log.csv.
    """

    def __init__(
        self,
        run: TrainingRun,
        config,
        *,
        save_every: int,
        snapshot_every: int,
        recorder=None,
        prior_wall_s: float = 0.0,
        restarts: int = 0,
        environment: dict | None = None,
    ):
        super().__init__()
        self.run, self.config, self.recorder, self.environment = run, config, recorder, environment
        self.save_every, self.snapshot_every = save_every, snapshot_every
        self.prior_wall_s, self.restarts = prior_wall_s, restarts
        self.started = time.monotonic()  # reset when training starts; set here so log_row works before that

    def _rollout_index(self) -> int:
        return self.num_timesteps // (self.training_env.num_envs * self.model.n_steps)

    def _on_training_start(self) -> None:
        self.started = time.monotonic()
        if self.recorder is not None:
            self.recorder.iteration = self._rollout_index()

    def _on_rollout_start(self) -> None:
        index = self._rollout_index()
        if self.recorder is not None:
            self.recorder.iteration = index
        if self.snapshot_every and index % self.snapshot_every == 0:
            save_policy(self.model, self.run.snapshots / f"step_{self.num_timesteps}.zip")

    def _on_step(self) -> bool:
        return True

    def log_row(self, row: dict) -> None:
        """Append one rollout's log row (from `learn`'s progress callback) to log.csv."""
        new = not self.run.log_path.is_file()
        with self.run.log_path.open("a", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=["rollout", "total_wall_s", *row])
            if new:
                writer.writeheader()
            writer.writerow(
                {
                    "rollout": self._rollout_index(),
                    "total_wall_s": round(self.prior_wall_s + time.monotonic() - self.started, 2),
                    **row,
                }
            )

    def _on_rollout_end(self) -> None:
        if self._rollout_index() % self.save_every == 0:
            self.save()

    def save(self) -> None:
        save_policy(self.model, self.run.latest)
        write_json(
            self.run.state_path,
            {
                "ppo": asdict(self.config),
                "env": self.environment,
                "timesteps": int(self.num_timesteps),
                "rollouts": self._rollout_index(),
                "learning_rate": float(self.model.learning_rate),
                "wall_s": self.prior_wall_s + time.monotonic() - self.started,
                "restarts": self.restarts,
                "experience": sorted(str(p.name) for p in self.run.experience.glob("part_*.h5")),
                "experience_episodes_this_process": None if self.recorder is None else self.recorder.episodes_written,
            },
        )


def resume_model(run: TrainingRun, env, device: str) -> PPO:
    """The model at the run's resume point, on `env`, with its adapted learning rate."""
    from rwm_gym.rl.ppo import PPOConfig, load_ppo

    saved = {**PPOConfig().to_dict(), **run.state()["ppo"]}  # a field added since the run started: its default
    config = PPOConfig(**{**saved, "net_arch": tuple(saved["net_arch"])})
    model = load_ppo(run.latest, env, config, device=device)
    model.learning_rate = run.state()["learning_rate"]
    model._setup_lr_schedule()
    return model

"""The imagined task: N rollouts of a trained world model stepped in one forward pass.

`ImaginedCore` has the same interface as the physics cores (`rwm_gym.physics.locomotion.LocomotionCore`,
`rwm_gym.physics.dmc.DMCCore`): the same observation, and the task's commands, reward and termination
(the task object of `rwm_gym.task.tasks`, chosen from the checkpoint's spec, the same the physics env uses), fed with
the model's predicted state and privileged
signals instead of measured ones. Contacts are predicted logits > 0; a task that terminates (ANYmal D) ends an
episode when the predicted termination probability is > 0.5.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch

from rwm_gym.batched_core import check_actions, check_num_envs
from rwm_gym.data.dataset import Dataset
from rwm_gym.imagination.kinematics import KinematicClosure
from rwm_gym.imagination.options import MATMUL_PRECISION_NAMES, ImaginationOptions
from rwm_gym.imagination.reset_data import ResetWindows, WarmUpCache
from rwm_gym.model.checkpoint import load_checkpoint
from rwm_gym.resources import assets_dir
from rwm_gym.spec import TaskSpec, shipped_spec
from rwm_gym.task.observation import build_observation
from rwm_gym.task.tasks import Task, make_task


def default_checkpoint(env_id: str = "RWM-AnymalD-v0") -> Path:
    """The checkpoint shipped for an imagined env id (its spec's `task.default_checkpoint`)."""
    spec = shipped_spec(env_id)
    if spec is None or not spec.default_checkpoint:
        raise ValueError(
            f"{env_id} needs checkpoint=PATH: rwm-gym ships no trained world model for it (collect data "
            f"with `rwm-gym collect`, train one with `rwm-gym train`)"
        )
    path = assets_dir() / spec.default_checkpoint
    if not path.is_file():
        raise FileNotFoundError(f"the default {env_id} checkpoint {path} is not installed; pass checkpoint=PATH")
    return path


MATMUL_PRECISIONS = dict(zip(MATMUL_PRECISION_NAMES, (None, torch.bfloat16), strict=True))
"""`ImaginationOptions.matmul_precision` -> the dtype handed to the model (None: its weights' own)."""

HISTORY_COMMAND_NAMES = ("vx", "vy", "yaw_rate")
"""The commands `ImaginationOptions.command_from_history` reads off a history: base-frame planar velocity, yaw rate."""
HISTORY_COMMAND_ROWS = 10
"""Last rows of a history window whose mean velocity becomes its command (0.2 s at 50 Hz: about a trot step)."""


def tilt_degrees(projected_gravity: np.ndarray) -> np.ndarray:
    """(N,) angle between the base's z axis and up, from the gravity direction in the base frame (N, 3)."""
    g = np.asarray(projected_gravity, dtype=np.float64)
    cos = -g[:, 2] / np.maximum(np.linalg.norm(g, axis=1), 1e-9)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


class ImaginedCore:
    """N imagined rollouts; arrays are (N, ...) numpy, the model runs on `device`."""

    def __init__(
        self,
        checkpoint: str | Path | None = None,
        num_envs: int = 1,
        *,
        device: str = "cpu",
        reset_data: str | Path | None = None,
        options: ImaginationOptions | None = None,
        env_id: str | None = None,
        reward_fn=None,
        termination_fn=None,
    ):
        """env_id: the imagined env id this core serves (registration passes it): picks the shipped checkpoint when
        `checkpoint` is None, and a checkpoint of another task is refused. None: the checkpoint decides.
        reset_data: dataset of real histories episodes restart from (None: the checkpoint's).
        reward_fn, termination_fn: functions of the predicted `rwm_gym.task.entry_points.Transition` that replace the
        task's reward / termination (default: the spec's `[imagination]` entry points, else the task's own)."""
        self.options = options or ImaginationOptions()
        self.checkpoint = Path(checkpoint) if checkpoint is not None else default_checkpoint(env_id or "RWM-AnymalD-v0")
        self.device = torch.device(device)
        self._load_model(env_id)
        self.num_envs = num_envs = check_num_envs(num_envs)
        self._load_reset_windows(reset_data)
        self.episode_steps = self.options.episode_steps or self.spec.episode_steps
        self.task: Task = make_task(
            self.spec,
            num_envs,
            resample_commands=self.options.resample_commands,
            reward_fn=reward_fn,
            termination_fn=termination_fn,
            trust_entry_points=self.options.trust_entry_points,
            source=f"the spec in checkpoint {self.checkpoint}",
        )
        self._check_state_groups()
        self.kinematics = KinematicClosure.of(self.spec) if self.options.kinematics else None
        """A fixed-base arm's angles and sites, computed rather than predicted (None: other robots)."""
        self._allocate(num_envs)

    def _load_model(self, env_id: str | None) -> None:
        """The checkpoint's model, set up for the options (disagreement, matmul dtype), and its spec."""
        self.model, self.meta = load_checkpoint(self.checkpoint, device=self.device)
        if self.options.acts_on_disagreement and self.ensemble_size < 2:
            raise ValueError(
                f"{self.checkpoint}: the uncertainty penalty and halt act on the ensemble's disagreement, "
                "and this model has one head (train it with --ensemble-size 5)"
            )
        self.model.set_disagreement(self.needs_uncertainty)  # the model is this core's own; options are frozen
        if self.options.matmul_precision != "float32":
            if not hasattr(self.model, "set_step_matmul_dtype"):
                raise ValueError(
                    f"{self.checkpoint}: matmul_precision {self.options.matmul_precision} is implemented "
                    f"for RWM models, not {self.model.config.kind}"
                )
            self.model.set_step_matmul_dtype(MATMUL_PRECISIONS[self.options.matmul_precision])
        self.spec: TaskSpec = self.meta.spec
        if env_id is not None and self.spec.imagined_env_id != env_id:
            raise ValueError(
                f"{self.checkpoint}: a world model of {self.spec.name} (for {self.spec.imagined_env_id}), "
                f"not of {env_id}"
            )
        self.norm = self.meta.normalizer

    def _load_reset_windows(self, reset_data: str | Path | None) -> None:
        """The real history windows resets draw from, `options.history` rows each (default the training history)."""
        history = self.options.history or (self.meta.train_config.history if self.meta.train_config else 32)
        reset_dataset = Dataset.load(self._reset_data_path(reset_data))
        if reset_dataset.spec().name != self.spec.name:
            raise ValueError(
                f"reset data {reset_dataset.path} is of task {reset_dataset.spec().name}, the world model "
                f"{self.checkpoint} of {self.spec.name}"
            )
        self.reset_windows = ResetWindows(reset_dataset, history)

    def _check_state_groups(self) -> None:
        """Refuse an option that reads a state group (or limit) the task's spec has not."""
        slices, name = self.spec.state_slices, self.spec.name
        if self.options.fall_tilt > 0 and "projected_gravity" not in slices:
            raise ValueError(
                f"{self.checkpoint}: fall_tilt needs a projected_gravity state group, which {name} has not"
            )
        if self.options.torque_halt > 0 and (
            "joint_torque" not in slices or not np.isfinite(self.spec.actuator.per_joint("effort_limit")).all()
        ):
            raise ValueError(
                f"{self.checkpoint}: torque_halt needs a joint_torque state group and a finite effort "
                f"limit, which {name} has not"
            )
        if self.options.command_from_history > 0 and (
            list(self.spec.command.names) != list(HISTORY_COMMAND_NAMES)
            or not {"base_lin_vel", "base_ang_vel"} <= set(slices)
        ):
            raise ValueError(
                f"{self.checkpoint}: command_from_history needs commands {', '.join(HISTORY_COMMAND_NAMES)} and "
                f"base_lin_vel and base_ang_vel state groups, which {name} has not"
            )
        if self.options.push_interval_s > 0 and "base_lin_vel" not in slices:
            raise ValueError(
                f"{self.checkpoint}: push_interval_s needs a base_lin_vel state group, which {name} has not"
            )

    def _allocate(self, n: int) -> None:
        """Per-env arrays, generators, hidden states, the warm-up cache and the spaces."""
        s, a = self.spec.state_dim, self.spec.action_dim
        self.rngs = [np.random.default_rng() for _ in range(n)]
        self.state = np.zeros((n, s), dtype=np.float32)
        self.contact = np.zeros((n, self.spec.contact_dim), dtype=bool)
        self.foot_height = np.zeros((n, self.spec.foot_dim), dtype=np.float32)
        self.last_action = np.zeros((n, a))
        self.steps = np.zeros(n, dtype=np.int64)
        self.started = np.zeros(n, dtype=bool)
        self.uncertainty = np.zeros(n)
        self.member = torch.zeros(n, dtype=torch.long, device=self.device)
        self.hidden = self.model.initial_hidden(n, self.device)
        template = self.model.initial_hidden(1, self.device)
        self.warm_up_cache = None
        if (
            not self.model.warm_hidden_reads_member
            and WarmUpCache.nbytes(self.reset_windows, template) <= self.options.warm_up_cache_mb * 2**20
        ):
            self.warm_up_cache = WarmUpCache(self.reset_windows, template, prefetch=n)
        self.single_action_space = gym.spaces.Box(-np.ones(a, np.float32), np.ones(a, np.float32), dtype=np.float32)
        self.single_observation_space = gym.spaces.Box(-np.inf, np.inf, (self.spec.observation_dim,), np.float32)

    def _reset_data_path(self, given: str | Path | None) -> Path:
        if given is not None:
            return Path(given)
        named = self.meta.extras.get("reset_data")
        if named:
            # beside the checkpoint; a copy of a shipped checkpoint finds the shipped reset data
            for folder in (self.checkpoint.parent, assets_dir() / "checkpoints"):
                if (folder / named).is_file():
                    return folder / named
            raise FileNotFoundError(
                f"{self.checkpoint}: its reset data {named} is neither beside it nor shipped; "
                f"copy it there or pass reset_data=PATH"
            )
        dataset = self.meta.provenance.get("dataset")
        if dataset and Path(dataset).is_file():
            return Path(dataset)
        raise ValueError(
            f"{self.checkpoint}: names no reset data (extras['reset_data']) and its training data "
            f"{dataset!r} is not here; pass reset_data=PATH"
        )

    @property
    def command(self) -> np.ndarray:
        """(N, K) the task's current commands (K = 0 for tasks without commands)."""
        return self.task.command

    @property
    def ensemble_size(self) -> int:
        return self.model.config.ensemble_size

    def observe(self, ids: np.ndarray | slice = slice(None)) -> np.ndarray:
        return build_observation(self.spec, self.state[ids], self.command[ids], self.last_action[ids])

    @property
    def needs_uncertainty(self) -> bool:
        """Whether a step computes the ensemble disagreement (the penalty or the report asks for it)."""
        return self.options.acts_on_disagreement or self.options.report_uncertainty

    @torch.inference_mode()
    def reset(
        self, ids: np.ndarray, seeds: Sequence[int | None] | None = None, commands: np.ndarray | None = None
    ) -> np.ndarray:
        """Start envs `ids` from real history windows, replaying the full warm-up through the model; hold `commands`
        (len(ids), K) for the episode if given."""
        ids = np.asarray(ids, dtype=int)
        for i, seed in zip(ids, seeds or [None] * len(ids)):
            if seed is not None:
                self.rngs[i] = np.random.default_rng(seed)
        # per env: its window's draw, then its head's draw, from its own generator (seeded envs repeat exactly)
        ends, members = np.zeros(len(ids), dtype=np.int64), np.zeros(len(ids), dtype=np.int64)
        for row, i in enumerate(ids):
            ends[row] = self.reset_windows.draw(self.rngs[i])
            members[row] = self.rngs[i].integers(self.ensemble_size)
        windows = self.reset_windows.gather(ends)
        index = torch.as_tensor(ids, device=self.device)
        member = torch.as_tensor(members, device=self.device)
        self.member[index] = member
        if self.warm_up_cache is not None:
            hidden = self.warm_up_cache.get(ends, lambda rows: self._warm_hidden(self.reset_windows.gather(rows)))
        else:
            hidden = self._warm_hidden(windows, member if self.ensemble_size > 1 else None)
        self.model.scatter_hidden_(self.hidden, index, hidden)
        self.state[ids] = windows.states[:, -1]
        self.contact[ids] = windows.contact
        self.foot_height[ids] = windows.foot_height
        self.last_action[ids] = windows.actions[:, -1]
        self.task.reset(ids, [self.rngs[i] for i in ids], commands)
        if commands is None and self.options.command_from_history > 0:
            self._command_from_history(ids, windows.states)
        self.steps[ids] = 0
        if self.options.random_first_episode_length:
            for i in ids[~self.started[ids]]:
                self.steps[i] = self.rngs[i].integers(self.episode_steps)
        self.started[ids] = True
        self.uncertainty[ids] = 0.0
        return self.observe(ids)

    def _command_from_history(self, ids: np.ndarray, states: np.ndarray) -> None:
        """Give a share of the restarted envs `ids` the velocity their history windows (states (n, T, S), SI) end at
        as their command (`ImaginationOptions.command_from_history`); each env decides with its own generator."""
        chosen = np.array([self.rngs[i].random() < self.options.command_from_history for i in ids])
        if not chosen.any():
            return
        s, recent = self.spec.state_slices, states[chosen, -HISTORY_COMMAND_ROWS:]
        velocity = np.concatenate(
            [recent[:, :, s["base_lin_vel"]][:, :, :2], recent[:, :, s["base_ang_vel"]][:, :, 2:]], axis=2
        ).mean(axis=1)
        command = self.spec.command
        self.task.command[ids[chosen]] = np.clip(velocity, command.low, command.high)

    def _warm_hidden(self, windows, member: torch.Tensor | None = None):
        """The model's hidden state after replaying real history windows (`ResetWindow`s stacked)."""
        states = torch.as_tensor(windows.states, device=self.device)
        actions = torch.as_tensor(windows.actions, device=self.device)
        return self.model.warm_hidden(self.norm.normalize_state(states).float(), actions.float(), member)

    def step(self, actions: np.ndarray):
        """Every env one imagined step: obs, reward, terminated, truncated, info (arrays per env)."""
        actions = check_actions(actions, (self.num_envs, self.spec.action_dim))
        host = self._predict(actions)
        sizes = (self.spec.state_dim, self.spec.contact_dim, self.spec.foot_dim, 1)
        host_parts = np.split(host, np.cumsum(sizes), axis=1)
        next_norm = host_parts[0].astype(np.float64)
        diverged = ~np.isfinite(next_norm).all(axis=1) | (np.abs(next_norm) > self.options.divergence_bound).any(axis=1)
        next_state = self.norm.denormalize_state(next_norm).astype(np.float32)
        next_state[diverged] = self.state[diverged]  # never hand NaN to the learner
        if self.kinematics is not None:
            self.kinematics.apply(self.state, next_state)
        held = getattr(self.task, "held_columns", ())
        if held:  # the task's fixed goal (a reach's target) is not the model's to move
            next_state[:, held] = self.state[:, held]
        contact = host_parts[1] > 0.5
        foot_height = self.norm.denormalize_foot_height(host_parts[2]).astype(np.float32)
        terminated = diverged.copy()
        if self.task.terminates:
            terminated |= host_parts[3][:, 0] > 0
        if self.needs_uncertainty:
            self.uncertainty = np.nan_to_num(host_parts[4][:, 0].astype(np.float64), nan=0.0)

        reward, terms = self.task.reward(next_state, self.state, contact, foot_height, actions, self.last_action)
        ended = getattr(self.task, "ended", None)  # a termination function's verdict on this step (FunctionTask)
        if ended is not None:
            terminated |= ended
        if self.options.uncertainty_penalty > 0:
            excess = np.maximum(self.uncertainty - self.options.uncertainty_floor, 0.0)
            reward = reward - self.options.uncertainty_penalty * excess * self.spec.policy_dt
        tipped = np.zeros(self.num_envs, dtype=bool)
        if self.options.fall_tilt > 0:
            tipped = tilt_degrees(next_state[:, self.spec.state_slices["projected_gravity"]]) > self.options.fall_tilt
            terminated |= tipped
        saturated = np.zeros(self.num_envs, dtype=bool)
        if self.options.torque_halt > 0:
            torque = np.abs(next_state[:, self.spec.state_slices["joint_torque"]])
            saturated = (torque >= self.options.torque_halt * self.spec.actuator.per_joint("effort_limit")).any(axis=1)
            terminated |= saturated
        halted = np.zeros(self.num_envs, dtype=bool)
        if self.options.uncertainty_halt > 0:
            halted = self.uncertainty > self.options.uncertainty_halt
            terminated |= halted
        reward = np.where(diverged, 0.0, reward)
        info = {
            "command": self.command.copy(),
            "model_diverged": diverged,
            "uncertainty_halt": halted,
            "fall_tilt": tipped,
            "torque_halt": saturated,
            **({"uncertainty": self.uncertainty.copy()} if self.needs_uncertainty else {}),
            **{f"reward/{k}": v for k, v in terms.items()},
        }
        success = getattr(self.task, "success", None)  # a manipulation task's goal, judged on the prediction
        if success is not None:
            info["success"] = success & ~diverged

        self.state, self.contact, self.foot_height, self.last_action = next_state, contact, foot_height, actions
        self.steps += 1
        truncated = (self.steps >= self.episode_steps) & ~terminated
        self._push()
        self.task.advance(self.steps, self.rngs)
        return self.observe(), reward.astype(np.float64), terminated, truncated, info

    @torch.inference_mode()
    def _predict(self, actions: np.ndarray) -> np.ndarray:
        """The model's step on the host: (N, S + C + F + 1 [+ 1]) normalised next state (sampled if asked), contact
        flags, foot heights, termination logit [, disagreement when `needs_uncertainty`]."""
        x = self.norm.normalize_state(torch.as_tensor(self.state, device=self.device))
        u = torch.as_tensor(actions, dtype=torch.float32, device=self.device)
        member = self.member if self.ensemble_size > 1 else None
        self.hidden, p = self.model.step(self.hidden, x.float(), u, member)
        mean = p.state_mean
        if self.options.sample_predictions:
            noise = np.stack([rng.standard_normal(self.spec.state_dim) for rng in self.rngs])
            mean = mean + p.state_std * torch.as_tensor(noise, dtype=mean.dtype, device=self.device)
        # The task runs in numpy (the Gymnasium contract): one device-to-host copy per step carries every output.
        parts = [
            mean,
            (p.contact_logits > 0).to(mean.dtype),
            p.foot_height.to(mean.dtype),
            p.termination_logit.to(mean.dtype).unsqueeze(1),
        ]
        if self.needs_uncertainty:
            parts.append(p.uncertainty.to(mean.dtype).unsqueeze(1))
        return torch.cat(parts, dim=1).cpu().numpy()

    def _push(self) -> None:
        if self.options.push_interval_s <= 0:
            return
        every = max(1, round(self.options.push_interval_s / self.spec.policy_dt))
        lin = self.spec.state_slices["base_lin_vel"]
        for i in np.flatnonzero(self.steps % every == 0):
            v = self.options.push_velocity
            self.state[i, lin.start : lin.start + 2] += self.rngs[i].uniform(-v, v, 2).astype(np.float32)

    def record(self) -> dict[str, np.ndarray]:
        """The imagined rows, in the dataset's field names (no simulator state: qpos/qvel are absent)."""
        return {
            "state": self.state.copy(),
            "contact": self.contact.copy(),
            "foot_height": self.foot_height.copy(),
            "command": self.command.copy(),
        }

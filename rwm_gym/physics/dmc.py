"""dm_control tasks as rwm-gym physics envs: the suite (cheetah, walker, hopper, quadruped, humanoid, finger, ...) and
the Kinova Jaco arm of `dm_control.manipulation` (reach, lift; see `rwm_gym.task.dmc_environments`).

`DMCCore` runs N environments of one task side by side (a plain loop: the models are small), using dm_control's own
MJCF models and task code for initial states and rewards. It follows the protocol of
`rwm_gym.batched_core` (which `rwm_gym.data.collect` drives); `DMCEnv` is the core with N = 1 behind `gymnasium.Env`,
and the vector envs of `rwm_gym.vector` (`DMCGymVectorEnv`, `DMCSB3VecEnv`) the core with N > 1, so all give
identical transitions per seed.

The world-model state is read from the physics as the spec declares (see `rwm_gym.physics.dmc_layout`); the policy
observation is the spec's `[observation]` groups (the state plus the last action). The tasks never terminate; an
episode is truncated after the spec's `episode_steps` (dm_control's time limit). Actions in [-1, 1] are mapped
linearly onto each actuator's control range. The reward is the dm_control task's reward after the step; a
manipulation task's step also reports `info["success"]` (its goal met, see `rwm_gym.task.manipulation_reward`).
"""

from __future__ import annotations

from collections.abc import Sequence

import gymnasium as gym
import mujoco
import numpy as np

from rwm_gym.batched_core import check_actions, check_num_envs, commands_from_options
from rwm_gym.physics.dmc_layout import DMCLayout
from rwm_gym.spec import SuiteTask, TaskSpec, load_spec
from rwm_gym.task.dmc_environments import MANIPULATION, load_environment
from rwm_gym.task.manipulation_reward import GOAL_REWARD
from rwm_gym.task.observation import build_observation


class DMCCore:
    """One dm_control task for N environments. Arrays are (N, ...) unless said otherwise."""

    def __init__(self, spec: TaskSpec, num_envs: int = 1):
        self.spec = spec
        self.num_envs = num_envs = check_num_envs(num_envs)
        self.params = SuiteTask.from_spec(spec)
        self.envs = [load_environment(self.params.domain, self.params.task) for _ in range(num_envs)]
        physics = self.envs[0].physics
        self.model: mujoco.MjModel = physics.model.ptr
        for field, ours, theirs in (
            ("task.physics_dt", spec.physics_dt, physics.timestep()),
            ("task.policy_dt", spec.policy_dt, self.envs[0].control_timestep()),
        ):
            if not np.isclose(ours, theirs):
                raise ValueError(
                    f"task spec {spec.name}: {field} is {ours} s but dm_control's "
                    f"{self.params.domain}-{self.params.task} uses {theirs} s"
                )
        self.layout = DMCLayout(self.model, spec, self.params.contact_partner)
        low, high = self.model.actuator_ctrlrange.T
        self._ctrl_mid, self._ctrl_half = (high + low) / 2, (high - low) / 2
        n, a = num_envs, spec.action_dim
        self.last_action = np.zeros((n, a))
        self.command = np.zeros((n, 0), dtype=np.float32)
        self.steps = np.zeros(n, dtype=np.int64)
        self.state = np.stack([self.layout.state(env.physics.data.ptr) for env in self.envs])
        self._reports_success = self.params.domain == MANIPULATION and "manipulation" in spec.extra

        high_a = np.ones(a, dtype=np.float32)
        self.single_action_space = gym.spaces.Box(-high_a, high_a, dtype=np.float32)
        self.single_observation_space = gym.spaces.Box(-np.inf, np.inf, (spec.observation_dim,), dtype=np.float32)

    def observe(self, ids: np.ndarray | slice = slice(None)) -> np.ndarray:
        """Policy observations of envs `ids`, (len(ids), O) float32."""
        return build_observation(self.spec, self.state[ids], self.command[ids], self.last_action[ids])

    def reset(
        self, ids: np.ndarray, seeds: Sequence[int | None] | None = None, commands: np.ndarray | None = None
    ) -> np.ndarray:
        """Start new episodes in envs `ids` (re-seeding the task's generator where a seed is given)."""
        if commands is not None and np.shape(commands)[-1]:
            raise ValueError(f"{self.spec.name} has no commands")
        ids = np.asarray(ids, dtype=int)
        for i, seed in zip(ids, seeds or [None] * len(ids)):
            env = self.envs[i]
            if seed is not None:
                env.reseed(seed)
            env.reset()
            self.state[i] = self.layout.state(env.physics.data.ptr)
        self.last_action[ids] = 0.0
        self.steps[ids] = 0
        return self.observe(ids)

    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, np.ndarray]]:
        """Advance every env one control step. Returns obs, reward, terminated, truncated, info (arrays per env).

        No env is reset here; callers reset finished envs (the vector adapters do it automatically).
        """
        actions = check_actions(actions, (self.num_envs, self.spec.action_dim))
        ctrl = self._ctrl_mid + self._ctrl_half * actions
        reward = np.zeros(self.num_envs)
        for i, env in enumerate(self.envs):
            reward[i] = env.step(ctrl[i], self.spec.substeps)
            self.state[i] = self.layout.state(env.physics.data.ptr)
        self.last_action = actions
        self.steps += 1
        terminated = np.zeros(self.num_envs, dtype=bool)
        truncated = self.steps >= self.spec.episode_steps
        info = {"success": reward >= GOAL_REWARD} if self._reports_success else {}
        return self.observe(), reward, terminated, truncated, info

    def record(self) -> dict[str, np.ndarray]:
        """The dataset row of every env at the current time (see `rwm_gym.data.dataset` for the layout)."""
        datas = [env.physics.data.ptr for env in self.envs]
        return {
            "state": self.state.copy(),
            "contact": np.stack([self.layout.contact(d) for d in datas]),
            "foot_height": np.stack([self.layout.foot_height(d) for d in datas]),
            "terminated": np.zeros(self.num_envs, dtype=bool),
            "command": self.command.copy(),
            "qpos": np.stack([d.qpos for d in datas]).astype(np.float64),
            "qvel": np.stack([d.qvel for d in datas]).astype(np.float64),
        }


def make_core(spec: str | TaskSpec, num_envs: int = 1) -> DMCCore:
    """The batched core of a dm_control spec, by spec name (e.g. "dmc_cheetah_run") or TaskSpec."""
    return DMCCore(spec if isinstance(spec, TaskSpec) else load_spec(spec), num_envs)


class DMCEnv(gym.Env):
    """A dm_control task as a Gymnasium env (e.g. `DMC-Cheetah-Run-v0`, `DMC-Jaco-ReachSite-v0`).

    Observation: the spec's `[observation]` groups (state, then last action), float32. Action: [-1, 1]^A, mapped onto
    the actuators' control ranges. Reward: the dm_control task's. Never terminates; truncates after `episode_steps`.
    Info: `success` (bool) for a manipulation task.
    `render_mode="rgb_array"` renders dm_control's camera `camera` (needs an OpenGL backend, see MUJOCO_GL).
    """

    metadata = {"render_modes": ["rgb_array"]}  # render_fps: the spec's control rate, set per instance

    def __init__(
        self,
        spec: str | TaskSpec,
        *,
        render_mode: str | None = None,
        width: int = 320,
        height: int = 240,
        camera: int = 0,
    ):
        self.core = make_core(spec, 1)
        self.task_spec = self.core.spec
        self.observation_space = self.core.single_observation_space
        self.action_space = self.core.single_action_space
        self.metadata = {**self.metadata, "render_fps": int(round(1.0 / self.task_spec.policy_dt))}
        self.render_mode = render_mode
        self._render_size, self._camera = (height, width), camera

    @property
    def physics(self):
        """The dm_control `Physics` (its `.model.ptr` / `.data.ptr` are the raw MjModel / MjData)."""
        return self.core.envs[0].physics

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        commands_from_options(options, 1, self.task_spec.command)  # refuses unknown options and commands
        return self.core.reset(np.array([0]), [seed])[0], {}

    def step(self, action):
        obs, reward, terminated, truncated, info = self.core.step(np.asarray(action)[None])
        info = {k: v[0].item() for k, v in info.items()}
        return obs[0], float(reward[0]), bool(terminated[0]), bool(truncated[0]), info

    def record(self) -> dict[str, np.ndarray]:
        return {k: v[0] for k, v in self.core.record().items()}

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        height, width = self._render_size
        return self.physics.render(height=height, width=width, camera_id=self._camera)

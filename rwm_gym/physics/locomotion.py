"""Velocity-tracking locomotion in MuJoCo: the vectorised task core and the single `gymnasium.Env`.

`LocomotionCore` runs N simulations at once on either simulator backend and hands the measured states to the task
object (`rwm_gym.task.tasks.VelocityTrackingTask`: commands, reward) that the imagined env shares; `LocomotionEnv` is
the core with N = 1 behind the standard Gymnasium API, and the vector
envs in `rwm_gym.vector` are the same core with N > 1 (`make_core`). So the three give identical transitions per seed.
"""

from __future__ import annotations

import atexit
from collections.abc import Sequence
from dataclasses import replace

import gymnasium as gym
import mujoco
import numpy as np

from rwm_gym.batched_core import check_actions, check_num_envs, commands_from_options
from rwm_gym.physics.options import PhysicsOptions
from rwm_gym.physics.params import PhysicsParams, SolverSettings, build_model, drive_rewrites
from rwm_gym.physics.robot import Measurement, RobotLayout, measure
from rwm_gym.physics.sensors import SensorBias
from rwm_gym.physics.simulator import BatchSimulator, SingleSimulator
from rwm_gym.spec import TaskSpec, load_spec
from rwm_gym.task.observation import build_observation
from rwm_gym.task.tasks import VelocityTrackingTask


class LocomotionCore:
    """The task for N simulations of one robot. Arrays are (N, ...) unless said otherwise; `options` (a
    `PhysicsOptions`, default its defaults) say which robot and how it runs."""

    def __init__(self, spec: TaskSpec, num_envs: int = 1, *, options: PhysicsOptions | None = None):
        options = options or PhysicsOptions()
        self.spec, self.options = spec, options
        self.num_envs = num_envs = check_num_envs(num_envs)
        physics = options.physics
        self.params = physics if isinstance(physics, PhysicsParams) else PhysicsParams.from_dict(physics)
        self.solver = SolverSettings.from_dict(options.solver)
        self.model = build_model(spec, options.xml_file, self.params, self.solver)
        if not np.isclose(self.model.opt.timestep, spec.physics_dt):
            raise ValueError(
                f"task spec {spec.name}: task.physics_dt is {spec.physics_dt} s but the MJCF "
                f"{options.xml_file or spec.model_path} steps {self.model.opt.timestep} s"
            )
        self.layout = RobotLayout.from_model(self.model, spec)
        drives = drive_rewrites(spec, self.model, self.params)
        self.sim = (
            SingleSimulator(self.model, drives)
            if num_envs == 1
            else BatchSimulator(self.model, num_envs, options.nthread, drives)
        )
        self.sensor_bias = SensorBias.of(self.layout, self.params)
        self.keyframe = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_KEY, spec.keyframe)
        if self.keyframe < 0:
            raise ValueError(f"robot model has no keyframe named {spec.keyframe!r} (task spec {spec.name})")
        self.observation_noise = options.observation_noise
        self.rngs = [np.random.default_rng() for _ in range(num_envs)]
        n, a = num_envs, spec.action_dim
        self.task = VelocityTrackingTask(spec, n, options.resample_commands)
        self.last_action = np.zeros((n, a))
        self.steps = np.zeros(n, dtype=np.int64)
        self.current: Measurement = self._measure()

        high = np.ones(a, dtype=np.float32)
        self.single_action_space = gym.spaces.Box(-high, high, dtype=np.float32)
        self.single_observation_space = gym.spaces.Box(-np.inf, np.inf, (spec.observation_dim,), dtype=np.float32)

    @property
    def command(self) -> np.ndarray:
        """(N, K) the task's current commands."""
        return self.task.command

    def _measure(self) -> Measurement:
        return measure(self.layout, self.spec, **self._read())

    def _read(self) -> dict[str, np.ndarray]:
        """The simulators' arrays as the robot's sensors read them (qpos and qvel through `sensor_bias`)."""
        arrays = self.sim.arrays()
        if self.sensor_bias is not None:
            qpos, qvel = self.sensor_bias.read(arrays["qpos"], arrays["qvel"])
            arrays = {**arrays, "qpos": qpos, "qvel": qvel}
        return arrays

    def observe(self, ids: np.ndarray | slice = slice(None)) -> np.ndarray:
        rngs = [self.rngs[i] for i in np.arange(self.num_envs)[ids]] if self.observation_noise else None
        return build_observation(self.spec, self.current.state[ids], self.command[ids], self.last_action[ids], rngs)

    def reset(
        self, ids: np.ndarray, seeds: Sequence[int | None] | None = None, commands: np.ndarray | None = None
    ) -> np.ndarray:
        """Start new episodes in envs `ids` (re-seeding those with a seed; holding `commands` (len(ids), K) if given);
        return their observations."""
        ids = np.asarray(ids, dtype=int)
        for i, seed in zip(ids, seeds or [None] * len(ids)):
            if seed is not None:
                self.rngs[i] = np.random.default_rng(seed)
        key, r = self.model.key(self.keyframe), self.spec.reset
        qpos = np.repeat(key.qpos[None], len(ids), axis=0)
        qvel = np.repeat(key.qvel[None], len(ids), axis=0)
        for row, i in enumerate(ids):
            rng = self.rngs[i]
            qpos[row, self.layout.qpos_adr] += rng.uniform(-r.joint_pos_noise, r.joint_pos_noise, self.spec.action_dim)
            qvel[row, 0:3] += rng.uniform(-r.base_lin_vel_noise, r.base_lin_vel_noise, 3)
            qvel[row, 3:6] += rng.uniform(-r.base_ang_vel_noise, r.base_ang_vel_noise, 3)
        self.sim.reset(ids, self.keyframe, qpos, qvel)
        self.task.reset(ids, [self.rngs[i] for i in ids], commands)
        self.last_action[ids] = 0.0
        self.steps[ids] = 0
        fresh = self._measure()
        for field in ("state", "contact", "foot_height", "terminated"):
            getattr(self.current, field)[ids] = getattr(fresh, field)[ids]
        return self.observe(ids)

    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, np.ndarray]]:
        """Advance every env one policy step. Returns obs, reward, terminated, truncated, info (arrays per env).

        No env is reset here; callers reset finished envs (the vector adapters do it automatically). An env whose
        simulation blew up during the step (`info["physics_diverged"]`; MuJoCo reset it to the default pose) is
        terminated with reward 0: what it measures after the step is no motion of the robot.
        """
        actions = check_actions(actions, (self.num_envs, self.spec.action_dim))
        act = self.spec.actuator
        # actuators the spec does not drive (a legs-only humanoid's arms) hold the keyframe's control
        ctrl = np.repeat(self.model.key_ctrl[self.keyframe][None], self.num_envs, axis=0)
        ctrl[:, self.layout.actuator_ids] = np.asarray(act.default_pose) + act.action_scale * actions
        self.sim.step(ctrl, self.spec.substeps)

        diverged = self.sim.diverged.copy()
        prev, now = self.current, self._measure()
        reward, terms = self.task.reward(now.state, prev.state, now.contact, now.foot_height, actions, self.last_action)
        reward = np.where(diverged, 0.0, reward)
        info = {
            "command": self.command.copy(),
            "physics_diverged": diverged,
            **{f"reward/{k}": v for k, v in terms.items()},
        }

        self.current, self.last_action = now, actions
        self.steps += 1
        terminated = now.terminated | diverged
        truncated = (self.steps >= self.spec.episode_steps) & ~terminated
        self.task.advance(self.steps, self.rngs)
        return self.observe(), reward.astype(np.float64), terminated, truncated, info

    def record(self) -> dict[str, np.ndarray]:
        """The dataset row of every env at the current time (see `rwm_gym.data.dataset` for the layout); qpos and qvel
        as the sensors read them, as a real robot's log holds them."""
        arrays = self._read()
        return {
            "state": self.current.state.copy(),
            "contact": self.current.contact.copy(),
            "foot_height": self.current.foot_height.copy(),
            "terminated": self.current.terminated.copy(),
            "command": self.command.copy(),
            "qpos": np.array(arrays["qpos"], dtype=np.float64),
            "qvel": np.array(arrays["qvel"], dtype=np.float64),
        }


def make_core(
    spec: str | TaskSpec = "anymal_d", num_envs: int = 1, *, options: PhysicsOptions | None = None, **kwargs
) -> LocomotionCore:
    """The batched core of N simulations of a spec, by spec name (e.g. "anymal_d") or TaskSpec. kwargs: fields of
    `PhysicsOptions` (xml_file, physics, observation_noise, nthread, resample_commands, solver) that replace those of
    `options`; the one place the keyword conveniences of the physics envs become options."""
    options = replace(options or PhysicsOptions(), **kwargs)
    return LocomotionCore(spec if isinstance(spec, TaskSpec) else load_spec(spec), num_envs, options=options)


class LocomotionEnv(gym.Env):
    """A legged robot tracking velocity commands in MuJoCo (e.g. `AnymalD-MuJoCo-v0`).

    Observation (spec `observation.groups`, 48 for ANYmal D), action in [-1, 1]^A scaled to joint-position offsets
    around the default pose. `info` carries the command and every unweighted reward term. The MuJoCo model and data are
    `env.unwrapped.model` / `env.unwrapped.data`; `xml_file` and `physics` (see `PhysicsParams`) change the robot;
    `solver` (see `SolverSettings`, e.g. `{"iterations": 100}`) how exactly MuJoCo solves each step, not the robot.
    `reset(options={"command": (vx, vy, yaw_rate)})` holds a command for the episode; `resample_commands=False` keeps
    each episode's sampled command. The keyword arguments are `make_core`'s: `options` (a `PhysicsOptions`) and its
    fields one by one, listed there once.
    """

    metadata = {"render_modes": ["rgb_array"]}  # render_fps: the spec's control rate, set per instance

    def __init__(
        self,
        spec: str | TaskSpec = "anymal_d",
        *,
        render_mode: str | None = None,
        width: int = 640,
        height: int = 480,
        camera: str = "track",
        **kwargs,
    ):
        """kwargs as `make_core`: `options` and the fields of `PhysicsOptions` (xml_file, physics, ...)."""
        self.core = make_core(spec, 1, **kwargs)
        self.task_spec = self.core.spec
        self.observation_space = self.core.single_observation_space
        self.action_space = self.core.single_action_space
        self.metadata = {**self.metadata, "render_fps": int(round(1.0 / self.task_spec.policy_dt))}
        self.render_mode = render_mode
        self._render_size, self._camera, self._renderer = (height, width), camera, None

    @property
    def model(self) -> mujoco.MjModel:
        return self.core.model

    @property
    def data(self) -> mujoco.MjData:
        return self.core.sim.data

    @property
    def physics_params(self) -> PhysicsParams:
        return self.core.params

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        commands = commands_from_options(options, 1, self.task_spec.command)
        obs = self.core.reset(np.array([0]), [seed], commands)
        return obs[0], {"command": self.core.command[0].copy()}

    def step(self, action):
        obs, reward, terminated, truncated, info = self.core.step(np.asarray(action)[None])
        return obs[0], float(reward[0]), bool(terminated[0]), bool(truncated[0]), {k: v[0] for k, v in info.items()}

    def record(self) -> dict[str, np.ndarray]:
        return {k: v[0] for k, v in self.core.record().items()}

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        if self._renderer is None:
            height, width = self._render_size
            self._renderer = mujoco.Renderer(self.model, height=height, width=width)
            atexit.register(self.close)  # an env left open at exit closes before EGL is torn down (no traceback)
        self._renderer.update_scene(self.data, camera=self._camera)
        return self._renderer.render()

    def close(self):
        if self._renderer is not None:
            atexit.unregister(self.close)
            self._renderer.close()
            self._renderer = None

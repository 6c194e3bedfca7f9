"""dm_control suite rewards as pure functions of the world-model state, the foot heights and the action.

The imagined env cannot hand a MuJoCo `Physics` to a suite task, but a suite task's `get_reward(physics)` only calls a
few named quantities on it (`speed()`, `torso_upright()`, ...). `StateReadout` answers those calls from one env's
state, so the reward is dm_control's own code with dm_control's own constants (`cheetah._RUN_SPEED`, the tolerance
margins, ...), none re-typed here. Where the suite reads a quantity the state lacks, the readout returns the closest
state quantity; each method says how close:

- exact: torso height, torso upright (`xmat zz` = minus the projected gravity's z), finger hinge velocity, the
  controls (the action mapped onto the actuators' control ranges), the humanoid's head height (the head is rigidly
  fixed to the torso: torso height plus the head offset rotated by the attitude the projected gravity gives);
- approximate: the suite's centre-of-mass velocities (sensor `torso_subtreelinvel`) are read as the torso frame's
  velocity (planar robots: world-frame forward velocity recovered from the body-frame velocity and the projected
  gravity; the humanoid: the norm of the horizontal velocity, which is all its walk reward reads); the quadruped's
  velocimeter (at the torso site) as the torso frame's body-frame velocity; the hopper's torso-to-foot height of the
  centres of mass as the height difference of the two body frames (the foot height the world model predicts).

`tests/test_suite_reward.py` measures these against the suite's reward in physics.
"""

from __future__ import annotations

import numpy as np

from rwm_gym.spec import SuiteTask, TaskSpec

SUPPORTED = {
    ("cheetah", "run"),
    ("walker", "walk"),
    ("walker", "run"),
    ("walker", "stand"),
    ("hopper", "hop"),
    ("hopper", "stand"),
    ("quadruped", "walk"),
    ("quadruped", "run"),
    ("humanoid", "walk"),
    ("humanoid", "run"),
    ("finger", "spin"),
}
"""(domain, task) pairs whose reward reads only quantities `StateReadout` provides."""


class StateReadout:
    """The `physics` a suite task's `get_reward` sees: one env's state (SI units), foot heights and controls."""

    def __init__(self, values: dict[str, np.ndarray], index: int):
        self._values, self._index = values, index

    def _get(self, name: str) -> np.ndarray:
        return self._values[name][self._index]

    def torso_height(self) -> float:
        """m, exact: the base body's frame height (walker)."""
        return float(self._get("height"))

    def torso_upright(self) -> float:
        """Exact: z-z entry of the torso's rotation, minus the projected gravity's z."""
        return float(self._get("upright"))

    def speed(self) -> float:
        """m/s, approximate: world-frame forward velocity of the torso frame for the subtree COM's (cheetah, hopper)."""
        return float(self._get("forward_velocity"))

    horizontal_velocity = speed  # walker: same sensor, same approximation

    def height(self) -> float:
        """m, approximate: torso frame height minus foot frame height for the COMs' difference (hopper)."""
        return float(self._get("height") - self._get("foot_height")[0])

    def torso_velocity(self) -> np.ndarray:
        """m/s, approximate: body-frame velocity of the torso frame for the torso site's velocimeter (quadruped)."""
        return self._get("local_velocity").copy()

    def head_height(self) -> float:
        """m, exact for a head rigidly fixed to the torso (humanoid)."""
        return float(self._get("head_height"))

    def center_of_mass_velocity(self) -> np.ndarray:
        """m/s, approximate: (horizontal speed of the torso frame, 0, vertical velocity); yaw is not in the state,
        so only the horizontal norm (what the walk and run rewards read) is meaningful (humanoid)."""
        return np.array([self._get("horizontal_speed"), 0.0, self._get("vertical_velocity")])

    def control(self) -> np.ndarray:
        """Exact: the action mapped linearly onto the actuators' control ranges (`data.ctrl`)."""
        return self._get("ctrl").copy()

    def hinge_velocity(self) -> float:
        """rad/s, exact: the spinner hinge's velocity (finger)."""
        return float(self._get("hinge_velocity"))


def _column(spec: TaskSpec, group: str, column: str) -> int | None:
    """Index of `group/column` in the state vector, None if the spec has no such column."""
    name = f"{group}/{column}"
    return spec.state_columns.index(name) if name in spec.state_columns else None


class SuiteReward:
    """The suite task's reward of a dm_control spec, for a batch: `reward(state, foot_height, action) -> (N,)`.

    state (N, S) SI units after the step; foot_height (N, F) m; action (N, A) in [-1, 1], the step's action.
    """

    def __init__(self, spec: TaskSpec):
        from dm_control import suite

        self.spec, self.suite_task = spec, SuiteTask.from_spec(spec)
        key = (self.suite_task.domain, self.suite_task.task)
        if key not in SUPPORTED:
            raise ValueError(
                f"task spec {spec.name}: the reward of dm_control {key[0]}-{key[1]} cannot be computed "
                f"from the world-model state (supported: "
                f"{', '.join(f'{d}-{t}' for d, t in sorted(SUPPORTED))}); name a reward function in the "
                f'spec ([imagination] reward = "module:function") or pass reward_fn='
            )
        env = suite.load(*key, task_kwargs={"random": 0})
        self.task = env.task
        model = env.physics.model.ptr
        low, high = model.actuator_ctrlrange.T
        self._ctrl_mid, self._ctrl_half = (high + low) / 2, (high - low) / 2
        self._head_offset = None
        if key[0] == "humanoid":
            import mujoco

            head = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "head")
            base = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, spec.base_body)
            if model.body_parentid[head] != base or model.body_dofnum[head] != 0:
                raise ValueError(f"task spec {spec.name}: the head must be rigidly fixed to {spec.base_body!r}")
            self._head_offset = model.body_pos[head].copy()  # m, in the torso frame
        self._columns = {
            (g, c): _column(spec, g, c)
            for g in ("base_height", "projected_gravity", "base_lin_vel")
            for c in ("x", "y", "z")
        }
        self._hinge = _column(spec, "joint_vel", "hinge")

    def _vector(self, state: np.ndarray, group: str) -> np.ndarray:
        """The group's x, y, z columns as (N, 3), zeros for the columns a planar spec leaves out."""
        out = np.zeros((len(state), 3))
        for k, axis in enumerate("xyz"):
            index = self._columns[(group, axis)]
            if index is not None:
                out[:, k] = state[:, index]
        return out

    def quantities(self, state: np.ndarray, foot_height: np.ndarray, action: np.ndarray) -> dict[str, np.ndarray]:
        """Everything `StateReadout` answers with, for every env: name -> (N, ...)."""
        state = np.asarray(state, dtype=np.float64)
        values = {
            "foot_height": np.asarray(foot_height, dtype=np.float64),
            "ctrl": self._ctrl_mid + self._ctrl_half * np.asarray(action, dtype=np.float64),
        }
        if self._hinge is not None:
            values["hinge_velocity"] = state[:, self._hinge]
        if self.spec.base_body:
            height_column = self._columns[("base_height", "z")]
            gravity, velocity = self._vector(state, "projected_gravity"), self._vector(state, "base_lin_vel")
            world_z = -gravity  # the world z axis in the base frame: the third row of the base's rotation
            values["height"] = state[:, height_column] if height_column is not None else np.zeros(len(state))
            values["upright"] = world_z[:, 2]
            values["local_velocity"] = velocity
            # planar (rotation about y by pitch p): gravity_body = (sin p, 0, -cos p); world x axis in the base frame
            # = (cos p, 0, sin p) = (-g_z, 0, g_x)
            values["forward_velocity"] = -gravity[:, 2] * velocity[:, 0] + gravity[:, 0] * velocity[:, 2]
            values["vertical_velocity"] = np.sum(world_z * velocity, axis=1)
            values["horizontal_speed"] = np.sqrt(
                np.maximum(np.sum(velocity**2, axis=1) - values["vertical_velocity"] ** 2, 0.0)
            )
            if self._head_offset is not None:
                values["head_height"] = values["height"] + world_z @ self._head_offset
        return values

    def __call__(self, state: np.ndarray, foot_height: np.ndarray, action: np.ndarray) -> np.ndarray:
        values = self.quantities(state, foot_height, action)
        return np.array([float(self.task.get_reward(StateReadout(values, i))) for i in range(len(state))])

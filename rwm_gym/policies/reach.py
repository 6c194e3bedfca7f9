"""A scripted reach for an arm of `dm_control.manipulation`: a damped-least-squares velocity controller that moves the
hand site toward the target site, the goal-directed data a world model needs to learn reaching.

Random actions seldom bring the hand near the target, so a world model trained on them alone has not seen the states
around the goal. This controller reads the arm's joint angles and both sites' positions from the observation (the
state the env exposes, `rwm_gym.task.observation`), computes the hand site's positional Jacobian from the task's own
MuJoCo model at those angles, and commands the joint velocities

    dq = J^T (J J^T + damping^2 I)^-1 v,   v = gain * (target + aim offset - hand), |v| <= max_speed,

scaled as a whole into the velocity servos' ranges (so the hand moves straight toward the target even when a joint
saturates). The fingers are held still. One knob, the policy's `action_noise` sigma, makes the data cover approach,
hover and miss: each episode draws an aim offset of std `aim_noise * sigma` per axis (the hand hovers beside the
target instead of on it), and the actions get temporally correlated noise of std sigma (white noise on velocity
servos at 25 Hz averages out; correlated noise moves the hand off its path). On DMC-Jaco-ReachSite-v0, sigma = 0 ends
within the target's 5 cm on nearly every episode, 0.1 on most, 0.2 on about half, 0.5 on few. Deterministic given
the per-episode generators (see `rwm_gym.policies.base.Policy`).
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from rwm_gym.spec import SuiteTask, TaskSpec
from rwm_gym.task.observation import observation_slices

_SCALAR_JOINTS = (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))
"""Joint types with one coordinate (the model stores the type as a plain integer)."""


@dataclass(frozen=True)
class ReachParams:
    """The controller's numbers; units in the field docs."""

    gain: float = 2.0
    """Commanded hand speed per unit of distance to the aim point (1/s)."""
    max_speed: float = 0.5
    """Bound on the commanded hand speed (m/s)."""
    damping: float = 0.05
    """Damped least squares' damping, limits joint speeds near singular poses (m)."""
    aim_noise: float = 0.1
    """Std of the aim point's per-episode offset from the target, per axis, per unit of action noise (m)."""
    noise_correlation: float = 0.9
    """Step-to-step correlation of the action noise (its std is the policy's `action_noise`)."""


class ReachPolicy:
    """Damped-least-squares reach over N envs: `act(obs (N, O)) -> actions (N, A)` in [-1, 1].

    The spec must declare a `[manipulation]` goal = "reach" (hand and target sites with `site_pos` state columns) and
    the arm's joints in `joint_pos` or in `joint_cos` / `joint_sin` (the unlimited hinges).
    """

    name = "reach"

    def __init__(self, spec: TaskSpec, num_envs: int, *, action_noise: float = 0.0, params: ReachParams | None = None):
        from rwm_gym.task.dmc_environments import load_environment
        from rwm_gym.task.manipulation_reward import ReachGoal, manipulation_goal

        goal = manipulation_goal(spec)
        if not isinstance(goal, ReachGoal):
            raise ValueError(f"task spec {spec.name}: the reach policy needs a [manipulation] goal = 'reach'")
        self.params, self.action_noise, self.spec = params or ReachParams(), action_noise, spec
        task = SuiteTask.from_spec(spec)
        self._environment = load_environment(task.domain, task.task)  # held: composer keeps its model weakly
        self.model: mujoco.MjModel = self._environment.physics.model.ptr
        self.data = mujoco.MjData(self.model)
        self.hand_site = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_SITE, goal.hand_site)
        if self.hand_site < 0:
            raise ValueError(f"task spec {spec.name}: site {goal.hand_site!r} not in dm_control's model")
        self.slices = observation_slices(spec)
        self._hand = self._site_columns(goal.hand_site)
        self._target = self._site_columns(goal.target_site)
        self._angle_readers = self._joint_readers()
        actuated = self.model.actuator_trnid[:, 0]
        if self.model.nu != spec.action_dim or (self.model.actuator_trntype != int(mujoco.mjtTrn.mjTRN_JOINT)).any():
            raise ValueError(f"task spec {spec.name}: the reach policy needs one joint actuator per action")
        self.arm = [a for a, j in enumerate(actuated) if self._reaches(j)]
        """Actuators whose joint moves the hand site (the arm's, not the fingers')."""
        self.dofs = self.model.jnt_dofadr[actuated[self.arm]]
        low, high = self.model.actuator_ctrlrange[self.arm].T
        self.speed_limit = (high - low) / 2  # rad/s, the velocity servos' range (actions map linearly onto it)
        self.mid = (high + low) / 2
        n, a = num_envs, spec.action_dim
        self.offset = np.zeros((n, 3))
        """(N, 3) m, each episode's aim offset."""
        self.noise = np.zeros((n, a))
        self.rngs: list[np.random.Generator] = [np.random.default_rng(i) for i in range(n)]

    def _site_columns(self, site: str) -> np.ndarray:
        start = self.slices["site_pos"].start
        group = next(g for g in self.spec.state if g.name == "site_pos")
        index = [group.columns.index(f"{site}:{c}") for c in "xyz"]
        return start + np.asarray(index)

    def _joint_readers(self) -> list[tuple[int, int, int | None]]:
        """(qpos address, observation index of the angle or its cos, of its sin or None) per named arm joint."""
        readers = []
        groups = {g.name: g for g in self.spec.state}
        for name in ("joint_pos", "joint_cos"):
            if name not in groups or name not in self.slices:
                continue
            for k, joint in enumerate(groups[name].columns):
                j = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_JOINT, joint)
                if j < 0 or int(self.model.jnt_type[j]) not in (
                    int(mujoco.mjtJoint.mjJNT_HINGE),
                    int(mujoco.mjtJoint.mjJNT_SLIDE),
                ):
                    continue
                first = self.slices[name].start + k
                sine = None
                if name == "joint_cos":
                    sine = self.slices["joint_sin"].start + groups["joint_sin"].columns.index(joint)
                readers.append((int(self.model.jnt_qposadr[j]), first, sine))
        return readers

    def _reaches(self, joint: int) -> bool:
        """Whether `joint` is an ancestor of the hand site's body (it moves the hand)."""
        body = self.model.site_bodyid[self.hand_site]
        target = self.model.jnt_bodyid[joint]
        while body > 0:
            if body == target:
                return True
            body = self.model.body_parentid[body]
        return False

    def reset(self, ids: np.ndarray, rngs: list[np.random.Generator]) -> None:
        """Start new episodes in envs `ids`: draw each one's aim offset and initial action noise."""
        ids = np.asarray(ids, dtype=int)
        if len(rngs) != len(ids):
            raise ValueError(f"ReachPolicy.reset: {len(ids)} env ids but {len(rngs)} generators")
        for i, rng in zip(ids, rngs):
            self.rngs[i] = rng
            self.offset[i] = rng.normal(0.0, self.params.aim_noise * self.action_noise, 3)
            self.noise[i] = rng.normal(0.0, self.action_noise, self.noise.shape[1])

    def joint_velocities(self, obs: np.ndarray) -> np.ndarray:
        """(N, arm joints) rad/s, the damped-least-squares joint velocities toward each env's aim point."""
        p = self.params
        obs = np.asarray(obs, dtype=np.float64)
        error = obs[:, self._target] + self.offset - obs[:, self._hand]
        distance = np.linalg.norm(error, axis=1, keepdims=True)
        velocity = error * np.minimum(p.gain, p.max_speed / np.maximum(distance, 1e-9))
        out = np.zeros((len(obs), len(self.arm)))
        jacobian = np.zeros((3, self.model.nv))
        for i, row in enumerate(obs):
            for address, first, sine in self._angle_readers:
                self.data.qpos[address] = row[first] if sine is None else np.arctan2(row[sine], row[first])
            mujoco.mj_kinematics(self.model, self.data)
            mujoco.mj_comPos(self.model, self.data)
            mujoco.mj_jacSite(self.model, self.data, jacobian, None, self.hand_site)
            j = jacobian[:, self.dofs]
            out[i] = j.T @ np.linalg.solve(j @ j.T + p.damping**2 * np.eye(3), velocity[i])
        return out

    def act(self, obs: np.ndarray) -> np.ndarray:
        """Actions (N, A) in [-1, 1] for observations (N, O)."""
        dq = self.joint_velocities(obs)
        arm = (dq - self.mid) / self.speed_limit
        arm = arm / np.maximum(1.0, np.abs(arm).max(axis=1, keepdims=True))  # keep the direction when one saturates
        actions = np.zeros((len(obs), self.spec.action_dim))
        actions[:, self.arm] = arm
        if self.action_noise > 0:
            rho = self.params.noise_correlation
            for i, rng in enumerate(self.rngs):
                fresh = rng.normal(0.0, self.action_noise, self.noise.shape[1])
                self.noise[i] = rho * self.noise[i] + np.sqrt(1.0 - rho**2) * fresh
            actions = actions + self.noise
        return np.clip(actions, -1.0, 1.0)

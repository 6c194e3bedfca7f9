"""What a fixed-base arm's MJCF fixes exactly, computed in the imagined step instead of predicted.

An arm of `dm_control.manipulation` is bolted to the table: its joint angles are the integral of its joint
velocities, and every site on it sits where the forward kinematics of those angles puts it. A world model predicts
each of these columns on its own. On the Jaco reach, a GRU trained on 300 k rows predicted the joint velocities to
0.015 rad/s, but its angles drifted (the pinch site by the forward kinematics of the predicted angles was 15 cm off
the truth after 40 open-loop steps) and its predicted pinch site drifted apart from both. Here the imagined step
keeps what the model learns well (joint velocities, actuator forces, contacts, the brick) and closes the rest:

    angle' = angle + dt * (velocity + velocity') / 2        (the trapezoid over one policy step)
    site'  = forward kinematics of angle'                     (sites on bodies the arm's joints move)

Unlimited hinges, which the state holds as cos and sin, integrate through their angle. Applies to specs of
`dm_control.manipulation` (the arm's base is fixed); `KinematicClosure.of(spec)` is None for every other robot.
"""

from __future__ import annotations

import mujoco
import numpy as np

from rwm_gym.spec import SuiteTask, TaskSpec


class KinematicClosure:
    """Integrates a fixed-base robot's joint angles and places its sites, in place on a batch of states (SI units)."""

    def __init__(self, spec: TaskSpec):
        from rwm_gym.task.dmc_environments import load_environment

        task = SuiteTask.from_spec(spec)
        self._environment = load_environment(task.domain, task.task)  # held: composer keeps its model weakly
        self.model: mujoco.MjModel = self._environment.physics.model.ptr
        self.data = mujoco.MjData(self.model)
        self.dt = spec.policy_dt
        groups, slices = {g.name: g for g in spec.state}, spec.state_slices
        velocity = {name: slices["joint_vel"].start + k for k, name in enumerate(groups["joint_vel"].columns)}
        self.plain: list[tuple[int, int, int]] = []
        """(state column of the angle, of its velocity, qpos address) per joint held as an angle."""
        self.circular: list[tuple[int, int, int, int]] = []
        """(state column of cos, of sin, of the velocity, qpos address) per unlimited hinge."""
        for k, name in enumerate(groups["joint_pos"].columns if "joint_pos" in groups else ()):
            if name in velocity:
                self.plain.append((slices["joint_pos"].start + k, velocity[name], self._qpos(name)))
        for k, name in enumerate(groups["joint_cos"].columns if "joint_cos" in groups else ()):
            sine = slices["joint_sin"].start + groups["joint_sin"].columns.index(name)
            self.circular.append((slices["joint_cos"].start + k, sine, velocity[name], self._qpos(name)))
        moved = self._moved_bodies()
        self.sites: list[tuple[list[int], int]] = []
        """(state columns x, y, z, MuJoCo site id) per site in `site_pos` on a body the joints move."""
        if "site_pos" in groups:
            names = groups["site_pos"].columns
            for start in range(0, len(names), 3):
                site = names[start].rsplit(":", 1)[0]
                site_id = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_SITE, site)
                if site_id >= 0 and int(self.model.site_bodyid[site_id]) in moved:
                    columns = [slices["site_pos"].start + start + c for c in range(3)]
                    self.sites.append((columns, site_id))

    @classmethod
    def of(cls, spec: TaskSpec) -> KinematicClosure | None:
        """The closure of a fixed-base arm's spec (dm_control.manipulation with joint velocities), else None."""
        from rwm_gym.task.dmc_environments import MANIPULATION

        names = {g.name for g in spec.state}
        if spec.extra.get("dm_control", {}).get("domain") != MANIPULATION or "joint_vel" not in names:
            return None
        return cls(spec)

    def _qpos(self, joint: str) -> int:
        j = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_JOINT, joint)
        if j < 0:
            raise ValueError(f"joint {joint!r} of the spec is not in dm_control's model")
        return int(self.model.jnt_qposadr[j])

    def _moved_bodies(self) -> set[int]:
        """Bodies below any joint the state holds an angle of (the sites on them move with those angles)."""
        roots = {int(self.model.jnt_bodyid[j]) for j in range(self.model.njnt) if self._held(j)}
        moved = set()
        for body in range(self.model.nbody):
            b = body
            while b > 0:
                if b in roots:
                    moved.add(body)
                    break
                b = int(self.model.body_parentid[b])
        return moved

    def _held(self, joint: int) -> bool:
        address = int(self.model.jnt_qposadr[joint])
        return any(a == address for *_, a in self.plain) or any(a == address for *_, a in self.circular)

    def apply(self, previous: np.ndarray, state: np.ndarray) -> None:
        """Overwrite `state`'s (N, S) angles (from `previous`'s and both velocities) and its robot sites, in place."""
        half = 0.5 * self.dt
        for angle, velocity, _ in self.plain:
            state[:, angle] = previous[:, angle] + half * (previous[:, velocity] + state[:, velocity])
        for cos, sin, velocity, _ in self.circular:
            theta = np.arctan2(previous[:, sin], previous[:, cos])
            theta = theta + half * (previous[:, velocity] + state[:, velocity])
            state[:, cos], state[:, sin] = np.cos(theta), np.sin(theta)
        if not self.sites:
            return
        qpos = self.data.qpos
        for row in state:
            for angle, _, address in self.plain:
                qpos[address] = row[angle]
            for cos, sin, _, address in self.circular:
                qpos[address] = np.arctan2(row[sin], row[cos])
            mujoco.mj_kinematics(self.model, self.data)
            for columns, site in self.sites:
                row[columns] = self.data.site_xpos[site]

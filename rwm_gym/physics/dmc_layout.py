"""Where a dm_control task's world-model state, contacts and foot heights sit in MuJoCo's arrays.

A dm_control spec (`envs/dmc_*.toml`) names its state groups from a fixed vocabulary, each column one component:

    base_height        ["z"]                     m, height of the base body's frame above the world origin
    projected_gravity  subset of ["x","y","z"]   1, unit gravity in the base frame (attitude without yaw)
    base_lin_vel       subset of ["x","y","z"]   m/s, base-frame linear velocity of the base frame origin
    base_ang_vel       subset of ["x","y","z"]   rad/s, base-frame angular velocity
    joint_pos          joint names               rad (or m for slides), qpos of 1-dof joints
    joint_cos          joint names               1, cos of the angle, for unlimited hinges (e.g. a spinner)
    joint_sin          joint names               1, sin of the angle
    joint_vel          joint names               rad/s (or m/s), qvel of 1-dof joints
    actuator_force     actuator names            N or N·m, force the actuator applied during the last step
    site_pos           "SITE:axis"               m, world position of a site (a hand's pinch site, a reach target)
    body_pos           "BODY:axis"               m, world position of a body's frame (a free object, e.g. a brick)
    body_rot           "BODY:ij", i, j in x,y,z  1, entry (i, j) of the body's rotation matrix (body -> world)
    body_lin_vel       "BODY:axis"               m/s, world-frame linear velocity of the body's frame origin
    body_ang_vel       "BODY:axis"               rad/s, world-frame angular velocity of the body

Planar robots (cheetah, walker, hopper) take the x/z components of the linear quantities and y of the angular one; the
world x position is never part of the state. The site and body groups (for a manipulator and the objects it moves)
name each column `NAME:component`, e.g. `"jaco_arm/jaco_hand/pinchsite:x"`, `"duplo2x4/:zz"`.

Contacts: a contact body is in contact when MuJoCo's collision detection lists a contact between one of its geoms
and a geom of the spec's `[dm_control] contact_partner` body (the floor's `world` for robots on the ground, the
brick for an arm lifting it). The suite's models have zero geom margins, so a listed contact is a touching one; the
manipulation brick's geoms have 0.1 mm margins, so a listed contact there is within 0.1 mm.
"""

from __future__ import annotations

from collections.abc import Callable

import mujoco
import numpy as np

from rwm_gym.spec import TaskSpec

_AXES = {"x": 0, "y": 1, "z": 2}
_ROTATION = {i + j: 3 * _AXES[i] + _AXES[j] for i in _AXES for j in _AXES}
"""Entry "ij" of a rotation matrix -> its index in MuJoCo's row-major 9 (xmat)."""
_OBJECT_GROUPS = ("site_pos", "body_pos", "body_rot", "body_lin_vel", "body_ang_vel")


def _ids(model: mujoco.MjModel, kind: mujoco.mjtObj, names: tuple[str, ...], spec: TaskSpec, what: str) -> np.ndarray:
    ids = np.array([mujoco.mj_name2id(model, kind, name) for name in names], dtype=int)
    if (ids < 0).any():
        missing = names[int(np.flatnonzero(ids < 0)[0])]
        raise ValueError(f"task spec {spec.name}: {what} {missing!r} is not in the dm_control model")
    return ids


Reader = Callable[[mujoco.MjData], np.ndarray]


class DMCLayout:
    """Readers of the spec's state groups, contact flags and foot heights from one MjData."""

    def __init__(self, model: mujoco.MjModel, spec: TaskSpec, partner: str):
        self.model, self.spec = model, spec
        base = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, spec.base_body) if spec.base_body else -1
        self.base = base
        self.readers: list[Reader] = [self._reader(group.name, group.columns) for group in spec.state]
        self.contact_ids = _ids(model, mujoco.mjtObj.mjOBJ_BODY, spec.privileged.contact_bodies, spec, "contact body")
        self.partner = int(_ids(model, mujoco.mjtObj.mjOBJ_BODY, (partner,), spec, "contact partner")[0])
        self.feet = _ids(model, mujoco.mjtObj.mjOBJ_BODY, spec.privileged.feet, spec, "foot body")
        actuators = _ids(model, mujoco.mjtObj.mjOBJ_ACTUATOR, spec.actuator.joints, spec, "actuator")
        if len(actuators) != model.nu or (actuators != np.arange(model.nu)).any():
            raise ValueError(
                f"task spec {spec.name}: actuator.joints must list the model's {model.nu} actuators in model order"
            )

    def _reader(self, name: str, columns: tuple[str, ...]) -> Reader:
        m, spec = self.model, self.spec
        if name in ("base_height", "projected_gravity", "base_lin_vel", "base_ang_vel"):
            if self.base < 0:
                raise ValueError(f"task spec {spec.name}: state group {name!r} needs task.base_body in the model")
            if any(c not in _AXES for c in columns):
                raise ValueError(f"task spec {spec.name}: state group {name!r} columns must be among x, y, z")
            axes, base = [_AXES[c] for c in columns], self.base
            if name == "base_height":
                return lambda d: d.xpos[base, axes]
            if name == "projected_gravity":
                return lambda d: -d.xmat[base].reshape(3, 3)[2, axes]
            offset = 3 if name == "base_lin_vel" else 0

            def velocity(d: mujoco.MjData) -> np.ndarray:
                out = np.zeros(6)
                mujoco.mj_objectVelocity(m, d, mujoco.mjtObj.mjOBJ_XBODY, base, out, 1)  # body frame, not inertial
                return out[offset : offset + 3][axes]

            return velocity
        if name == "actuator_force":
            ids = _ids(m, mujoco.mjtObj.mjOBJ_ACTUATOR, columns, spec, f"state group {name!r} actuator")
            return lambda d: d.actuator_force[ids]
        if name in ("joint_pos", "joint_cos", "joint_sin", "joint_vel"):
            joints = _ids(m, mujoco.mjtObj.mjOBJ_JOINT, columns, spec, f"state group {name!r} joint")
            if (m.jnt_type[joints] == mujoco.mjtJoint.mjJNT_FREE).any() or (
                m.jnt_type[joints] == mujoco.mjtJoint.mjJNT_BALL
            ).any():
                raise ValueError(f"task spec {spec.name}: state group {name!r} takes only hinge or slide joints")
            if name == "joint_vel":
                dofs = m.jnt_dofadr[joints]
                return lambda d: d.qvel[dofs]
            adr = m.jnt_qposadr[joints]
            fn = {"joint_pos": lambda q: q, "joint_cos": np.cos, "joint_sin": np.sin}[name]
            return lambda d: fn(d.qpos[adr])
        if name in _OBJECT_GROUPS:
            return self._object_reader(name, columns)
        raise ValueError(f"task spec {spec.name}: unknown state group {name!r} for a dm_control task")

    def _object_reader(self, name: str, columns: tuple[str, ...]) -> Reader:
        """A site or body group: columns `NAME:component`, read from the site's or body's world pose or velocity."""
        m, spec = self.model, self.spec
        kind = mujoco.mjtObj.mjOBJ_SITE if name == "site_pos" else mujoco.mjtObj.mjOBJ_BODY
        components = _ROTATION if name == "body_rot" else _AXES
        objects, index = [], []
        for column in columns:
            object_name, sep, component = column.rpartition(":")
            if not sep or component not in components:
                raise ValueError(
                    f"task spec {spec.name}: state group {name!r} column {column!r} is not NAME:component "
                    f"(components: {', '.join(components)})"
                )
            objects.append(object_name)
            index.append(components[component])
        ids = _ids(m, kind, tuple(objects), spec, f"state group {name!r} {'site' if name == 'site_pos' else 'body'}")
        if name == "site_pos":
            return lambda d: d.site_xpos[ids, index]
        if name == "body_pos":
            return lambda d: d.xpos[ids, index]
        if name == "body_rot":
            return lambda d: d.xmat[ids, index]
        offset = 3 if name == "body_lin_vel" else 0

        def velocity(d: mujoco.MjData) -> np.ndarray:
            out, value = np.zeros(len(ids)), np.zeros(6)
            for k, (body, component) in enumerate(zip(ids, index)):
                mujoco.mj_objectVelocity(m, d, mujoco.mjtObj.mjOBJ_XBODY, body, value, 0)  # world-aligned frame
                out[k] = value[offset + component]
            return out

        return velocity

    def state(self, data: mujoco.MjData) -> np.ndarray:
        """The world-model state, (S,) float32."""
        return np.concatenate([read(data) for read in self.readers]).astype(np.float32)

    def contact(self, data: mujoco.MjData) -> np.ndarray:
        """Contact flag of each contact body with the partner, (C,) bool."""
        flags = np.zeros(len(self.contact_ids), dtype=bool)
        if data.ncon == 0 or len(self.contact_ids) == 0:
            return flags
        bodies = self.model.geom_bodyid[np.stack([data.contact.geom1, data.contact.geom2], axis=1)]  # (ncon, 2)
        with_partner = (bodies == self.partner).any(axis=1)
        touching = bodies[with_partner].ravel()
        return np.isin(self.contact_ids, touching)

    def foot_height(self, data: mujoco.MjData) -> np.ndarray:
        """m, height of each foot body's frame, (F,) float32."""
        return data.xpos[self.feet, 2].astype(np.float32)

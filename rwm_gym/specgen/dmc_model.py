"""What every dm_control spec reads off the model: its bodies and names, the state layout, and the tables a suite
task and a manipulation task share (`from_dmc`, `from_manipulation`).

The state follows the vocabulary of `rwm_gym.physics.dmc_layout`:

- a floating base (the first body under the world with a free joint, or with two or more joints none of which is
  actuated, e.g. cheetah's rootx/rootz/rooty) gives `base_height` (if it moves vertically), the components of
  `projected_gravity` its rotations change, and the components of `base_lin_vel` / `base_ang_vel` its joints move
  along / about; its horizontal position is left out (the tasks do not depend on where the robot is);
- every other hinge or slide joint gives `joint_pos` (limited joints and slides) or `joint_cos` and `joint_sin`
  (unlimited hinges), and `joint_vel`; the actuators give `actuator_force`.
"""

from __future__ import annotations

import mujoco
import numpy as np

from rwm_gym.specgen.draft import Table

_AXES = "xyz"
_FREE, _BALL, _SLIDE, _HINGE = (
    int(mujoco.mjtJoint.mjJNT_FREE),
    int(mujoco.mjtJoint.mjJNT_BALL),
    int(mujoco.mjtJoint.mjJNT_SLIDE),
    int(mujoco.mjtJoint.mjJNT_HINGE),
)


def _axis_name(axis: np.ndarray) -> str | None:
    """ "x", "y" or "z" for a unit axis along a coordinate axis, else None."""
    k = int(np.argmax(np.abs(axis)))
    return _AXES[k] if np.isclose(abs(axis[k]), 1.0) else None


def children(model: mujoco.MjModel, body: int) -> list[int]:
    """The bodies whose parent is `body` (0: the world)."""
    return [b for b in range(1, model.nbody) if model.body_parentid[b] == body]


def subtree(model: mujoco.MjModel, body: int) -> list[int]:
    """`body` and every body below it."""
    out = [body]
    for child in children(model, body):
        out += subtree(model, child)
    return out


def name_of(model: mujoco.MjModel, kind: mujoco.mjtObj, i: int) -> str:
    """The name of object `i` of `kind`, or "" where it has none."""
    return mujoco.mj_id2name(model, kind, i) or ""


def find_base(model: mujoco.MjModel) -> int | None:
    """The floating base: a body under the world with a free joint, or with >= 2 joints none of them actuated."""
    actuated = {
        int(model.actuator_trnid[a, 0])
        for a in range(model.nu)
        if int(model.actuator_trntype[a]) == int(mujoco.mjtTrn.mjTRN_JOINT)
    }
    for body in children(model, 0):
        joints = list(range(model.body_jntadr[body], model.body_jntadr[body] + model.body_jntnum[body]))
        if any(int(model.jnt_type[j]) == _FREE for j in joints):
            return body
        if len(joints) >= 2 and not actuated & set(joints):
            return body
    return None


def base_groups(model: mujoco.MjModel, base: int) -> tuple[list[tuple[str, list[str], str]], list[int]]:
    """The base's state groups [(name, columns, unit)] and the joints it owns."""
    joints = list(range(model.body_jntadr[base], model.body_jntadr[base] + model.body_jntnum[base]))
    if any(int(model.jnt_type[j]) == _FREE for j in joints):
        xyz = list(_AXES)
        return [
            ("base_height", ["z"], "m"),
            ("projected_gravity", xyz, "1"),
            ("base_lin_vel", xyz, "m/s"),
            ("base_ang_vel", xyz, "rad/s"),
        ], joints
    slides, hinges = [], []
    for j in joints:
        axis = _axis_name(model.jnt_axis[j])
        if axis is None or int(model.jnt_type[j]) not in (_SLIDE, _HINGE):
            raise ValueError(
                f"base joint {name_of(model, mujoco.mjtObj.mjOBJ_JOINT, j)!r} is not a slide or hinge "
                f"along a coordinate axis"
            )
        (slides if int(model.jnt_type[j]) == _SLIDE else hinges).append(axis)
    groups = []
    if "z" in slides:
        groups.append(("base_height", ["z"], "m"))
    tilting = [a for a in hinges if a != "z"]  # a rotation about the vertical leaves gravity where it is
    if tilting:
        gravity = sorted({c for a in tilting for c in _AXES if c != a})
        groups.append(("projected_gravity", gravity, "1"))
    if slides:
        groups.append(("base_lin_vel", sorted(slides), "m/s"))
    if hinges:
        groups.append(("base_ang_vel", sorted(hinges), "rad/s"))
    return groups, joints


def layout(
    model: mujoco.MjModel, objects: tuple[int, ...] = ()
) -> tuple[str, list[tuple[str, list[str], str]], list[str]]:
    """(base body name or "", state groups [(name, columns, unit)], notes on what was chosen).

    objects: free bodies a fixed-base manipulator moves (their joints are left out here, and no base is looked for).
    """
    notes = []
    base = None if objects else find_base(model)
    groups, base_joints = base_groups(model, base) if base is not None else ([], [])
    base_joints += [
        j for b in objects for j in range(model.body_jntadr[b], model.body_jntadr[b] + model.body_jntnum[b])
    ]
    base_name = name_of(model, mujoco.mjtObj.mjOBJ_BODY, base) if base is not None else ""
    if base is not None:
        notes.append(
            f"floating base {base_name!r}: state groups {', '.join(g[0] for g in groups)}; its horizontal "
            f"position is not in the state (add it by hand if the reward needs it)"
        )
    positions, angles, velocities = [], [], []
    for j in range(model.njnt):
        if j in base_joints:
            continue
        name = name_of(model, mujoco.mjtObj.mjOBJ_JOINT, j)
        kind = int(model.jnt_type[j])
        if kind in (_FREE, _BALL):
            raise ValueError(
                f"joint {name!r} is a free or ball joint outside the base; the dm_control layout "
                "takes hinges and slides only"
            )
        if not name:
            raise ValueError(f"joint {j} has no name; the spec names every state column")
        unlimited_hinge = kind == _HINGE and not model.jnt_limited[j]
        (angles if unlimited_hinge else positions).append(name)
        velocities.append(name)
    if angles:
        notes.append(f"unlimited hinges {', '.join(angles)} enter as cos and sin of the angle")
    groups += [
        (n, cols, unit)
        for n, cols, unit in (
            ("joint_pos", positions, "rad or m"),
            ("joint_cos", angles, "1"),
            ("joint_sin", angles, "1"),
            ("joint_vel", velocities, "rad/s or m/s"),
        )
        if cols
    ]
    actuators = [name_of(model, mujoco.mjtObj.mjOBJ_ACTUATOR, a) for a in range(model.nu)]
    if not all(actuators):
        raise ValueError("every actuator needs a name (the spec lists them as actuator.joints)")
    groups.append(("actuator_force", actuators, "N or N·m"))
    return base_name, groups, notes


def task_table_of(values: dict, time_limit_note: str) -> Table:
    """The [task] table of a dm_control spec, its timing fields annotated (`time_limit_note` for episode_steps)."""
    return Table(
        "task",
        values,
        {
            "policy_dt": "s, dm_control's control timestep (checked at load)",
            "physics_dt": "s, the model's timestep (checked at load)",
            "episode_steps": time_limit_note,
        },
    )


def observation_table(groups: list[tuple[str, list[str], str]]) -> Table:
    """The policy observation of a dm_control spec: every state group, then the last action."""
    return Table(
        "observation",
        {"groups": [g[0] for g in groups] + ["last_action"]},
        note="Policy observation: the state, then the last action.",
    )


def spec_header(what: str, name: str) -> list[str]:
    """The comment lines that open a spec written by `rwm-gym spec --from-dmc NAME`."""
    return [
        f"Task spec: {what}, written by `rwm-gym spec --from-dmc {name}`.",
        "dm_control's own MJCF model and task code (initial states, reward) run underneath; this file declares",
        "how the world-model state, contacts and observation are read from its physics",
        "(see rwm_gym/physics/dmc_layout.py). Units: SI (m, s, rad, N, N·m).",
    ]

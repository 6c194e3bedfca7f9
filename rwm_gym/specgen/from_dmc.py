"""A task spec for any dm_control suite task, read off the suite's own model (`rwm-gym spec --from-dmc DOMAIN-TASK`).

`--from-dmc manipulation-TASK` drafts a `dm_control.manipulation` task instead (`rwm_gym.specgen.from_manipulation`).

The state follows the vocabulary of `rwm_gym.physics.dmc_layout`:

- a floating base (the first body under the world with a free joint, or with two or more joints none of which is
  actuated, e.g. cheetah's rootx/rootz/rooty) gives `base_height` (if it moves vertically), the components of
  `projected_gravity` its rotations change, and the components of `base_lin_vel` / `base_ang_vel` its joints move
  along / about; its horizontal position is left out (the tasks do not depend on where the robot is);
- every other hinge or slide joint gives `joint_pos` (limited joints and slides) or `joint_cos` and `joint_sin`
  (unlimited hinges), and `joint_vel`; the actuators give `actuator_force`.

Contacts are those of the robot's colliding bodies with the world's geoms (the floor) when the world has a plane;
feet are the contact bodies named like a foot. The cheetah's generated layout equals the shipped
`envs/dmc_cheetah_run.toml` column for column (tested).
"""

from __future__ import annotations

import mujoco
import numpy as np

from rwm_gym.specgen.draft import SpecDraft, Table

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


def _children(model: mujoco.MjModel, body: int) -> list[int]:
    return [b for b in range(1, model.nbody) if model.body_parentid[b] == body]


def _subtree(model: mujoco.MjModel, body: int) -> list[int]:
    out = [body]
    for child in _children(model, body):
        out += _subtree(model, child)
    return out


def _name(model: mujoco.MjModel, kind: mujoco.mjtObj, i: int) -> str:
    return mujoco.mj_id2name(model, kind, i) or ""


def find_base(model: mujoco.MjModel) -> int | None:
    """The floating base: a body under the world with a free joint, or with >= 2 joints none of them actuated."""
    actuated = {
        int(model.actuator_trnid[a, 0])
        for a in range(model.nu)
        if int(model.actuator_trntype[a]) == int(mujoco.mjtTrn.mjTRN_JOINT)
    }
    for body in _children(model, 0):
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
                f"base joint {_name(model, mujoco.mjtObj.mjOBJ_JOINT, j)!r} is not a slide or hinge "
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
    base_name = _name(model, mujoco.mjtObj.mjOBJ_BODY, base) if base is not None else ""
    if base is not None:
        notes.append(
            f"floating base {base_name!r}: state groups {', '.join(g[0] for g in groups)}; its horizontal "
            f"position is not in the state (add it by hand if the reward needs it)"
        )
    positions, angles, velocities = [], [], []
    for j in range(model.njnt):
        if j in base_joints:
            continue
        name = _name(model, mujoco.mjtObj.mjOBJ_JOINT, j)
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
    actuators = [_name(model, mujoco.mjtObj.mjOBJ_ACTUATOR, a) for a in range(model.nu)]
    if not all(actuators):
        raise ValueError("every actuator needs a name (the spec lists them as actuator.joints)")
    groups.append(("actuator_force", actuators, "N or N·m"))
    return base_name, groups, notes


def contacts(model: mujoco.MjModel, base_name: str, feet: list[str] | None) -> tuple[list[str], list[str], list[str]]:
    """(contact bodies, feet, notes): the robot's colliding bodies when the world has a plane to touch."""
    world_planes = [
        g
        for g in range(model.ngeom)
        if model.geom_bodyid[g] == 0 and int(model.geom_type[g]) == int(mujoco.mjtGeom.mjGEOM_PLANE)
    ]
    if not world_planes:
        return [], [], ["no floor plane in the world: no contact flags"]
    robot = [b for root in _children(model, 0) for b in _subtree(model, root)]
    colliding = [
        b
        for b in robot
        if any(
            (model.geom_contype[g] | model.geom_conaffinity[g]) and model.geom_bodyid[g] == b
            for g in range(model.ngeom)
        )
    ]
    names = [_name(model, mujoco.mjtObj.mjOBJ_BODY, b) for b in colliding]
    names = [n for n in names if n]
    if feet is None:
        feet = [n for n in names if "foot" in n.lower()]
    unknown = sorted(set(feet) - set(names))
    if unknown:
        raise ValueError(f"--feet: {unknown[0]!r} is not a colliding body of the model (bodies: {', '.join(names)})")
    note = f"contact flags of {', '.join(names)} with the world's geoms; feet: {', '.join(feet) or 'none'}"
    return names, list(feet), [note]


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


def dmc_draft(domain: str, task: str, feet: list[str] | None = None) -> SpecDraft:
    """The spec of suite task `domain`-`task` with placeholder normalisation (see `draft.fill_normalization`)."""
    from dm_control import suite

    from rwm_gym.physics.dmc_environments import MANIPULATION

    if domain == MANIPULATION:
        from rwm_gym.specgen.from_manipulation import manipulation_draft

        return manipulation_draft(task)
    try:
        env = suite.load(domain, task, task_kwargs={"random": 0})
    except (ValueError, KeyError) as err:
        raise ValueError(f"dm_control has no task {domain}-{task} ({err})") from None
    model: mujoco.MjModel = env.physics.model.ptr
    base, groups, notes = layout(model)
    contact_bodies, feet, contact_notes = contacts(model, base, feet)
    limit = float(env._step_limit)  # the suite's time limit in control steps (inf: none)
    episode_steps = int(limit) if np.isfinite(limit) else 1000
    if not np.isfinite(limit):
        notes.append("the suite task has no time limit: episodes truncated after 1000 steps")
    from rwm_gym.task.suite_reward import SUPPORTED

    title = "".join(p.capitalize() for p in f"{domain}_{task}".replace("-", "_").split("_"))
    if (domain, task) not in SUPPORTED:
        notes.append(
            f"the imagined env cannot compute dm_control's {domain}-{task} reward from the predicted state: "
            f'give it a reward entry point ([imagination] reward = "module:function") or reward_fn='
        )
    task_table = {
        "name": f"DMC-{title}",
        "physics_env_id": f"DMC-{title}-v0",
        "imagined_env_id": f"RWM-{title}-v0",
        "policy_dt": float(env.control_timestep()),
        "physics_dt": float(env.physics.timestep()),
        "episode_steps": episode_steps,
    }
    if base:
        task_table["base_body"] = base
    actuators = groups[-1][1]
    tables = [
        task_table_of(task_table, "the suite's time limit; suite tasks never terminate"),
        Table("dm_control", {"domain": domain, "task": task, "contact_partner": "world"}),
        Table(
            "actuator",
            {"joints": actuators},
            note="The model's actuators in model order; actions in [-1, 1] map linearly onto each control range.",
        ),
    ]
    for name, columns, unit in groups:
        tables.append(
            Table(
                "state",
                {
                    "name": name,
                    "columns": columns,
                    "unit": unit,
                    "mean": [0.0] * len(columns),
                    "std": [1.0] * len(columns),
                },
                array=True,
            )
        )
    privileged = {"contact_bodies": contact_bodies, "feet": feet}
    if feet:
        privileged["foot_height_std"] = 0.1
    tables.append(
        Table(
            "privileged",
            privileged,
            {"foot_height_std": "m, std of the foot heights in the same data"},
            note="No termination: suite tasks run to their time limit.",
        )
    )
    tables.append(observation_table(groups))
    header = spec_header(f"dm_control suite {domain}-{task}", f"{domain}-{task}")
    return SpecDraft(header, tables, notes + contact_notes)

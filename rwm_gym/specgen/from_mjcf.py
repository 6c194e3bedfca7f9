"""A velocity-tracking task spec for a legged robot of one's own, from its MJCF (`rwm-gym spec --mjcf robot.xml`).

The physics env (`rwm_gym.physics.locomotion`) reads a robot through fixed names: a position actuator named after
each joint, a touch sensor `contact_NAME` per contact body, a site and a geom named after each foot, a named
keyframe. Few MJCF files have them, so the generator writes a copy of the model that does (`OUT.rwm.xml`, beside the
spec) and leaves the user's file alone:

- base: `--base`, else the body with the free joint; joints: every hinge below it, in model order;
- feet: `--feet`, else the leaf bodies with a geom that touches the floor, kept where they stand on it at the default
  pose (a humanoid's hands are leaves too); a geom collides through its contype/conaffinity or an explicit `<pair>`
  (`rwm_gym.specgen.mjcf_feet`). A foot's point is its lowest sphere or capsule end (or a box's bottom face), given a
  site named after its geom; thighs are the feet's nearest ancestors with colliding geoms (a humanoid's knees);
- touch sensors: a sphere around a one-geom foot, a box around a foot's sole of several geoms (a G1's box and three
  capsules), a box around the base's and each thigh's geoms; MuJoCo's touch sensors count pair contacts too;
- actuators: the joints' actuators are replaced by position servos; each joint's kp, kd and effort limit come from
  the file where it has them (position servos, force ranges, a motor's control range, a joint's
  `actuatorfrcrange`), else from the robot's weight (printed);
- default pose: the keyframe `--keyframe` names, else the first, else qpos0 lowered until the feet touch the floor
  (a plane is added if the world has none).

Reward weights, reset noise and action scale are ANYmal D's (`envs/anymal_d.toml`), a two-footed robot's reward the
shipped G1's (`envs/g1.toml`, with a `base_height` state group); command speeds follow `command_speed` (Froude
number 0.4, capped at ANYmal D's 1 m/s); `fast_physics` gives the copy ANYmal D's solver settings. Every such choice
is listed in the spec's header.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, replace
from pathlib import Path

import mujoco
import numpy as np

from rwm_gym.spec import load_spec
from rwm_gym.specgen.dmc_model import name_of as _name
from rwm_gym.specgen.dmc_model import subtree as _subtree
from rwm_gym.specgen.draft import SpecDraft, Table
from rwm_gym.specgen.fast_physics import apply_fast_physics, compare
from rwm_gym.specgen.mjcf_feet import (
    FootPoint,
    colliding_geoms,
    floor_geoms,
    foot_point,
    leaf_bodies,
    sole_box,
    standing_feet,
)
from rwm_gym.specgen.mjcf_servos import GRAVITY, Servo, gains
from rwm_gym.specgen.toml_text import significant

_BODY, _GEOM, _SITE = mujoco.mjtObj.mjOBJ_BODY, mujoco.mjtObj.mjOBJ_GEOM, mujoco.mjtObj.mjOBJ_SITE


def _find_base(model: mujoco.MjModel, base: str | None) -> int:
    if base:
        b = mujoco.mj_name2id(model, _BODY, base)
        if b < 0:
            raise ValueError(f"--base {base!r}: no such body")
    else:
        free = [j for j in range(model.njnt) if int(model.jnt_type[j]) == int(mujoco.mjtJoint.mjJNT_FREE)]
        if not free:
            raise ValueError("no body has a free joint: a legged robot needs a free-floating base (<freejoint/>)")
        b = int(model.jnt_bodyid[free[0]])
    j = int(model.body_jntadr[b])
    if model.body_jntnum[b] != 1 or int(model.jnt_type[j]) != int(mujoco.mjtJoint.mjJNT_FREE) or model.jnt_qposadr[j]:
        raise ValueError(f"base {_name(model, _BODY, b)!r} must have exactly one joint, the model's first, a free one")
    return b


def _enclosing_box(model: mujoco.MjModel, body: int) -> tuple[np.ndarray, np.ndarray]:
    """(centre, half sizes) in the body frame of a box around the body's colliding geoms, 10 % larger."""
    geoms = colliding_geoms(model, body) or list(
        range(model.body_geomadr[body], model.body_geomadr[body] + model.body_geomnum[body])
    )
    if not geoms:
        raise ValueError(f"body {_name(model, _BODY, body)!r} has no geom to sense contacts with")
    low = np.min([model.geom_pos[g] - model.geom_rbound[g] for g in geoms], axis=0)
    high = np.max([model.geom_pos[g] + model.geom_rbound[g] for g in geoms], axis=0)
    return (low + high) / 2, 1.1 * (high - low) / 2


def _task_name(name: str | None, model_name: str) -> str:
    raw = name or model_name or "MyRobot"
    parts = [p for p in re.split(r"[^0-9A-Za-z]+", raw) if p]
    out = "".join(p[0].upper() + p[1:] for p in parts)
    if not out or not out[0].isalpha():
        raise ValueError(f"task name {raw!r}: needs a letter first (pass --name)")
    return out


@dataclass
class _Legs:
    """The robot below the base body, as the MJCF gives it: ids index the compiled model."""

    base: int
    base_name: str
    joint_ids: list[int]
    joints: list[str]
    """The hinge joints' names, in model order."""
    feet: list[int]
    thighs: list[int]
    """Each foot's nearest ancestor with a colliding geom, other than the base (`_thighs`)."""
    thigh_names: list[str]


@dataclass
class _Pose:
    """The default pose: the keyframe's name, qpos, each foot's point (`FootPoint`), the joint angles (rad), and the
    base's height (m)."""

    keyframe: str
    qpos: np.ndarray
    points: list[FootPoint]
    default_pose: list[float]
    height: float


def legged_draft(
    mjcf: str | Path,
    *,
    base: str | None = None,
    feet: list[str] | None = None,
    name: str | None = None,
    fast_physics: bool = False,
    keyframe: str | None = None,
) -> tuple[SpecDraft, str]:
    """(draft spec, text of the rwm-ready MJCF copy). The draft's `task.model` is set by the caller. `fast_physics`:
    the copy takes ANYmal D's solver settings (`rwm_gym.specgen.fast_physics`), measured against the file's own;
    `keyframe`: the standing keyframe's name (default: the file's first)."""
    path = Path(mjcf)
    mj, model = _load(path)
    notes: list[str] = []
    legs, pose = _find_pose(mj, model, _find_legs(model, base, feet, notes), keyframe, bool(feet), notes)
    mass = float(model.body_subtreemass[legs.base])
    servo = gains(model, legs.joint_ids, mass, pose.height, len(legs.feet), notes)
    _add_floor_camera_and_servos(mj, model, legs, pose, servo, notes)
    foot_names = _add_contact_sensors(mj, model, legs, pose)
    own = _compile_copy(mj, path)
    if fast_physics:
        notes.append(apply_fast_physics(mj, float(model.opt.timestep)))
        fast = _compile_copy(mj, path)
        keyframe = mujoco.mj_name2id(fast, mujoco.mjtObj.mjOBJ_KEY, pose.keyframe)
        notes.append(compare(own, fast, keyframe).line())
        model = fast
    dt, policy_dt, speed = _timing(model, pose.height, notes)
    task_name = _task_name(name, mj.modelname)
    tables = _tables(task_name, legs, pose, servo, foot_names, dt, policy_dt, speed)
    if len(foot_names) == 2:
        _biped(tables, pose.height, notes)
    robot_line = (
        f"Robot: {mass:.3g} kg, {len(legs.joints)} joints, {len(foot_names)} feet, base {legs.base_name!r} "
        f"standing at {pose.height:.3f} m. Units: SI (m, s, rad, N, N·m, kg)."
    )
    header = [f"Task spec: {task_name} velocity tracking, written by `rwm-gym spec --mjcf {path.name}`.", robot_line]
    return SpecDraft(header, tables, notes), mj.to_xml()


def _compile_copy(mj: mujoco.MjSpec, path: Path) -> mujoco.MjModel:
    try:
        return mj.compile()
    except ValueError as err:
        raise ValueError(f"{path}: the rwm-ready copy does not compile ({' '.join(str(err).split())[:200]})") from None


def _load(path: Path) -> tuple[mujoco.MjSpec, mujoco.MjModel]:
    """The MJCF as an editable spec (its asset folders made absolute, for a copy that lives elsewhere) and compiled."""
    if not path.is_file():
        raise FileNotFoundError(f"MJCF {path} not found")
    try:
        mj = mujoco.MjSpec.from_file(str(path))
        model = mj.compile()
    except ValueError as err:  # MuJoCo's XML and compile errors, several lines long
        raise ValueError(f"{path}: MuJoCo cannot load it ({' '.join(str(err).split())[:200]})") from None
    for attr in ("meshdir", "texturedir"):  # the copy lives elsewhere: point it at the original's asset folders
        setattr(mj, attr, str((path.resolve().parent / (getattr(mj, attr) or "")).resolve()))
    return mj, model


def _find_legs(model: mujoco.MjModel, base: str | None, feet: list[str] | None, notes: list[str]) -> _Legs:
    """The base (`--base`, else the body with the free joint), its hinge joints, and the candidate feet (`--feet`, else
    every leaf body with a geom that touches the floor; `_find_pose` keeps those on the floor)."""
    b = _find_base(model, base)
    base_name = _name(model, _BODY, b)
    robot = _subtree(model, b)
    joint_ids, joints = _hinge_joints(model, b, robot, base_name)
    touching = floor_geoms(model)
    if not any(model.geom_bodyid[g] in robot for g in touching):
        raise ValueError(
            f"no geom of the robot below {base_name!r} can touch the floor (collision bits off and no <pair> with a "
            f"world geom)"
        )
    if feet:
        foot_bodies = [mujoco.mj_name2id(model, _BODY, f) for f in feet]
        missing = [f for f, i in zip(feet, foot_bodies) if i < 0 or i not in robot or i == b]
        if missing:
            raise ValueError(f"--feet: {missing[0]!r} is not a body of the robot below {base_name!r}")
    else:
        foot_bodies = leaf_bodies(model, b, robot)
        if not foot_bodies:
            raise ValueError(
                f"no leaf body below {base_name!r} has a geom that touches the floor: name the feet with --feet BODY"
            )
    return _Legs(b, base_name, joint_ids, joints, foot_bodies, [], [])


def _hinge_joints(model: mujoco.MjModel, b: int, robot: list[int], base_name: str) -> tuple[list[int], list[str]]:
    """Ids and names of the joints below the base `b`, which must all be named hinges."""
    joint_ids = [j for j in range(model.njnt) if model.jnt_bodyid[j] in robot and j != model.body_jntadr[b]]
    if any(int(model.jnt_type[j]) != int(mujoco.mjtJoint.mjJNT_HINGE) for j in joint_ids) or not joint_ids:
        raise ValueError(f"the robot below {base_name!r} must move by hinge joints only (and have some)")
    joints = [_name(model, mujoco.mjtObj.mjOBJ_JOINT, j) for j in joint_ids]
    if not all(joints):
        raise ValueError("every hinge joint needs a name (the spec lists them)")
    return joint_ids, joints


def _thighs(model: mujoco.MjModel, legs: _Legs) -> list[int]:
    """Each foot's nearest ancestor below the base with a colliding geom (a quadruped's thigh or shank, a humanoid's
    knee), once each."""
    thighs: list[int] = []
    for f in legs.feet:
        t = int(model.body_parentid[f])
        while t not in (legs.base, 0) and not colliding_geoms(model, t):
            t = int(model.body_parentid[t])
        if t not in (legs.base, 0) and t not in thighs:
            thighs.append(t)
    return thighs


def _keyframe(model: mujoco.MjModel, keyframe: str | None) -> int:
    """The keyframe index `--keyframe` names (-1: none named and the file has none), else the first."""
    if keyframe is None:
        return 0 if model.nkey else -1
    k = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_KEY, keyframe)
    if k < 0:
        names = [_name(model, mujoco.mjtObj.mjOBJ_KEY, i) for i in range(model.nkey)]
        listed = ", ".join(repr(n) for n in names if n) or "none named"
        raise ValueError(f"--keyframe {keyframe!r}: no such keyframe in the file (it has: {listed})")
    return k


def _find_pose(
    mj: mujoco.MjSpec, model: mujoco.MjModel, legs: _Legs, keyframe: str | None, given: bool, notes: list[str]
) -> tuple[_Legs, _Pose]:
    """The feet (the given ones, else the candidates on the floor: `standing_feet`) and the default pose: the keyframe
    `keyframe` names, else the first (named "home" in the copy if it has no name), else qpos0 lowered until the feet
    touch the floor."""
    data = mujoco.MjData(model)
    k = _keyframe(model, keyframe)
    if k >= 0:
        name = _name(model, mujoco.mjtObj.mjOBJ_KEY, k) or "home"
        mj.keys[k].name = name
        qpos = model.key_qpos[k].copy()
        other = "" if keyframe else " (the file's first; --keyframe NAME for another)"
        notes.append(f"default pose: keyframe {name!r}{other}")
    else:
        name, qpos = "home", model.qpos0.copy()
    data.qpos[:] = qpos
    mujoco.mj_forward(model, data)
    if not given:
        where = f"keyframe {name!r}" if k >= 0 else "qpos0"
        legs = replace(legs, feet=standing_feet(model, data, legs.feet, where, notes))
    thighs = _thighs(model, legs)
    legs = replace(legs, thighs=thighs, thigh_names=[_name(model, _BODY, t) for t in thighs])
    points = [foot_point(model, data, f) for f in legs.feet]
    if k < 0:
        lowest = min(
            float((data.xpos[f] + data.xmat[f].reshape(3, 3) @ p.point)[2]) - p.radius
            for f, p in zip(legs.feet, points)
        )
        qpos[2] -= lowest
        data.qpos[:] = qpos
        mujoco.mj_forward(model, data)
        notes.append(
            f"default pose: qpos0 with the base at {qpos[2]:.3f} m so the feet touch the floor (keyframe 'home' added)"
        )
    default_pose = [significant(float(qpos[model.jnt_qposadr[j]]), 6) for j in legs.joint_ids]
    return legs, _Pose(name, qpos, points, default_pose, float(data.xpos[legs.base, 2]))


def _add_floor_camera_and_servos(
    mj: mujoco.MjSpec,
    model: mujoco.MjModel,
    legs: _Legs,
    pose: _Pose,
    servo: Servo,
    notes: list[str],
) -> None:
    """Into the copy: a floor plane and a "track" camera where missing, a position servo named after each joint (in
    place of the joints' actuators), and the default keyframe where the file has none."""
    if not any(
        model.geom_bodyid[g] == 0 and int(model.geom_type[g]) == int(mujoco.mjtGeom.mjGEOM_PLANE)
        for g in range(model.ngeom)
    ):
        mj.worldbody.add_geom(name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[0, 0, 0.05])
        notes.append("no floor plane in the world: a plane 'floor' added at z = 0")
    if mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, "track") < 0:  # the physics env renders from "track"
        scale = 4.0 * pose.height
        mj.body(legs.base_name).add_camera(
            name="track",
            mode=mujoco.mjtCamLight.mjCAMLIGHT_TRACKCOM,
            pos=[0.5 * scale, -scale, 0.5 * scale],
            xyaxes=[0.894, 0.447, 0, -0.128, 0.255, 0.958],
        )
    for actuator in [a for a in mj.actuators if a.target in legs.joints]:
        mj.delete(actuator)
    for j, kp, kd, limit in zip(legs.joints, servo.kp, servo.kd, servo.limit):
        act = mj.add_actuator(name=j, target=j, trntype=mujoco.mjtTrn.mjTRN_JOINT)
        act.set_to_position(kp=kp, kv=kd)
        act.forcelimited, act.forcerange = True, [-limit, limit]
    if not model.nkey:
        mj.add_key(name=pose.keyframe, qpos=list(pose.qpos), ctrl=pose.default_pose)


def _add_contact_sensors(mj: mujoco.MjSpec, model: mujoco.MjModel, legs: _Legs, pose: _Pose) -> list[str]:
    """Into the copy: a site named after each foot's geom at its foot point (the foot names, returned) with a touch
    sensor `contact_FOOT` on a site around its sole (a sphere around a one-geom sole, else a box `contact_FOOT`), and a
    box site and touch sensor `contact_BODY` around the base and each thigh. A site of that name already on that
    body, and a touch sensor of that name already on a site of that body, are the model's own and kept (the shipped
    ANYmal D has both); a site or sensor of that name elsewhere is refused."""
    foot_names = []
    for f, foot in zip(legs.feet, pose.points):
        body = _name(model, _BODY, f)
        geom = mj.body(body).geoms[foot.geom - model.body_geomadr[f]]
        geom.name = geom.name or f"{body}_foot"
        name, sensor = geom.name, f"contact_{geom.name}"
        own = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SENSOR, sensor) >= 0
        size = [max(1.2 * foot.radius, 0.005), 0, 0]
        sphere = dict(type=mujoco.mjtGeom.mjGEOM_SPHERE, pos=list(foot.point), size=size, group=4)
        if own or (len(foot.sole) == 1 and foot.radius > 0):
            _touch_site(mj, model, f, name, sensor, sphere)
        else:
            _site(mj, model, f, name, sphere)
            centre, half = sole_box(model, foot.sole)
            box = dict(type=mujoco.mjtGeom.mjGEOM_BOX, pos=list(centre), size=list(half), group=4)
            _touch_site(mj, model, f, sensor, sensor, box)
        foot_names.append(name)
    for s in [legs.base, *legs.thighs]:
        centre, half = _enclosing_box(model, s)
        site = f"contact_{_name(model, _BODY, s)}"
        box = dict(type=mujoco.mjtGeom.mjGEOM_BOX, pos=list(centre), size=list(half), group=4)
        _touch_site(mj, model, s, site, site, box)
    return foot_names


def _site(mj: mujoco.MjSpec, model: mujoco.MjModel, body: int, site: str, shape: dict) -> int:
    """The id in `model` of the model's own site `site` on `body` (-1: added to the copy with `shape`: type, pos,
    size, group); a site of that name on another body is refused in one line."""
    found = mujoco.mj_name2id(model, _SITE, site)
    if found >= 0 and model.site_bodyid[found] != body:
        raise ValueError(
            f"a site named {site!r} exists already on body {_name(model, _BODY, model.site_bodyid[found])!r}, not "
            f"{_name(model, _BODY, body)!r}; rename it (feet and contact bodies get sites of their name)"
        )
    if found < 0:
        mj.body(_name(model, _BODY, body)).add_site(name=site, **shape)
    return found


def _touch_site(mj: mujoco.MjSpec, model: mujoco.MjModel, body: int, site: str, sensor: str, shape: dict) -> None:
    """A site `site` on `body` (`_site`) with a touch sensor `sensor` on it, in the copy: the model's own touch sensor
    of that name on a site of that body is kept; a sensor of that name that is something else is refused."""
    found = _site(mj, model, body, site, shape)
    touch = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SENSOR, sensor)
    if touch < 0:
        mj.add_sensor(name=sensor, type=mujoco.mjtSensor.mjSENS_TOUCH, objtype=_SITE, objname=site)
    elif not (
        model.sensor_type[touch] == mujoco.mjtSensor.mjSENS_TOUCH
        and model.sensor_objtype[touch] == _SITE
        and (model.sensor_objid[touch] == found or model.site_bodyid[model.sensor_objid[touch]] == body)
    ):
        raise ValueError(f"a sensor named {sensor!r} exists already, not a touch sensor on site {site!r}; rename it")


FROUDE = 0.4
"""The command rule's Froude number v² / (g h): a brisk walk for any leg length (walk-to-trot near 0.5)."""


def command_speed(height: float) -> float:
    """m/s and rad/s, the top of every command range: the speed at Froude number `FROUDE` for a base standing
    `height` m tall, capped at ANYmal D's top speed (ANYmal D itself gets its own 1 m/s)."""
    cap = max(load_spec("anymal_d").command.high)
    return significant(min(cap, float(np.sqrt(FROUDE * GRAVITY * height))), 2)


def _timing(model: mujoco.MjModel, height: float, notes: list[str]) -> tuple[float, float, float]:
    """(physics dt s, policy dt s: about 0.02 s in whole physics steps, command speed m/s and rad/s)."""
    dt = float(model.opt.timestep)
    substeps = max(1, round(0.02 / dt))
    policy_dt = significant(substeps * dt, 9)
    notes.append(f"policy step {policy_dt} s = {substeps} x the model's timestep {dt} s; episodes of 1000 steps")
    speed = command_speed(height)
    notes.append(
        f"commands up to {speed} m/s and rad/s: the speed at Froude number {FROUDE} for a base standing {height:.3f} m "
        f"tall, at most ANYmal D's 1 m/s (edit [command] low/high to change it); reward weights, reset noise and "
        f"action scale are ANYmal D's"
    )
    return dt, policy_dt, speed


def _tables(
    task_name: str,
    legs: _Legs,
    pose: _Pose,
    servo: Servo,
    foot_names: list[str],
    dt: float,
    policy_dt: float,
    speed: float,
) -> list[Table]:
    """The spec's tables: the robot's own figures, and ANYmal D's (`envs/anymal_d.toml`) for the rest."""
    a = load_spec("anymal_d")
    joints, thigh_names = legs.joints, legs.thigh_names
    tables = [
        Table(
            "task",
            {
                "name": task_name,
                "physics_env_id": f"{task_name}-MuJoCo-v0",
                "imagined_env_id": f"RWM-{task_name}-v0",
                "model": "",
                "policy_dt": policy_dt,
                "physics_dt": dt,
                "episode_steps": 1000,
                "keyframe": pose.keyframe,
                "base_body": legs.base_name,
            },
            {"model": "the rwm-ready copy written beside this spec", "policy_dt": "s", "physics_dt": "s"},
        ),
        Table(
            "reset",
            {
                "joint_pos_noise": a.reset.joint_pos_noise,
                "base_lin_vel_noise": a.reset.base_lin_vel_noise,
                "base_ang_vel_noise": a.reset.base_ang_vel_noise,
            },
            {"joint_pos_noise": "rad", "base_lin_vel_noise": "m/s", "base_ang_vel_noise": "rad/s"},
        ),
        Table(
            "actuator",
            {
                "joints": joints,
                "default_pose": pose.default_pose,
                "action_scale": a.actuator.action_scale,
                "kp": servo.figure(servo.kp),
                "kd": servo.figure(servo.kd),
                "effort_limit": servo.figure(servo.limit),
            },
            {
                "default_pose": "rad",
                "action_scale": "rad per unit action",
                "kp": "N·m/rad",
                "kd": "N·m·s/rad",
                "effort_limit": "N·m",
            },
        ),
    ]
    groups = [
        ("base_lin_vel", ["x", "y", "z"], "m/s"),
        ("base_ang_vel", ["x", "y", "z"], "rad/s"),
        ("projected_gravity", ["x", "y", "z"], "1"),
        ("joint_pos", joints, "rad"),
        ("joint_vel", joints, "rad/s"),
        ("joint_torque", joints, "N·m"),
    ]
    for group, columns, unit in groups:
        tables.append(
            Table(
                "state",
                {
                    "name": group,
                    "columns": columns,
                    "unit": unit,
                    "mean": [0.0] * len(columns),
                    "std": [1.0] * len(columns),
                },
                array=True,
            )
        )
    tables += [
        Table(
            "privileged",
            {
                "contact_bodies": thigh_names + foot_names,
                "contact_threshold": 1.0,
                "feet": foot_names,
                "thighs": thigh_names,
                "termination_bodies": [legs.base_name],
                "foot_height_std": 0.1,
            },
            {"contact_threshold": "N", "foot_height_std": "m"},
        ),
        Table("observation", {"groups": list(a.observation.groups)}),
        Table(
            "command",
            {
                "names": list(a.command.names),
                "low": [-speed] * 3,
                "high": [speed] * 3,
                "resample_seconds": a.command.resample_seconds,
                "standing_fraction": a.command.standing_fraction,
                "standing_threshold": a.command.standing_threshold,
            },
        ),
        Table(
            "reward", {"tracking_sigma": a.reward.tracking_sigma, "feet_air_time_target": a.reward.feet_air_time_target}
        ),
        Table("reward.weights", dict(a.reward.weights)),
    ]
    return tables


def _biped(tables: list[Table], height: float, notes: list[str]) -> None:
    """A two-footed robot's reward: the weights and air-time target of the shipped biped (`envs/g1.toml`), its own
    standing height as the base-height target, and a `base_height` state group for the term to read."""
    g1 = load_spec("g1")
    reward = next(t for t in tables if t.name == "reward")
    reward.values["feet_air_time_target"] = g1.reward.feet_air_time_target
    reward.values["base_height_target"] = significant(height)
    next(t for t in tables if t.name == "reward.weights").values = dict(g1.reward.weights)
    gravity = next(i for i, t in enumerate(tables) if t.name == "state" and t.values["name"] == "projected_gravity")
    group = {"name": "base_height", "columns": ["z"], "unit": "m", "mean": [0.0], "std": [1.0]}
    tables.insert(gravity + 1, Table("state", group, array=True))
    notes.append(
        f"two feet: the reward of envs/g1.toml (its biped terms base_height, feet_slip and single_stance; air-time "
        f"target {g1.reward.feet_air_time_target} s), the base-height target the standing {height:.3f} m, and a "
        f"base_height state group"
    )

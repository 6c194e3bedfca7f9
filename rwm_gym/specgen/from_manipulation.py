"""A task spec for a `dm_control.manipulation` task (`rwm-gym spec --from-dmc manipulation-TASK`), e.g. the Kinova
Jaco arm's reach_site_features or lift_brick_features.

The state follows `rwm_gym.physics.dmc_layout`: the arm's and hand's joints and actuator forces (as for a suite
task), then `site_pos` of the hand's tool centre point (dm_control's pinch site) and, for a reach task, of the target
site; then each free object's (the brick's) `body_pos`, `body_rot`, `body_lin_vel` and `body_ang_vel`. Contacts are
the robot's colliding bodies with the object when there is one (a grasp), else with the floor.

The `[manipulation]` table carries the goal that `rwm_gym.task.manipulation_reward` computes from the state, with
dm_control's figures: the reach target's radius (the target site's size), the lift distance, and the rest height of
the settled brick (measured here over a few resets).
"""

from __future__ import annotations

import mujoco
import numpy as np

from rwm_gym.specgen.dmc_model import children, layout, name_of, observation_table, spec_header, subtree, task_table_of
from rwm_gym.specgen.draft import SpecDraft, Table
from rwm_gym.specgen.toml_text import significant

_BODY_GROUPS = (
    ("body_pos", "xyz", "m"),
    ("body_rot", tuple(i + j for i in "xyz" for j in "xyz"), "1"),
    ("body_lin_vel", "xyz", "m/s"),
    ("body_ang_vel", "xyz", "rad/s"),
)
REST_RESETS = 4
"""Resets over which a lift task's settled brick height is measured (dm_control's settling makes it one figure)."""


def _title(name: str) -> str:
    return "".join(part.capitalize() for part in name.split("_"))


def _free_bodies(model: mujoco.MjModel) -> tuple[int, ...]:
    """Bodies under the world with a free joint: the objects a fixed-base arm moves."""
    free = int(mujoco.mjtJoint.mjJNT_FREE)
    return tuple(
        b
        for b in children(model, 0)
        if any(
            int(model.jnt_type[j]) == free
            for j in range(model.body_jntadr[b], model.body_jntadr[b] + model.body_jntnum[b])
        )
    )


def _colliding(model: mujoco.MjModel, bodies: list[int]) -> list[str]:
    names = []
    for b in bodies:
        geoms = np.flatnonzero(model.geom_bodyid == b)
        if any(model.geom_contype[g] | model.geom_conaffinity[g] for g in geoms) and name_of(
            model, mujoco.mjtObj.mjOBJ_BODY, b
        ):
            names.append(name_of(model, mujoco.mjtObj.mjOBJ_BODY, b))
    return names


def _lift_goal(env, model: mujoco.MjModel, prop: int) -> tuple[dict, dict]:
    """The lift goal's table and comments: vertex sites, dm_control's lift distance, the settled brick's height."""
    from dm_control.manipulation import lift

    vertices = [
        s
        for s in range(model.nsite)
        if model.site_bodyid[s] == prop and "vertex_" in name_of(model, mujoco.mjtObj.mjOBJ_SITE, s)
    ]
    if not vertices:
        raise ValueError(f"the lifted body {name_of(model, mujoco.mjtObj.mjOBJ_BODY, prop)!r} has no vertex sites")
    heights = []
    for seed in range(REST_RESETS):
        env.reseed(seed)
        env.reset()
        heights.append(env.physics.data.ptr.site_xpos[vertices, 2].min())
    table = {
        "goal": "lift",
        "prop_body": name_of(model, mujoco.mjtObj.mjOBJ_BODY, prop),
        "vertex_sites": [name_of(model, mujoco.mjtObj.mjOBJ_SITE, s) for s in vertices],
        "lift_distance": float(lift._DISTANCE_TO_LIFT),
        "rest_height": significant(float(np.mean(heights))),
    }
    comments = {
        "lift_distance": "m, dm_control's lift task: the reward is 1 from this height above rest",
        "rest_height": f"m, lowest vertex of the settled brick (mean of {REST_RESETS} resets; dm_control measures it "
        "per episode)",
    }
    return table, comments


def manipulation_draft(task: str) -> SpecDraft:
    """The spec of `dm_control.manipulation` task `task` with placeholder normalisation (see `fill_normalization`)."""
    from dm_control import manipulation

    from rwm_gym.task.dmc_environments import ManipulationEnvironment

    env = ManipulationEnvironment(task)
    model: mujoco.MjModel = env.physics.model.ptr
    composer_task = env.env.task
    objects = _free_bodies(model)
    _, groups, notes = layout(model, objects)
    actuators = groups[-1][1]
    hand_site = composer_task.hand.tool_center_point.full_identifier
    sites, goal, goal_comments = [hand_site], None, {}
    if task.startswith("reach_site"):
        target = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, "target_site")
        sites.append("target_site")
        goal = {
            "goal": "reach",
            "hand_site": hand_site,
            "target_site": "target_site",
            "target_radius": float(model.site_size[target, 0]),
        }
        goal_comments = {"target_radius": "m, dm_control's reach target (its site's radius)"}
    elif task.startswith("lift_") and len(objects) == 1:
        goal, goal_comments = _lift_goal(env, model, objects[0])
    else:
        notes.append(
            f"no state reward for {task}: give the imagined env a reward entry point "
            f'([imagination] reward = "module:function") or reward_fn='
        )
    groups.append(("site_pos", [f"{s}:{c}" for s in sites for c in "xyz"], "m"))
    object_names = [name_of(model, mujoco.mjtObj.mjOBJ_BODY, b) for b in objects]
    for name, components, unit in _BODY_GROUPS if objects else ():
        groups.append((name, [f"{o}:{c}" for o in object_names for c in components], unit))

    robot = [b for root in children(model, 0) if root not in objects for b in subtree(model, root)]
    contact_bodies = _colliding(model, robot)
    partner = object_names[0] if len(objects) == 1 else "world"
    notes.append(f"contact flags of the robot's colliding bodies with {partner!r}")
    if objects:
        notes.append(f"free objects {', '.join(object_names)}: position, rotation matrix and velocities in the state")

    limit = float(manipulation.load(task)._time_limit)  # s; ManipulationEnvironment itself runs without one
    episode_steps = int(round(limit / env.control_timestep())) if np.isfinite(limit) else 1000
    arm = composer_task.arm.mjcf_model.model.split("_")[0].capitalize()
    title = _title(task.removesuffix("_features"))
    task_table = {
        "name": f"DMC-{arm}-{title}",
        "physics_env_id": f"DMC-{arm}-{title}-v0",
        "imagined_env_id": f"RWM-{arm}-{title}-v0",
        "policy_dt": env.control_timestep(),
        "physics_dt": float(env.physics.timestep()),
        "episode_steps": episode_steps,
    }
    tables = [
        task_table_of(task_table, "dm_control's time limit; the tasks never terminate"),
        Table("dm_control", {"domain": "manipulation", "task": task, "contact_partner": partner}),
    ]
    if goal is not None:
        tables.append(
            Table(
                "manipulation",
                goal,
                goal_comments,
                note="The goal: reward and success from the state (rwm_gym/task/manipulation_reward.py).",
            )
        )
    tables.append(
        Table(
            "actuator",
            {"joints": actuators},
            note="The model's actuators in model order; actions in [-1, 1] map linearly onto each control range.",
        )
    )
    for name, columns, unit in groups:
        values = {"name": name, "columns": columns, "unit": unit, "mean": [0.0] * len(columns)}
        tables.append(Table("state", {**values, "std": [1.0] * len(columns)}, array=True))
    tables.append(
        Table("privileged", {"contact_bodies": contact_bodies, "feet": []}, note="No termination: none in dm_control.")
    )
    tables.append(observation_table(groups))
    header = spec_header(f"dm_control.manipulation {task}", f"manipulation-{task}")
    return SpecDraft(header, tables, notes)

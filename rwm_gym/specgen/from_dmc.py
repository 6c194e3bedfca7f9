"""A task spec for any dm_control suite task, read off the suite's own model (`rwm-gym spec --from-dmc DOMAIN-TASK`).

`--from-dmc manipulation-TASK` drafts a `dm_control.manipulation` task instead (`rwm_gym.specgen.from_manipulation`).

The state follows `rwm_gym.specgen.dmc_model.layout` (the vocabulary of `rwm_gym.physics.dmc_layout`). Contacts are
those of the robot's colliding bodies with the world's geoms (the floor) when the world has a plane; feet are the
contact bodies named like a foot. The cheetah's generated layout equals the shipped `envs/dmc_cheetah_run.toml` column
for column (tested).
"""

from __future__ import annotations

import mujoco
import numpy as np

from rwm_gym.specgen.dmc_model import children, layout, name_of, observation_table, spec_header, subtree, task_table_of
from rwm_gym.specgen.draft import SpecDraft, Table


def contacts(model: mujoco.MjModel, base_name: str, feet: list[str] | None) -> tuple[list[str], list[str], list[str]]:
    """(contact bodies, feet, notes): the robot's colliding bodies when the world has a plane to touch."""
    world_planes = [
        g
        for g in range(model.ngeom)
        if model.geom_bodyid[g] == 0 and int(model.geom_type[g]) == int(mujoco.mjtGeom.mjGEOM_PLANE)
    ]
    if not world_planes:
        return [], [], ["no floor plane in the world: no contact flags"]
    robot = [b for root in children(model, 0) for b in subtree(model, root)]
    colliding = [
        b
        for b in robot
        if any(
            (model.geom_contype[g] | model.geom_conaffinity[g]) and model.geom_bodyid[g] == b
            for g in range(model.ngeom)
        )
    ]
    names = [name_of(model, mujoco.mjtObj.mjOBJ_BODY, b) for b in colliding]
    names = [n for n in names if n]
    if feet is None:
        feet = [n for n in names if "foot" in n.lower()]
    unknown = sorted(set(feet) - set(names))
    if unknown:
        raise ValueError(f"--feet: {unknown[0]!r} is not a colliding body of the model (bodies: {', '.join(names)})")
    note = f"contact flags of {', '.join(names)} with the world's geoms; feet: {', '.join(feet) or 'none'}"
    return names, list(feet), [note]


def dmc_draft(domain: str, task: str, feet: list[str] | None = None) -> SpecDraft:
    """The spec of suite task `domain`-`task` with placeholder normalisation (see `draft.fill_normalization`)."""
    from dm_control import suite

    from rwm_gym.task.dmc_environments import MANIPULATION

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

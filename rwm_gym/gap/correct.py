"""Write the corrected simulator: the fitted effect as env options (`PhysicsParams` JSON) and as a standalone MJCF.

`corrected_physics.json` holds the env kwargs `{"physics": {...}}` that make the physics env the corrected robot:
`gym.make("AnymalD-MuJoCo-v0", **json.load(open(path)))` (or `rwm-gym collect --physics`). `corrected_model.xml` is the
same robot written by `MjSpec.to_xml()`, with every effect in it (MuJoCo holds actuator delay natively) except
backlash and the torque-speed limit, which no MJCF element can hold (the simulators apply them), and the sensor biases
(encoder offset, base-velocity bias), which change the readings, not the robot: they stay env options and the MJCF
says so in a comment. Inside rwm-gym use the JSON: the env re-applies the task spec's PD gains to whatever
MJCF it loads.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from rwm_gym.atomic import write_text
from rwm_gym.physics.params import PhysicsParams, build_spec
from rwm_gym.spec import TaskSpec


def write_corrected(
    spec: TaskSpec, params: PhysicsParams, out: Path, xml_file: str | Path | None = None, env_kwargs: dict | None = None
) -> dict[str, str]:
    """Write both files into `out`; returns {"physics": path, "mjcf": path}."""
    out.mkdir(parents=True, exist_ok=True)
    physics_path, mjcf_path = out / "corrected_physics.json", out / "corrected_model.xml"
    kwargs = {k: v for k, v in (env_kwargs or {}).items() if k != "physics"}
    write_text(physics_path, json.dumps({**kwargs, "physics": params.to_dict()}, indent=2))
    xml = build_spec(spec, xml_file, params).to_xml()
    if missing := env_only(params):
        note = f"<!-- Not in this file: {'; '.join(missing)}; env options only, use {physics_path.name}. -->\n"
        xml = xml.replace("<mujoco", note + "<mujoco", 1)
    write_text(mjcf_path, xml)
    return {"physics": str(physics_path), "mjcf": str(mjcf_path)}


def env_only(params: PhysicsParams) -> list[str]:
    """What of `params` no MJCF element holds (the simulators or the readings apply it), in words."""
    out = []
    if np.any(np.asarray(params.backlash) > 0):
        out.append(f"gear backlash {params.backlash} rad (dead band of the position error)")
    if np.any(np.asarray(params.torque_speed_slope) > 0):
        out.append(
            f"drive torque-speed limit, {params.torque_speed_slope} N·m·s/rad above {params.torque_speed_knee} rad/s"
        )
    if np.any(np.asarray(params.encoder_offset) != 0):
        out.append(f"joint encoder offset {params.encoder_offset} rad (a sensor bias)")
    if np.any(np.asarray(params.base_velocity_bias) != 0):
        out.append(f"base-velocity estimate bias {params.base_velocity_bias} m/s (a sensor bias)")
    return out

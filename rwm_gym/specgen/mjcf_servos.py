"""Each joint's PD gains and torque limit for a legged robot's spec, read from its MJCF (`rwm-gym spec --mjcf`).

Position servos give kp and kv; force ranges, a motor's control range times its gain and a joint's
`actuatorfrcrange` give the torque limit (Menagerie-style per-class figures reach each joint through MuJoCo's
defaults). Where the file gives no servo on every joint, kp follows the robot's weight.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from rwm_gym.specgen.toml_text import significant

GRAVITY = 9.81  # m/s²


@dataclass(frozen=True)
class Servo:
    """Each joint's PD gains and torque limit (N·m/rad, N·m·s/rad, N·m), in joint order."""

    kp: list[float]
    kd: list[float]
    limit: list[float]

    @staticmethod
    def figure(values: list[float]) -> float | list[float]:
        """One number where every joint has it, else the list: how the spec writes a per-joint figure."""
        return values[0] if len(set(values)) == 1 else values


def joint_actuator_figures(model: mujoco.MjModel, a: int) -> tuple[float | None, float | None, float | None]:
    """(kp, kd, torque limit) of actuator `a` on a joint where the file gives them, else None each."""
    gear = abs(float(model.actuator_gear[a, 0]))
    kp = kd = limit = None
    if int(model.actuator_biastype[a]) == int(mujoco.mjtBias.mjBIAS_AFFINE) and model.actuator_gainprm[a, 0] > 0:
        kp = float(model.actuator_gainprm[a, 0]) * gear
        kd = max(-float(model.actuator_biasprm[a, 2]) * gear, 0.0)
    if model.actuator_forcelimited[a]:
        limit = float(np.abs(model.actuator_forcerange[a]).max()) * gear
    elif model.actuator_ctrllimited[a] and int(model.actuator_biastype[a]) == int(mujoco.mjtBias.mjBIAS_NONE):
        limit = float(np.abs(model.actuator_ctrlrange[a]).max()) * gear * float(model.actuator_gainprm[a, 0])
    return kp, kd, limit


def gains(model: mujoco.MjModel, joints: list[int], mass: float, height: float, n_feet: int, notes: list[str]) -> Servo:
    """Each joint's kp, kd and effort limit: from the file's actuators (position servos' kp and kv, force ranges, a
    motor's control range times its gain) and joints (`actuatorfrcrange`) where it has them, else from weight."""
    found = {j: (None, None, None) for j in joints}
    for a in range(model.nu):
        j = int(model.actuator_trnid[a, 0])
        if int(model.actuator_trntype[a]) == int(mujoco.mjtTrn.mjTRN_JOINT) and j in found:
            found[j] = joint_actuator_figures(model, a)
    for j in joints:  # a joint's own actuator force range binds whatever drives it
        if model.jnt_actfrclimited[j]:
            joint_limit = float(np.abs(model.jnt_actfrcrange[j]).max())
            kp, kd, limit = found[j]
            found[j] = (kp, kd, joint_limit if limit is None else min(limit, joint_limit))
    kps = [found[j][0] for j in joints]
    if all(kp is not None for kp in kps):
        kp = [significant(v) for v in kps]
        kd = [significant(found[j][1]) for j in joints]
        notes.append(f"kp {span(kp)} N·m/rad, kd {span(kd)} N·m·s/rad from the file's position servos")
    else:
        weight_kp = significant(2.0 * mass * GRAVITY * height / n_feet)
        kp, kd = [weight_kp] * len(joints), [significant(weight_kp / 10.0)] * len(joints)
        # kd = kp / 40 (ANYmal D's ratio) leaves light legs chattering on the floor
        notes.append(
            f"kp = 2 x weight x standing height / feet = {weight_kp} N·m/rad, kd = kp x 0.1 s = {kd[0]} N·m·s/rad "
            f"(no position servo on every joint in the file)"
        )
    limits = [found[j][2] for j in joints]
    if all(v is not None for v in limits):
        limit = [significant(v) for v in limits]
        notes.append(f"effort limits {span(limit)} N·m per joint from the file's actuator and joint force ranges")
    else:
        limit = [significant(k * 1.0) if v is None else significant(v) for k, v in zip(kp, limits)]
        notes.append(f"effort limit = kp x 1 rad where the file gives no force range: {span(limit)} N·m")
    return Servo(kp, kd, limit)


def span(values: list[float]) -> str:
    """ "25" for equal values, "23.7 to 45.43" for a spread."""
    low, high = min(values), max(values)
    return f"{low:g}" if low == high else f"{low:g} to {high:g}"

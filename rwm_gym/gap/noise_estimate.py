"""The sensor noise of measured data, estimated from the data itself, beside the assumed noise model.

The noise floor (`noise_floor`) reads a twin trajectory through a sensor-noise model (`SensorNoise`: data-sheet values,
or `make-measured`'s). If the robot's sensors are twice as noisy as assumed, the floor is too low and a nominal robot
looks like a gap; half as noisy, and a real effect hides under it. So each quantity's noise is also estimated from the
measured episodes: white noise of std s added to a smooth signal x(t) leaves, in the k-th difference of the samples,
noise of std s * sqrt(C(2k, k)), while the smooth signal's k-th difference shrinks as (omega * dt)^k. At k =
`DIFFERENCE_ORDER` the difference of a walking or excitation signal at the policy rate is noise (ANYmal D: 2 Hz
gait, 0.02 s); contacts make it jump at a few rows, which the median absolute deviation ignores. Per quantity the
estimate is the median over its channels (joints, axes) of MAD(k-th difference) / 0.6745 / sqrt(C(2k, k)).

A robot's own motion leaks into the difference too (targets that jump every policy step, touchdowns), for joint
signals several times the data sheet's noise. The leak is measured on the nominal re-simulation of the measured
windows, which has no sensor noise: leak and noise add in variance, so the noise is sqrt(measured^2 - leak^2). A
quantity is resolved where noise makes at least `MIN_NOISE_SHARE` of the measured variance; elsewhere the estimate is
reported but the assumed value is kept.

Where a resolved estimate and the assumed value disagree by more than `MATERIAL_RATIO` either way, the workflow takes
the estimate for the floor (`noise_for_floor`); both are in the report.
"""

from __future__ import annotations

import dataclasses
from math import comb

import numpy as np

from rwm_gym.data.dataset import Dataset
from rwm_gym.gap.measured import SensorNoise
from rwm_gym.physics.robot import RobotLayout

DIFFERENCE_ORDER = 4
"""Order k of the differences whose spread is the noise (see the module docstring)."""

MIN_NOISE_SHARE = 0.5
"""Share of the measured difference variance that must be noise (not the leak of the motion) to trust an estimate."""

MATERIAL_RATIO = 1.5
"""Estimate / assumed outside [1 / this, this]: the two disagree and the floor takes the estimate."""

QUANTITIES: tuple[str, ...] = (
    "joint_pos",
    "joint_vel",
    "joint_torque",
    "base_lin_vel",
    "base_ang_vel",
    "base_orientation",
)
"""The `SensorNoise` fields estimated (its SI units)."""


def difference_noise(signal: np.ndarray, order: int = DIFFERENCE_ORDER) -> np.ndarray:
    """(C,) robust std of white noise in each column of `signal` (..., T, C) from its `order`-th difference along T,
    pooled over the leading axes (several episodes or windows of equal length)."""
    diff = np.diff(signal, n=order, axis=-2).reshape(-1, signal.shape[-1])
    mad = np.median(np.abs(diff - np.median(diff, axis=0)), axis=0)
    return mad / 0.6745 / np.sqrt(comb(2 * order, order))


def channels(layout: RobotLayout, qpos: np.ndarray, qvel: np.ndarray, torque: np.ndarray) -> dict[str, np.ndarray]:
    """The raw signals per quantity, (..., T, C) each, from qpos (..., T, nq), qvel (..., T, nv) and the joint torque
    (..., T, A); orientation as the base quaternion (one sign of the double cover)."""
    quat = qpos[..., 3:7] * np.sign(qpos[..., 3:4] + 1e-12)
    return {
        "joint_pos": qpos[..., layout.qpos_adr],
        "joint_vel": qvel[..., layout.dof_adr],
        "joint_torque": torque,
        "base_lin_vel": qvel[..., 0:3],
        "base_ang_vel": qvel[..., 3:6],
        "base_orientation": quat,
    }


def quantity_noise(signals: dict[str, np.ndarray]) -> dict[str, float]:
    """{quantity: noise std} from `channels`' signals: the median over a quantity's channels. Orientation: a small
    rotation of std s per axis moves the four quaternion components by noise whose variances sum to 3 s^2 / 4, so
    s = 2 sqrt(sum of the components' variances / 3)."""
    out = {}
    for name, signal in signals.items():
        per_channel = difference_noise(signal)
        if name == "base_orientation":
            out[name] = float(2.0 * np.sqrt(np.sum(per_channel**2) / 3.0))
        else:
            out[name] = float(np.median(per_channel))
    return out


def measured_noise(data: Dataset, layout: RobotLayout, episodes: np.ndarray) -> dict[str, float]:
    """{quantity: std} of the k-th differences of the measured episodes (noise and the leak of the motion)."""
    spec = data.spec()
    torque = spec.state_slices["joint_torque"]
    values: dict[str, list[float]] = {q: [] for q in QUANTITIES}
    weights = []
    for e in np.asarray(episodes, int):
        ep = data.episode(int(e))
        if len(ep["qpos"]) <= 2 * DIFFERENCE_ORDER:
            continue
        signals = channels(layout, np.asarray(ep["qpos"], float), np.asarray(ep["qvel"], float), ep["state"][:, torque])
        for name, value in quantity_noise(signals).items():
            values[name].append(value)
        weights.append(len(ep["qpos"]))
    if not weights:
        raise ValueError(f"{data.path}: no episode longer than {2 * DIFFERENCE_ORDER} rows to estimate its noise from")
    return {q: float(np.sqrt(np.average(np.square(v), weights=weights))) for q, v in values.items()}


def estimate_noise(measured: dict[str, float], leak: dict[str, float]) -> dict[str, dict]:
    """{quantity: {measured, leak, estimated, resolved}}: the noise left when the motion's leak (the same statistic
    on a noise-free re-simulation) is taken out in variance."""
    out = {}
    for name in QUANTITIES:
        total, motion = measured[name], leak[name]
        noise = float(np.sqrt(max(total**2 - motion**2, 0.0)))
        resolved = total > 0 and noise**2 >= MIN_NOISE_SHARE * total**2
        out[name] = {"measured": total, "leak": motion, "estimated": noise, "resolved": bool(resolved)}
    return out


def noise_for_floor(assumed: SensorNoise, estimates: dict[str, dict]) -> tuple[SensorNoise, dict[str, dict]]:
    """The sensor noise the floor is computed with (each quantity: the assumed value, or the resolved estimate where
    the two disagree materially) and the report's table {quantity: {assumed, estimated, ratio, resolved, used}}."""
    used, table = {}, {}
    for name in QUANTITIES:
        value, guess = assumed.scale * getattr(assumed, name), estimates[name]
        ratio = guess["estimated"] / value if value > 0 else float("inf")
        take = guess["resolved"] and not (1.0 / MATERIAL_RATIO <= ratio <= MATERIAL_RATIO)
        used[name] = guess["estimated"] if take else value
        table[name] = {"assumed": value, **guess, "ratio": float(ratio), "used": "estimated" if take else "assumed"}
    return dataclasses.replace(SensorNoise(), scale=1.0, **used), table

"""Where the simulator and the measured data disagree: residuals ranked per channel and per condition.

Input: measured windows and their nominal re-simulation. Channels are the state's columns (per joint for joint
signals). Conditions split every joint's residual by what the robot was doing at the window's start: its leg in
stance or swing (foot contact), the sign of the joint's velocity, the torque in the top decile of |torque|; the lag
between command and response compares, per joint, when the joint velocity answers a change of the position target in
the measured data and in the simulation.
"""

from __future__ import annotations

import numpy as np

from rwm_gym.gap.resim import Windows, normalised_residual
from rwm_gym.spec import TaskSpec


def channel_ranking(spec: TaskSpec, simulated: np.ndarray, windows: Windows, horizon: int) -> list[dict]:
    """Channels sorted by normalised MSE at `horizon` steps, largest first: [{channel, mse, share}]."""
    res = normalised_residual(spec, simulated[:, horizon - 1], windows.target[:, horizon - 1])
    mse = (res**2).mean(0)
    order = np.argsort(mse)[::-1]
    return [{"channel": spec.state_columns[i], "mse": float(mse[i]), "share": float(mse[i] / mse.sum())} for i in order]


def condition_ranking(spec: TaskSpec, simulated: np.ndarray, windows: Windows, horizon: int = 1) -> list[dict]:
    """Conditions sorted by how much larger the joints' residual is there than overall: [{condition, ratio, ...}]."""
    res = normalised_residual(spec, simulated[:, horizon - 1], windows.target[:, horizon - 1])
    sl = spec.state_slices
    joint_err = sum(res[:, sl[g]] ** 2 for g in ("joint_pos", "joint_vel", "joint_torque")) / 3  # (W, A)
    velocity, torque = windows.state0[:, sl["joint_vel"]], windows.state0[:, sl["joint_torque"]]
    feet = np.isin(spec.privileged.contact_bodies, spec.privileged.feet)
    legs = len(spec.privileged.feet)
    stance = np.repeat(windows.contact0[:, feet], spec.action_dim // legs, axis=1)  # (W, A), joints leg-major
    high = np.abs(torque) >= np.quantile(np.abs(torque), 0.9)
    conditions = {
        "stance": stance,
        "swing": ~stance,
        "joint velocity > 0": velocity > 0,
        "joint velocity < 0": velocity < 0,
        "torque in top 10%": high,
        "torque below top 10%": ~high,
    }
    overall = joint_err.mean()
    rows = [
        {
            "condition": name,
            "ratio": float(joint_err[mask].mean() / overall),
            "mse": float(joint_err[mask].mean()),
            "fraction_of_samples": float(mask.mean()),
        }
        for name, mask in conditions.items()
        if mask.any()
    ]
    return sorted(rows, key=lambda r: r["ratio"], reverse=True)


def response_lag(spec: TaskSpec, states: np.ndarray, windows: Windows, max_lag: int = 4) -> float:
    """s, the lag at which joint-velocity changes best follow target changes (parabolic peak of the correlation).

    states (W, H, S): measured (`windows.target`) or simulated.
    """
    k = windows.warmup
    d_target = np.diff(windows.actions[:, k:], axis=1)  # (W, H-1, A), changes of action[t0+j]
    d_vel = np.diff(states[:, :, spec.state_slices["joint_vel"]], axis=1)  # (W, H-1, A), change into row t0+j+2
    corr = []
    for lag in range(max_lag + 1):
        a = d_target[:, : d_target.shape[1] - lag].ravel()
        b = d_vel[:, lag:].ravel()
        corr.append(abs(np.corrcoef(a, b)[0, 1]) if a.std() > 0 and b.std() > 0 else 0.0)
    corr = np.nan_to_num(np.asarray(corr))
    i = int(np.argmax(corr))
    offset = 0.0
    if 0 < i < max_lag:
        denom = corr[i - 1] - 2 * corr[i] + corr[i + 1]
        offset = 0.5 * (corr[i - 1] - corr[i + 1]) / denom if denom != 0 else 0.0
    return float((i + offset) * spec.policy_dt)


def locate_gap(spec: TaskSpec, simulated: np.ndarray, windows: Windows, top: int = 8) -> dict:
    """The report's `where` section: top channels at horizons 1 and 5, ranked conditions, response lags."""
    return {
        "channels_h1": channel_ranking(spec, simulated, windows, 1)[:top],
        "channels_h5": channel_ranking(spec, simulated, windows, min(5, windows.horizon))[:top],
        "conditions": condition_ranking(spec, simulated, windows),
        "response_lag_s": {
            "measured": response_lag(spec, windows.target, windows),
            "simulated": response_lag(spec, simulated, windows),
        },
    }

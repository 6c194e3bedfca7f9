"""The gap as a distance between distributions of per-window statistics (foot slip, contact timing, base motion).

The report's gap (`fit.gap_per_window`) compares each re-simulated window with its measured one step by step. Where
contact is chaotic (a slippery floor under a fast contact solver) a right simulator turns the start state's sensor
noise into another slide in every window, so that gap can be larger after the correction than before, although the
corrected windows slide as the robot's do. This measure forgets which window is which: each window is summarised by a
few statistics (`STATISTICS`), and the distribution of each over the measured windows is compared with that over the
simulated ones by the 1-D Wasserstein distance, in units of the statistic's spread over the measured windows; the
measure is the mean over statistics. The simulated rows are read through the assumed sensor-noise model first (one
seeded draw; `--sensor-noise`, not the floor's estimate, which takes chattering contacts for noise), as the measured
rows were, so a right simulator leaves only the sampling noise of a finite set of windows.

Which measure heads the report (`headline`): this one where an effect was named by its noise spread (`gap.spread`),
since such an effect claims to reproduce the data's distribution, not each window; the step-by-step gap otherwise.
"""

from __future__ import annotations

import mujoco
import numpy as np
from scipy.stats import wasserstein_distance

from rwm_gym.data.dataset import Dataset
from rwm_gym.gap.measured import SensorNoise, noisy_measurement
from rwm_gym.gap.resim import Resimulator, Windows
from rwm_gym.physics.params import PhysicsParams
from rwm_gym.physics.robot import RobotLayout
from rwm_gym.spec import TaskSpec

STATISTICS = {
    "slip_speed": "m/s, mean horizontal speed of the feet in contact",
    "contact_duty": "1, share of foot-rows in contact",
    "touchdowns": "1/s, touchdowns per foot per second",
    "base_speed": "m/s, mean horizontal speed of the base",
    "base_speed_spread": "m/s, std over the window's rows of the base's horizontal velocity",
}
"""Each window's statistics (unit, meaning); the foot statistics need the spec's `privileged.feet`."""

MEASURE = (
    "mean over window statistics (" + ", ".join(STATISTICS) + ") of the 1-D Wasserstein distance between their "
    "distributions over measured and simulated held-out windows, each over its spread on the measured windows; "
    "simulated rows read through the sensor-noise model"
)

NOISE_SEED = 17
"""Seed of the sensor-noise draw that reads the simulated rows."""

Rows = dict[str, np.ndarray]
"""{"qpos" (W, H, nq), "qvel" (W, H, nv), "contact" (W, H, C)}: the rows of W windows, as the sensors read them."""


def measured_rows(data: Dataset, windows: Windows) -> Rows:
    """The measured rows start+1 .. start+H of every window (those `windows.target` holds the state of)."""
    rows: dict[str, list[np.ndarray]] = {"qpos": [], "qvel": [], "contact": []}
    ahead = np.arange(1, windows.horizon + 1)
    for episode, start in zip(windows.episode, windows.start):
        ep = data.episode(int(episode))
        for name, part in rows.items():
            part.append(ep[name][start + ahead])
    return {name: np.stack(part) for name, part in rows.items()}


def simulated_rows(
    resim: Resimulator, windows: Windows, params: PhysicsParams, noise: SensorNoise, seed: int = NOISE_SEED
) -> Rows:
    """The re-simulated rows of every window under `params`, qpos and qvel read through `noise` (seeded)."""
    sim = resim.simulate(windows, params)
    model = resim.model(params)
    layout = RobotLayout.from_model(model, resim.spec)
    w, h, nq = sim["qpos"].shape
    qpos, qvel, _ = noisy_measurement(
        layout,
        resim.spec,
        model,
        sim["qpos"].reshape(w * h, nq),
        sim["qvel"].reshape(w * h, -1),
        sim["joint_torque"].reshape(w * h, -1),
        noise,
        np.random.default_rng([seed, 23]),
    )
    return {"qpos": qpos.reshape(w, h, nq), "qvel": qvel.reshape(w, h, -1), "contact": sim["contact"]}


def foot_velocity(model: mujoco.MjModel, sites: np.ndarray, qpos: np.ndarray, qvel: np.ndarray) -> np.ndarray:
    """(N, F, 3) m/s world velocity of each foot site at rows qpos (N, nq), qvel (N, nv)."""
    data = mujoco.MjData(model)
    jac = np.zeros((3, model.nv))
    out = np.zeros((len(qpos), len(sites), 3))
    for n in range(len(qpos)):
        data.qpos[:] = qpos[n]
        mujoco.mj_kinematics(model, data)
        mujoco.mj_comPos(model, data)
        for f, site in enumerate(sites):
            mujoco.mj_jacSite(model, data, jac, None, int(site))
            out[n, f] = jac @ qvel[n]
    return out


def window_statistics(spec: TaskSpec, model: mujoco.MjModel, rows: Rows) -> dict[str, np.ndarray]:
    """(W,) each of `STATISTICS` per window; NaN where a window has none (no foot in contact: no slip speed)."""
    qpos, qvel, contact = rows["qpos"], rows["qvel"], rows["contact"]
    w, h, _ = qpos.shape
    base = qvel[..., 0:2]  # the free joint's world-frame horizontal velocity
    stats = {
        "base_speed": np.linalg.norm(base, axis=-1).mean(1),
        "base_speed_spread": np.sqrt(base.var(1).sum(-1)),
    }
    feet = spec.privileged.feet
    if not feet:
        return stats
    layout = RobotLayout.from_model(model, spec)
    on = contact[..., [spec.privileged.contact_bodies.index(f) for f in feet]].astype(bool)
    speed = np.linalg.norm(
        foot_velocity(model, layout.foot_site_ids, qpos.reshape(w * h, -1), qvel.reshape(w * h, -1))[..., :2], axis=-1
    ).reshape(w, h, -1)
    stance = on.sum((1, 2))
    with np.errstate(invalid="ignore", divide="ignore"):
        stats["slip_speed"] = np.where(stance > 0, (speed * on).sum((1, 2)) / stance, np.nan)
    stats["contact_duty"] = on.mean((1, 2))
    stats["touchdowns"] = (on[:, 1:] & ~on[:, :-1]).sum((1, 2)) / (len(feet) * h * spec.policy_dt)
    return stats


def distribution_distance(measured: dict[str, np.ndarray], simulated: dict[str, np.ndarray]) -> dict[str, float]:
    """Per statistic: the Wasserstein distance between its measured and simulated values over windows (NaN left out),
    over the measured values' std (1 where they do not vary); 0 where both sides are the same."""
    out = {}
    for name, values in measured.items():
        a, b = values[np.isfinite(values)], simulated[name][np.isfinite(simulated[name])]
        if len(a) == 0 or len(b) == 0:
            continue
        scale = float(a.std()) or 1.0
        out[name] = float(wasserstein_distance(a, b) / scale)
    return out


def distribution_gap(
    resim: Resimulator,
    data: Dataset,
    windows: Windows,
    base: PhysicsParams,
    corrected: PhysicsParams,
    noise: SensorNoise,
) -> dict:
    """The report's `distribution_gap`: the measure (`MEASURE`) of the nominal and the corrected simulator on
    `windows`, per statistic and in all, and the fraction of it the correction removes."""
    spec = resim.spec
    measured = window_statistics(spec, resim.model(base), measured_rows(data, windows))

    def distance(params: PhysicsParams) -> dict[str, float]:
        simulated = window_statistics(spec, resim.model(params), simulated_rows(resim, windows, params, noise))
        return distribution_distance(measured, simulated)

    before = distance(base)
    after = distance(corrected) if corrected != base else before
    total_before, total_after = float(np.mean(list(before.values()))), float(np.mean(list(after.values())))
    return {
        "gap_before": total_before,
        "gap_after": total_after,
        "explained_fraction": 1.0 - total_after / total_before if total_before > 0 else 0.0,
        "per_statistic": {name: {"before": before[name], "after": after[name]} for name in before},
        "statistics": {name: STATISTICS[name] for name in before},
        "windows": len(windows),
        "metric": MEASURE,
    }


def headline(step_by_step: dict, distribution: dict, by_spread: bool) -> dict:
    """The report's `gap_measure`: which gap heads the report and why, with its figures. `step_by_step`: the report's
    `explained_fraction`, `gap_before` and `gap_after`; `by_spread`: an effect was named by its noise spread."""
    if by_spread:
        chosen, name = distribution, "window_distribution"
        why = (
            "an effect was named by its noise spread: it claims to reproduce the distribution of the data's windows, "
            "not each window (its re-simulations slide elsewhere from the same noisy start), so the gap is measured "
            "between distributions of per-window statistics"
        )
    else:
        chosen, name = step_by_step, "state_mse"
        why = (
            "no effect was named by its noise spread: the named effects were fitted to reproduce each window, so "
            "the gap is the step-by-step normalised state error"
        )
    return {
        "measure": name,
        "gap_before": chosen["gap_before"],
        "gap_after": chosen["gap_after"],
        "explained_fraction": chosen["explained_fraction"],
        "reason": why,
    }

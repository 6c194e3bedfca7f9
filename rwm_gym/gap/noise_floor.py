"""Is there a gap at all? The sensor-noise floor of the gap, and a test of the measured gap against it.

Even a perfect simulator leaves a gap on measured data: re-simulation starts from a noisy measured state and is
compared with noisy measured states. The floor is that gap, computed on the measured windows themselves: the nominal
simulator re-simulated from each window's measured start gives a "twin" trajectory that the nominal simulator explains
exactly; the twin is read through the sensor-noise model (`SensorNoise`: the same draw as `make-measured`, per sensor,
in SI units; for a real robot its data-sheet values) at the start, the warm-up rows and every target row, and
re-simulated like the measured data. Its gap per window is the floor; `draws` noise draws are averaged.

The test: one-sided Wilcoxon signed-rank test on block means of (measured gap - floor) per window (paired: the same
windows, actions and states), and the measured gap at least `min_ratio` times the floor. On n blocks the rank test
cannot go below p = 2^-n, so a log whose robot falls at once (five held-out windows) could never show a gap, however
large; with too few blocks for the rank test to reach `significance`, a one-sided t-test on the blocks' log ratios
log(gap / floor) decides instead, which weighs how far above the floor each block is. After named effects, this test
on the remaining gap, against the corrected simulator's own floor, decides whether anything is left (a slippery floor
carries the same noise further). Before any, a gap that fails it may still hold an effect that shows in a few windows
only; `select` then asks each candidate's own reduction (Bonferroni) before saying `none`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from rwm_gym.gap.fit import gap_horizons, gap_per_window
from rwm_gym.gap.measured import SensorNoise, noisy_measurement
from rwm_gym.gap.resim import Resimulator, SimulationDiverged, Windows
from rwm_gym.gap.significance import paired_p_value, paired_test
from rwm_gym.options import check_ranges, option
from rwm_gym.physics.params import PhysicsParams
from rwm_gym.physics.robot import RobotLayout


@dataclass(frozen=True)
class FloorConfig:
    """How the floor is computed and the gap tested against it."""

    draws: int = option(2, ge=1)
    """Noise draws averaged into the floor."""
    significance: float = option(0.01, gt=0, lt=1)
    """p-value under which the gap is significantly above the floor."""
    min_ratio: float = option(1.2, ge=0)
    """The gap must also be at least this multiple of the floor."""
    seed: int = 0

    def __post_init__(self) -> None:
        check_ranges(self)


def noise_floor(
    resim: Resimulator, windows: Windows, params: PhysicsParams, noise: SensorNoise, config: FloorConfig = FloorConfig()
) -> np.ndarray:
    """(W, len(gap_horizons(windows.horizon))) gap of a simulator that is exactly right (`params`), through the
    sensor noise."""
    spec = resim.spec
    model = resim.model(params)
    layout = RobotLayout.from_model(model, spec)
    truth = resim.simulate(windows, params)
    n, k1, nq = windows.qpos.shape
    nv, h = windows.qvel.shape[2], truth["state"].shape[1]
    rng = np.random.default_rng([config.seed, 11])
    gaps = []
    for _ in range(config.draws):
        qpos, qvel, _ = noisy_measurement(
            layout,
            spec,
            model,
            windows.qpos.reshape(-1, nq),
            windows.qvel.reshape(-1, nv),
            np.zeros((n * k1, spec.action_dim)),
            noise,
            rng,
        )
        _, _, target = noisy_measurement(
            layout,
            spec,
            model,
            truth["qpos"].reshape(-1, nq),
            truth["qvel"].reshape(-1, nv),
            truth["joint_torque"].reshape(n * h, -1),
            noise,
            rng,
        )
        twin = dataclasses.replace(
            windows, qpos=qpos.reshape(n, k1, nq), qvel=qvel.reshape(n, k1, nv), target=target.reshape(n, h, -1)
        )
        # NaN where the noisy twin blows up (left out of the test)
        gap = np.full((n, len(gap_horizons(windows.horizon))), np.nan)
        try:
            gap[:] = gap_per_window(spec, resim.rollout(twin, params), twin)
        except SimulationDiverged as err:
            keep = ~err.windows
            kept = twin.subset(keep)
            gap[keep] = gap_per_window(spec, resim.rollout(kept, params), kept)
        gaps.append(gap)
    drawn = np.isfinite(gaps).sum(0)  # a window whose every draw blew up stays NaN, without nanmean's warning
    return np.where(drawn > 0, np.nansum(gaps, axis=0) / np.maximum(drawn, 1), np.nan)


def compare_with_floor(
    gap: np.ndarray, floor: np.ndarray, windows: Windows, block_rows: int, config: FloorConfig = FloorConfig()
) -> dict:
    """Is the per-window gap (W, 3) significantly above the floor (W, 3)? The report's `noise_floor` section.
    Windows where every noise draw of the floor blew up (NaN) are left out of both."""
    keep = np.isfinite(floor).all(1)
    gap, floor, windows = gap[keep], floor[keep], windows.subset(keep)
    ratio = float(gap.mean() / floor.mean())
    p_value = paired_p_value(gap.mean(1), floor.mean(1), windows, block_rows, config.significance)
    return {
        "gap": float(gap.mean()),
        "floor": float(floor.mean()),
        "windows": int(keep.sum()),
        "windows_left_out": int((~keep).sum()),
        "floor_per_horizon": {str(h): float(v) for h, v in zip(gap_horizons(windows.horizon), floor.mean(0))},
        "ratio": ratio,
        "p_value": p_value,
        "above_floor": bool(p_value < config.significance and ratio >= config.min_ratio),
        "test": f"{paired_test(windows, block_rows, config.significance)} of the gap against the floor, "
        f"p < {config.significance}, and gap >= {config.min_ratio} x floor",
    }

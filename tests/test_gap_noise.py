"""The sensor noise of measured data estimated from the data, beside the assumed noise model, and used for the floor
where the two disagree."""

from __future__ import annotations

import numpy as np
import pytest

from rwm_gym.data.dataset import Dataset
from rwm_gym.gap.measured import SensorNoise, make_measured
from rwm_gym.gap.noise_estimate import difference_noise, estimate_noise, measured_noise, noise_for_floor
from rwm_gym.gap.workflow import GapConfig, run_gap
from rwm_gym.physics.locomotion import make_core
from rwm_gym.physics.params import CONVERGED_SOLVER

SIM = "AnymalD-MuJoCo-v0"


def test_difference_noise_of_a_smooth_signal_is_its_white_noise():
    rng = np.random.default_rng(0)
    t = np.arange(400)[:, None] * 0.02
    smooth = 0.3 * np.sin(2 * np.pi * 2.0 * t + np.arange(3)) + 0.1 * t  # a 2 Hz gait at the policy rate
    for sigma in (0.002, 0.02):
        estimate = difference_noise(smooth + rng.normal(0, sigma, (400, 3)))
        np.testing.assert_allclose(estimate, sigma, rtol=0.15)


@pytest.mark.parametrize("scale", [0.5, 2.0])
def test_noise_estimate_of_measured_data_is_near_the_truth(tmp_path, scale):
    """The same episodes without noise give the motion's own leak; what is left is the sensor noise. Joint signals at
    the policy rate are mostly motion (not resolved, the assumed value kept); the base's velocity and attitude are
    resolved within 20 % and, being `scale` x the assumed, taken for the floor."""
    core = make_core("anymal_d", 1)
    paths = [
        make_measured({}, 2, tmp_path / f"{s}.h5", max_steps=100, noise=SensorNoise(scale=s), progress=False)
        for s in (0.0, scale)
    ]
    clean, noisy = (Dataset.load(p) for p in paths)
    leak = measured_noise(clean, core.layout, np.arange(2))
    estimates = estimate_noise(measured_noise(noisy, core.layout, np.arange(2)), leak)
    floor_noise, table = noise_for_floor(SensorNoise(), estimates)
    for name in ("base_lin_vel", "base_orientation"):
        truth = scale * getattr(SensorNoise(), name)
        assert estimates[name]["resolved"] and abs(estimates[name]["estimated"] - truth) <= 0.2 * truth, name
        assert table[name]["used"] == "estimated" and getattr(floor_noise, name) == estimates[name]["estimated"]
    assert table["joint_pos"]["used"] == "assumed" and floor_noise.joint_pos == SensorNoise().joint_pos


@pytest.mark.parametrize(
    "scale",
    [
        # less noise than assumed raises no false effect either way; the estimate itself at 0.5x is tested above
        pytest.param(0.5, marks=pytest.mark.slow),
        2.0,  # more noise than assumed: with the assumed floor, noise could be taken for an effect
    ],
)
def test_nominal_robot_measured_with_other_noise_than_assumed_is_none(tmp_path, scale):
    """Re-simulated with a converged solve, as make-measured's robot is solved (the noise check is tested here; the
    solver check's own case is in test_gap)."""
    data = make_measured({}, 6, tmp_path / "m.h5", max_steps=150, noise=SensorNoise(scale=scale), progress=False)
    report = run_gap(SIM, data, tmp_path / "report", config=GapConfig(solver=CONVERGED_SOLVER), progress=False)
    assert report["effect"] == "none", report["reason"]
    check = report["noise_floor"]["noise_check"]["quantities"]
    assert check["base_lin_vel"]["used"] == "estimated"
    assert abs(check["base_lin_vel"]["ratio"] - scale) <= 0.2 * scale
    assert report["noise_floor"]["floor_sensor_noise"]["base_lin_vel"] == check["base_lin_vel"]["estimated"]

"""The gap between distributions of per-window statistics (`gap.distribution`): zero on the same data, large where an
effect is hidden, smaller after the right correction where the step-by-step gap is not, and named in the report."""

from __future__ import annotations

import numpy as np
import pytest

from rwm_gym.data.collect import make_physics_core
from rwm_gym.data.dataset import Dataset
from rwm_gym.gap.distribution import (
    STATISTICS,
    distribution_distance,
    distribution_gap,
    headline,
    measured_rows,
    window_statistics,
)
from rwm_gym.gap.effects import vocabulary
from rwm_gym.gap.fit import gap_per_window
from rwm_gym.gap.measured import SensorNoise, make_measured
from rwm_gym.gap.report import _gap_measures, _headline
from rwm_gym.gap.resim import Resimulator
from rwm_gym.gap.workflow import GapConfig, held_out_windows
from rwm_gym.spec import load_spec

SPEC = load_spec("anymal_d")
SIM = "AnymalD-MuJoCo-v0"


def _case(path, effects):
    """Excitation data of the package's own fast physics with `effects` hidden (3 episodes of 100 steps), the nominal
    simulator under its own solver and the default held-out windows."""
    make_measured(effects, 3, path, max_steps=100, solver=None, progress=False)
    data = Dataset.load(path)
    core = make_physics_core(SIM, 1)
    _, _, held = held_out_windows(data, GapConfig())
    return data, Resimulator(SPEC, solver=core.solver), core.params, held


@pytest.fixture(scope="module")
def nominal(tmp_path_factory):
    return _case(tmp_path_factory.mktemp("nominal") / "m.h5", {})


@pytest.fixture(scope="module")
def slippery(tmp_path_factory):
    """A floor of friction 0.3 (nominal 1.0): under 4 solver iterations each re-simulated window slides elsewhere."""
    return _case(tmp_path_factory.mktemp("slippery") / "m.h5", {"ground_friction": [0.3]})


def test_the_same_windows_are_at_distance_zero(nominal):
    data, resim, base, held = nominal
    stats = window_statistics(SPEC, resim.model(base), measured_rows(data, held))
    assert set(stats) == set(STATISTICS)
    assert all(v.shape == (len(held),) for v in stats.values())
    assert distribution_distance(stats, stats) == {name: 0.0 for name in STATISTICS}


def test_the_distance_grows_with_a_hidden_effect_and_falls_after_the_right_correction(nominal, slippery):
    data, resim, base, held = nominal
    on_nominal = distribution_gap(resim, data, held, base, base, SensorNoise())
    data, resim, base, held = slippery
    truth = vocabulary(SPEC)["ground_friction"].physics(np.array([0.3]), base)
    on_slippery = distribution_gap(resim, data, held, base, truth, SensorNoise())
    assert on_slippery["gap_before"] > 3 * on_nominal["gap_before"]
    assert on_slippery["gap_after"] < 0.5 * on_slippery["gap_before"]
    # why it is needed: the right floor leaves a larger step-by-step gap than the nominal one
    step_by_step = [gap_per_window(SPEC, resim.rollout(held, p), held).mean() for p in (base, truth)]
    assert step_by_step[1] > step_by_step[0]


def test_the_report_names_its_gap_measure_and_why():
    step_by_step = {"gap_before": 4.0, "gap_after": 6.0, "explained_fraction": -0.5}
    distribution = {
        "gap_before": 5.0,
        "gap_after": 1.0,
        "explained_fraction": 0.8,
        "per_statistic": {"slip_speed": {"before": 5.0, "after": 1.0}},
        "statistics": {"slip_speed": STATISTICS["slip_speed"]},
        "windows": 15,
        "metric": "a distance",
    }
    by_spread = headline(step_by_step, distribution, by_spread=True)
    assert by_spread["measure"] == "window_distribution" and by_spread["explained_fraction"] == 0.8
    assert "noise spread" in by_spread["reason"]
    assert headline(step_by_step, distribution, by_spread=False)["measure"] == "state_mse"
    report = {**step_by_step, "distribution_gap": distribution, "gap_measure": by_spread}
    text = "\n".join(_headline(by_spread) + _gap_measures(report))  # the report.md sections of these figures
    assert "The report's gap measure is `window_distribution`" in text and "noise spread" in text
    assert "5 before, 1 after the correction (80.0% explained)" in text

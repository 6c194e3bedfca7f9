"""The bootstrap over fitting episodes: each named value's spread when other episodes had been measured."""

from __future__ import annotations

import numpy as np
import pytest

from rwm_gym.data.dataset import Dataset
from rwm_gym.gap.bootstrap import bootstrap, resample
from rwm_gym.gap.effects import vocabulary
from rwm_gym.gap.fit import CandidateFit, FitConfig
from rwm_gym.gap.measured import make_measured
from rwm_gym.gap.report import _named_effects
from rwm_gym.gap.resim import Resimulator, make_windows
from rwm_gym.gap.select import Selection
from rwm_gym.gap.workflow import named_section
from rwm_gym.physics.params import PhysicsParams
from rwm_gym.spec import load_spec

SPEC = load_spec("anymal_d")


def test_bootstrap_spreads_each_fitted_value_over_resampled_episodes(tmp_path):
    path = make_measured({"armature": [0.1]}, 4, tmp_path / "m.h5", max_steps=60, progress=False)
    train = make_windows(Dataset.load(path), np.arange(4), 5, 8)
    effect = vocabulary(SPEC)["armature"]
    fit = CandidateFit("armature", ["armature"], ["kg·m²"], [0.1], [0.01], 0.0)
    resim, config = Resimulator(SPEC), FitConfig(max_evaluations=8)
    spread = bootstrap([(effect, fit)], resim, train, PhysicsParams(), config, resamples=3)
    assert spread["resamples"] == 3
    armature = spread["parameters"]["armature"]
    low, high = armature["interval"]
    assert 0.05 < low <= high < 0.15 and 0 < armature["std"] < 0.05  # the truth, 0.1, moved by other episodes
    assert bootstrap([(effect, fit)], resim, train, PhysicsParams(), config, resamples=3) == spread  # seeded
    drawn = resample(train, np.random.default_rng(1))
    assert len(np.unique(drawn.episode)) <= 4 and set(drawn.episode) <= set(train.episode)
    assert bootstrap([], resim, train, PhysicsParams(), config, resamples=3)["parameters"] == {}
    with pytest.raises(ValueError, match="resamples must be >= 0"):
        bootstrap([(effect, fit)], resim, train, PhysicsParams(), config, resamples=-1)

    selection = Selection("armature", "named", [(effect, fit)], PhysicsParams(armature=0.1), np.zeros((1, 3)), [1.0])
    section = named_section(selection, spread)
    assert section["effects"][0]["bootstrap"]["armature"] == armature
    table = "\n".join(_named_effects({**section, "bootstrap": spread}))
    assert "bootstrap 95 %" in table and f"{low:.4g} to {high:.4g}" in table

"""Effects that spread sensor noise (`gap.spread`): a slippery floor under the package's fast contact solver, which
least squares cannot name, is named by its own noise spread; a spread that only covers a misfit is not."""

from __future__ import annotations

import pytest

from rwm_gym.data.collect import make_physics_core
from rwm_gym.data.dataset import Dataset
from rwm_gym.gap.bootstrap import bootstrap
from rwm_gym.gap.effects import vocabulary
from rwm_gym.gap.fit import FitConfig, gap_per_window
from rwm_gym.gap.measured import SensorNoise, make_measured, write_spring_model
from rwm_gym.gap.noise_floor import FloorConfig, noise_floor
from rwm_gym.gap.resim import Resimulator, make_windows
from rwm_gym.gap.spread import SpreadInputs, name_by_spread
from rwm_gym.gap.workflow import GapConfig, held_out_windows
from rwm_gym.physics.params import CONVERGED_SOLVER
from rwm_gym.spec import load_spec

SPEC = load_spec("anymal_d")
EFFECTS = vocabulary(SPEC)
SIM = "AnymalD-MuJoCo-v0"
FAST = None
"""`make_measured`'s robot solved as the package's own physics (the MJCF's 4 solver iterations), as `SIM` runs."""


def _inputs(path):
    """What `name_by_spread` reads, built as the workflow builds it: the nominal simulator under its own solver, the
    default split."""
    data, config, fit = Dataset.load(path), GapConfig(), FitConfig()
    train_ids, _, held = held_out_windows(data, config)
    train = make_windows(data, train_ids, fit.fit_horizon, config.fit_stride, config.warmup)
    core = make_physics_core(SIM, 1)
    resim, base = Resimulator(SPEC, solver=core.solver), core.params

    def floor_of(params, windows=None):
        return noise_floor(resim, held if windows is None else windows, params, SensorNoise())

    before = gap_per_window(SPEC, resim.rollout(held, base), held)
    return SpreadInputs(resim, train, held, base, before, floor_of(base), floor_of, fit, FloorConfig())


def _name(inputs, *names):
    """`name_by_spread` over the effects `names` on `_inputs`."""
    return name_by_spread({n: EFFECTS[n] for n in names}, inputs)


@pytest.fixture(scope="module")
def slippery(tmp_path_factory):
    """Excitation data of the fast physics on a floor of friction 0.3 (nominal 1.0)."""
    path = tmp_path_factory.mktemp("slippery") / "m.h5"
    make_measured({"ground_friction": [0.3]}, 6, path, max_steps=150, solver=FAST, progress=False)
    return _inputs(path)


@pytest.fixture(scope="module")
def slippery_named(slippery):
    """`name_by_spread` on the slippery floor's data over three effects."""
    return _name(slippery, "ground_friction", "motor_strength", "joint_damping")


def test_a_slippery_floor_under_the_fast_solver_is_named_by_its_spread(slippery, slippery_named):
    pick, records = slippery_named
    assert pick is not None, records
    effect, fit = pick
    assert effect.name == "ground_friction"
    assert abs(fit.values[0] - 0.3) <= 0.25 * 0.7, fit.values  # within 25 % of its distance from nominal
    # why least squares never got there: the right floor leaves a larger gap than the nominal one
    assert fit.gap_mean > slippery.before.mean()
    record = fit.spread
    assert record["named"] and not record["own_floor_test"]["above_floor"]
    assert record["systematic_misfit"]["explained"] >= 0.3 and record["likelihood"]["p_value"] < 0.01
    assert record["likelihood"]["nll"] < record["likelihood"]["nll_nominal"]


def test_nominal_data_leave_nothing_for_a_spread_to_cover(tmp_path):
    path = make_measured({}, 3, tmp_path / "m.h5", max_steps=100, solver=FAST, progress=False)
    pick, records = _name(_inputs(path), "ground_friction")
    assert pick is None and records == [{"reason": "the nominal simulator's own spread covers the fitting windows"}]


@pytest.mark.parametrize(("solver", "policy"), [(FAST, "excitation"), (CONVERGED_SOLVER, "gait")])
def test_a_spread_that_only_covers_a_misfit_is_not_named(tmp_path, solver, policy):
    """A knee spring (outside the vocabulary), on the fast physics and on a converged robot's walking data: a floor
    slippery enough spreads noise wide enough to cover the spring's misfit on the fitting windows, but it leaves the
    misfit's mean over windows where it was (on the walking data it also covers the held-out windows, and the data
    are far more likely under its spread than under the nominal simulator's, 25x its floor)."""
    xml = write_spring_model(SPEC, tmp_path / "spring.xml", "KFE", 30.0)
    path = make_measured(
        {},
        6,
        tmp_path / "m.h5",
        max_steps=150,
        solver=solver,
        policy=policy,
        progress=False,
        env_kwargs={"xml_file": str(xml)},
    )
    pick, records = _name(_inputs(path), "ground_friction")
    assert pick is None
    [record] = records  # ground friction did cover the fitting windows
    assert record["values"][0] < 1.0 and not record["own_floor_test"]["above_floor"]
    assert record["systematic_misfit"]["explained"] < 0.3 and "systematic misfit" in record["reason"]


def test_the_bootstrap_of_an_effect_named_by_its_spread_searches_its_spread_again(slippery, slippery_named):
    pick, _ = slippery_named
    inputs = slippery
    spread = bootstrap([pick], inputs.resim, inputs.train, inputs.base, inputs.config, 2, floor_of=inputs.floor_of)
    assert "least spread" in spread["method"]
    low, high = spread["parameters"]["ground_friction"]["interval"]
    assert 0.3 - 0.25 * 0.7 <= low <= high <= 0.3 + 0.25 * 0.7  # a least-squares refit would go back towards 1.0

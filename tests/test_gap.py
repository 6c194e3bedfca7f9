"""The sim-to-real gap workflow: vocabulary, hidden measured data, exact re-simulation, corrected model, and the
workflow naming each hidden effect (under the workflow's defaults on every effect, and the broad sweep over
magnitudes, `slow`)."""

from __future__ import annotations

import dataclasses
import json
from types import SimpleNamespace

import h5py
import mujoco
import numpy as np
import pytest

from rwm_gym.cli import main
from rwm_gym.data.dataset import Dataset
from rwm_gym.gap import resim as resim_module
from rwm_gym.gap import solver_check
from rwm_gym.gap.correct import write_corrected
from rwm_gym.gap.effects import EFFECT_NAMES, combined_physics, parse_effects, vocabulary
from rwm_gym.gap.fit import FitConfig
from rwm_gym.gap.measured import SensorNoise, make_measured
from rwm_gym.gap.resim import Resimulator, make_windows, normalised_residual
from rwm_gym.gap.scope import leg_groups, per_leg
from rwm_gym.gap.workflow import GapConfig, run_gap
from rwm_gym.gap.world_model import WorldModelGapConfig
from rwm_gym.model.config import TrainConfig
from rwm_gym.model.factory import model_config_for
from rwm_gym.model.train import train
from rwm_gym.physics.backlash import DeadBand
from rwm_gym.physics.locomotion import LocomotionEnv
from rwm_gym.physics.params import CONVERGED_SOLVER, ModelCache, PhysicsParams, SolverSettings, build_model
from rwm_gym.spec import load_spec

SPEC = load_spec("anymal_d")
EFFECTS = vocabulary(SPEC)
SIM = "AnymalD-MuJoCo-v0"

CONVERGED = GapConfig(solver=CONVERGED_SOLVER)
"""Re-simulate with a converged solve, as make-measured's robot is solved: the workflow then has no solver to choose
(`gap.solver_check` is a no-op) and a test pays for one selection, not for step 1 under two solvers as well. The
workflow's defaults (the sim env's own solver and the check) are run where the check is what a test is about, and on
every effect in the `slow` sweeps."""


def test_vocabulary_is_complete_with_units_and_nominal_values():
    assert tuple(EFFECTS) == EFFECT_NAMES
    for effect in EFFECTS.values():
        nominal = effect.physics(effect.nominal)
        if effect.name in ("torque_limit", "ground_friction", "ground_compliance"):  # the spec's / model's value
            model, default = build_model(SPEC, params=nominal), build_model(SPEC)
            for field in ("actuator_forcerange", "geom_friction", "geom_solref", "geom_solimp"):
                np.testing.assert_array_equal(getattr(model, field), getattr(default, field))
        else:
            assert nominal == PhysicsParams(), effect.name
        for p in effect.parameters:
            assert p.unit and p.low <= p.nominal <= p.high and p.low <= p.default <= p.high, (effect.name, p.name)
    hidden = parse_effects(SPEC, ["joint_friction", "pd_gains"], ["1.5", "0.8,1.2"])
    params = combined_physics(hidden, SPEC)
    assert (params.joint_friction, params.kp_scale, params.kd_scale) == (1.5, 0.8, 1.2)
    with pytest.raises(ValueError, match="unknown effect 'gearbox'"):
        parse_effects(SPEC, ["gearbox"], None)


def test_measured_data_hides_the_effect(tmp_path):
    path = make_measured({"armature": [0.1]}, 2, tmp_path / "m.h5", max_steps=30, progress=False)
    with h5py.File(path) as f:
        attrs = {k: str(v) for k, v in f.attrs.items() if k != "spec"}
    assert json.loads(attrs["physics_params"]) == {} and json.loads(attrs["metadata"]) == {}
    assert attrs["policy"] == "unknown" and attrs["env_id"] == SIM
    assert not any("armature" in v for v in attrs.values())
    assert [p.name for p in tmp_path.iterdir()] == ["m.h5"]  # no temp file left beside it
    # The effect is really in the data: the nominal simulator does not reproduce it, the hidden one does.
    data = Dataset.load(path)
    windows = make_windows(data, np.arange(2), 5, 4)
    resim = Resimulator(SPEC)
    errors = [
        float((normalised_residual(SPEC, resim.rollout(windows, p), windows.target) ** 2).mean())
        for p in (PhysicsParams(), PhysicsParams(armature=0.1))
    ]
    assert errors[1] < 0.5 * errors[0]


def test_measured_data_whose_physics_blows_up_are_refused(tmp_path):
    """The MJCF's own 4 solver iterations blow up on ice under the walking policy: no robot moves so."""
    out = tmp_path / "ice.h5"
    with pytest.raises(ValueError, match="blew up in 1 of 2 episodes"):
        make_measured({"ground_friction": [0.05]}, 2, out, max_steps=150, policy="gait", solver=None, progress=False)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("physics", [{}, {"action_delay": 0.015}, {"backlash": 0.03}])
def test_resimulation_reproduces_noise_free_data_exactly(tmp_path, physics):
    hidden = {name: [value] for name, value in physics.items()}
    path = make_measured(hidden, 2, tmp_path / "m.h5", max_steps=40, noise=SensorNoise(scale=0.0), progress=False)
    data = Dataset.load(path)
    windows = make_windows(data, np.arange(2), 10, 7)
    simulated = Resimulator(SPEC).rollout(windows, PhysicsParams.from_dict(physics))
    np.testing.assert_allclose(simulated, windows.target, atol=1e-4)  # state is stored as float32


def test_resimulator_hands_out_a_repeated_rollout_again_as_a_copy(tmp_path, monkeypatch):
    path = make_measured({}, 2, tmp_path / "m.h5", max_steps=40, progress=False)
    windows = make_windows(Dataset.load(path), np.arange(2), 5, 7)
    resim = Resimulator(SPEC)
    runs = []
    simulate = resim._simulate
    monkeypatch.setattr(resim, "_simulate", lambda *args: runs.append(args[1]) or simulate(*args))
    first = resim.rollout(windows, PhysicsParams())
    first[:] = 0.0  # a caller's change reaches no later caller
    again = resim.rollout(windows, PhysicsParams())
    assert len(runs) == 1 and np.abs(again).sum() > 0
    np.testing.assert_array_equal(again, simulate(windows, PhysicsParams(), windows.horizon, None)["state"])
    resim.rollout(windows, PhysicsParams(joint_friction=1.0))
    resim.rollout(windows.subset(np.ones(len(windows), bool)), PhysicsParams())  # equal windows, another object
    resim.rollout(windows, PhysicsParams(), horizon=2)
    assert len(runs) == 4
    monkeypatch.setattr(resim_module, "RECENT_BYTES", 0)  # none fits: each rollout runs again
    resim.rollout(windows, PhysicsParams(joint_friction=2.0))
    resim.rollout(windows, PhysicsParams(joint_friction=2.0))
    assert len(runs) == 6


def test_corrected_mjcf_is_the_corrected_robot(tmp_path):
    params = PhysicsParams(
        joint_friction=1.5,
        armature=0.05,
        action_delay=0.01,
        payload_mass=5.0,
        payload_com=(0.1, 0.0, 0.0),
        motor_strength=0.9,
        ground_friction=0.5,
    )
    paths = write_corrected(SPEC, params, tmp_path)
    assert PhysicsParams.from_dict(json.loads(open(paths["physics"]).read())["physics"]) == params
    written, direct = mujoco.MjModel.from_xml_path(paths["mjcf"]), build_model(SPEC, params=params)
    runs = []
    for model in (written, direct):
        data = mujoco.MjData(model)
        mujoco.mj_resetDataKeyframe(model, data, 0)
        data.ctrl[:] = data.qpos[7:] + 0.2
        mujoco.mj_step(model, data, 40)
        runs.append(data.qpos.copy())
    np.testing.assert_allclose(runs[0], runs[1], atol=2e-3)  # MJCF holds 6 significant digits


@pytest.mark.parametrize(
    "params",
    [
        PhysicsParams(joint_friction=1.3, joint_damping=0.7, armature=tuple(np.linspace(0.0, 0.1, 12))),
        PhysicsParams(payload_mass=3.0, payload_com=(0.1, 0.0, 0.05), ground_friction=0.4, motor_strength=0.8),
        PhysicsParams(payload_mass=-4.0, payload_com=(0.1, -0.05, 0.0), ground_friction=0.4),
        PhysicsParams(action_delay=0.005, kp_scale=1.2, kd_scale=0.5, torque_limit=50.0),
        PhysicsParams(ground_solref=(0.05, 0.6), ground_solimp=(0.8, 0.9, 0.002)),
        PhysicsParams(ground_friction=0.5, ground_solref=(0.03, 1.2)),
    ],
)
def test_model_cache_gives_the_compiled_model(params):
    """The gap fit's cache writes parameters into a once-compiled structure; every field must equal a fresh compile."""
    cache = ModelCache(SPEC, solver=CONVERGED_SOLVER)
    cache(PhysicsParams(payload_mass=9.0, ground_friction=1.0, action_delay=params.action_delay))  # a used template
    cached, compiled = cache(params), build_model(SPEC, params=params, solver=CONVERGED_SOLVER)
    fields = [n for n in dir(compiled) if not n.startswith("_") and isinstance(getattr(compiled, n), np.ndarray)]
    assert len(fields) > 100
    for name in fields:
        np.testing.assert_allclose(getattr(cached, name), getattr(compiled, name), rtol=1e-12, err_msg=name)
    # meansize is a rendering scale only; a compile derives it from the bodies' inertia boxes, a lighter base's too
    scales = ("meaninertia", "meanmass", "extent") + (("meansize",) if params.payload_mass >= 0 else ())
    for name in scales:
        assert getattr(cached.stat, name) == pytest.approx(getattr(compiled.stat, name), rel=1e-12), name


def test_backlash_is_a_dead_band_of_the_position_error():
    """Torque = kp * D(target - q) at every physics step: none inside the band, kp * (e -+ b/2) outside."""
    model = build_model(SPEC)
    band = DeadBand.from_model(model, SPEC.actuator.joints, np.full(12, 0.02))
    qpos = model.key_qpos[:1].copy()
    ctrl = np.zeros((1, model.nu))
    q = qpos[0, band.qpos_adr]
    ctrl[0, band.actuator_ids] = q + np.linspace(-0.05, 0.05, 12)
    rewritten = band.control(ctrl, qpos)[0, band.actuator_ids] - q
    np.testing.assert_allclose(
        rewritten,
        np.sign(ctrl[0, band.actuator_ids] - q) * np.maximum(np.abs(ctrl[0, band.actuator_ids] - q) - 0.01, 0.0),
        atol=1e-12,
    )
    assert DeadBand.from_model(model, SPEC.actuator.joints, np.zeros(12)) is None
    with pytest.raises(ValueError, match="backlash"):
        DeadBand.from_model(model, SPEC.actuator.joints, np.full(12, -0.01))
    # The env honours it, and the single env matches the batched core (both step the physics one step at a time).
    runs = []
    for physics in ({}, {"backlash": 0.03}):
        env = LocomotionEnv(physics=physics)
        env.reset(seed=3)
        for _ in range(20):
            env.step(np.full(12, 0.3))
        runs.append(env.data.qpos.copy())
    assert np.abs(runs[0] - runs[1]).max() > 1e-3
    from rwm_gym.physics.locomotion import make_core

    core = make_core("anymal_d", 2, physics={"backlash": 0.03}, nthread=1)
    core.reset(np.arange(2), [3, 4])
    for _ in range(20):
        core.step(np.full((2, 12), 0.3))
    np.testing.assert_array_equal(core.record()["qpos"][0], runs[1])


def _tiny_world_model(path):
    """A tiny GRU world model trained briefly on nominal-sim gait data (stands in for the shipped checkpoint)."""
    from rwm_gym.data.collect import collect

    data = collect(SIM, "gait", 4, path.parent / "nominal.h5", max_steps=80, num_envs=4, progress=False)
    config = model_config_for("rwm", SPEC, hidden_size=16, num_layers=1, head_hidden=16)
    train(
        data,
        config,
        TrainConfig(history=8, forecast=4, batch_size=8, iterations=20, val_every=20, checkpoint_every=20),
        path,
        progress=False,
    )
    return path


TINY_WM = WorldModelGapConfig(
    episodes=2, max_steps=60, iterations=20, batch_size=8, forecast=4, history=8, horizons=(1, 5, 25)
)


ONE_EFFECT = FitConfig(max_effects=1)
"""One effect hidden, one named: the steps after a naming are tested in test_gap_selection."""


def _hidden_and_check(
    tmp_path,
    name: str,
    scale: float = 1.0,
    episodes: int = 6,
    steps: int = 150,
    world_model=None,
    config: GapConfig = CONVERGED,
):
    effect = EFFECTS[name]
    p = effect.parameters[0]
    true = p.nominal + scale * (p.default - p.nominal)
    data = make_measured(
        {name: effect.values_from_magnitude(true)}, episodes, tmp_path / "m.h5", max_steps=steps, progress=False
    )
    report = run_gap(
        SIM,
        data,
        tmp_path / "report",
        config=config,
        fit_config=ONE_EFFECT,
        progress=False,
        world_model=world_model,
        wm_config=TINY_WM,
    )
    assert report["effect"] == name, report["reason"]
    assert report["scope"] == "global"  # a global effect is not taken for a per-leg one
    fitted = report["parameters"][p.name]
    assert abs(fitted - true) <= 0.25 * abs(true - p.nominal), (fitted, true)
    assert report["gap_after"] <= 0.5 * report["gap_before"]
    return report


EPISODES = {"backlash": 9}
"""Measured episodes per test where 6 leave too few held-out blocks for the significance test."""

DEFAULT_EPISODES = {**EPISODES, "base_velocity_bias": 9}
"""The same under the workflow's defaults: a base-velocity bias of 0.1 m/s on 6 episodes was fitted to a third by the
sim env's own solver, and the converged solve's fit to 4 % was better at p = 0.014 only, short of the check's bar."""


ROBOT_EFFECTS = tuple(n for n in EFFECT_NAMES if n != "contact_solver")
"""Effects make-measured can hide: its robot is solved to convergence, so a finer solve hides nothing
(`contact_solver` is tested in test_gap_selection)."""


NAMED_AT_DEFAULT = [n for n in ROBOT_EFFECTS if n not in ("backlash", "torque_speed_limit")]
"""Effects the workflow names at their default size on 6 x 150 steps of excitation data (backlash: tested with the
world-model rows; the torque-speed limit: fitted, not named)."""


FITTED_FAST = ("ground_compliance", "base_velocity_bias")
"""Effects whose workflow test here is `slow`: test_gap_effects fits each from the same data in seconds."""


@pytest.mark.parametrize(
    "name",
    [
        pytest.param(n, marks=pytest.mark.slow) if n in FITTED_FAST else n
        for n in NAMED_AT_DEFAULT
        if n != "pd_gains"  # named under the workflow's defaults below, where the solver check takes a converged solve
    ],
)
def test_workflow_names_hidden_effect_fits_it_and_shrinks_the_gap(tmp_path, name):
    report = _hidden_and_check(tmp_path, name, episodes=EPISODES.get(name, 6))
    assert set(report) >= {
        "effect",
        "parameters",
        "explained_fraction",
        "gap_before",
        "gap_after",
        "where",
        "corrected",
        "plots",
    }


def test_workflow_defaults_fit_two_pd_gains_under_the_sim_envs_own_solver(tmp_path):
    """The workflow's defaults on a converged robot with PD gains off (kp 0.7x): under the sim env's own solver (4
    iterations) the two gains' cost is rough, and the fit, which searches kp within its screening bracket before least
    squares, still finds them, so the solver check keeps the sim env's own solver and names them under it, and the
    named gains refitted under a converged solve keep it too."""
    report = _hidden_and_check(tmp_path, "pd_gains", config=GapConfig())
    check = report["solver"]["check"]
    assert check["checked"] and check["own"]["best_effect"] == "pd_gains", check["reason"]
    assert check["taken"] == "own" and report["solver"]["iterations"] < CONVERGED_SOLVER.iterations
    # the named gains refitted under the converged solve do not fit materially better either, and the report says so
    assert check["named_set"]["effects"] == ["pd_gains"] and check["named_set"]["taken"] == "own"
    assert check["named_set"]["reason"] in (tmp_path / "report" / "report.md").read_text()


class _StubResimulator:
    """What `choose_solver` reads of a re-simulator (its best candidate is stubbed in the test)."""

    def __init__(self, spec=None, xml_file="robot.xml", nthread=1, solver=None):
        self.spec, self.xml_file, self.nthread, self.solver = spec, xml_file, nthread, solver


@pytest.mark.parametrize(("converged_gap", "taken"), [(0.5, "converged"), (0.9, "own")])
def test_solver_check_takes_a_converged_solve_only_where_it_fits_materially_better(monkeypatch, converged_gap, taken):
    """Each held-out window's gap is 1.0 under the sim env's own solver; under a converged one `converged_gap`. Half
    the gap is taken (the corrected robot carries the converged settings and the selection the converged fits); 10 %
    less is within `MATERIAL` and the sim env's own solver stays."""
    held = SimpleNamespace(episode=np.repeat(np.arange(4), 8), start=np.tile(np.arange(0, 160, 20), 4))
    gaps = {False: 1.0, True: converged_gap}

    def best_candidate(resim, train, held, base, config, progress, every_scope_if_none=False, scoped=True, memo=None):
        gap = gaps[resim.solver is not None and resim.solver.iterations == CONVERGED_SOLVER.iterations]
        per_window = gap * (1 + 0.1 * (np.arange(len(held.start)) % 3))
        return {
            "effect": "pd_gains",
            "scope": "global",
            "values": [0.7, 1.0],
            "gap": float(per_window.mean()),
            "per_window": per_window,
            "nominal_gap": 2.0,
        }, f"memo of {gap}"

    monkeypatch.setattr(solver_check, "best_candidate", best_candidate)
    monkeypatch.setattr(solver_check, "is_converged", lambda resim: False)
    monkeypatch.setattr(solver_check, "Resimulator", _StubResimulator)
    own = _StubResimulator()
    choice = solver_check.choose_solver(own, None, held, PhysicsParams(), FitConfig(), progress=False)
    check = choice.check
    assert check["checked"] and check["taken"] == taken, check["reason"]
    assert (choice.resim is own) == (taken == "own")
    assert choice.first_step == f"memo of {gaps[taken == 'converged']}"
    assert (choice.converged is None) == (taken == "converged")
    assert solver_check.corrected_solver(choice.resim, check) == (choice.resim.solver if taken == "converged" else None)


@pytest.mark.parametrize(
    ("own_global", "own_scoped", "conv_global", "conv_scoped", "taken", "scoped_fitted"),
    [
        (0.8, 0.8, 0.5, 0.5, "converged", False),  # the globals show the converged solve better: no scoped form
        (0.5, 0.5, 0.8, 0.3, "own", False),  # the converged globals leave more: no scoped form either
        (0.8, 0.3, 0.7, 0.7, "own", True),  # the globals leave it open: the scoped forms decide, as before
        (0.8, 0.8, 0.7, 0.3, "converged", True),
        (1.0, 0.3, 0.5, 0.5, "own", True),  # no global lowers the own gap: its scoped forms get their say
        (0.95, 0.3, 0.5, 0.5, "own", True),  # nor where the best lowers it by 5 % only
    ],
)
def test_the_solver_check_fits_scoped_forms_only_where_the_global_forms_leave_it_open(
    monkeypatch, own_global, own_scoped, conv_global, conv_scoped, taken, scoped_fitted
):
    """The nominal held-out gap is 1.2 under either solver (a gap of 1.0 is 1.1 in the windows' mean). Where the
    converged solve's best global effect already leaves materially less than the own solver's best global one (which
    lowers the gap materially too), the converged solve is taken without fitting a scoped form, and where it leaves
    more, the own solver is kept so; else the scoped forms are fitted under both (from the memo of the globals) and
    decide."""
    held = SimpleNamespace(episode=np.repeat(np.arange(4), 8), start=np.tile(np.arange(0, 160, 20), 4))
    calls = []

    def best_candidate(resim, train, held, base, config, progress, every_scope_if_none=False, scoped=True, memo=None):
        conv = resim.solver is not None and resim.solver.iterations == CONVERGED_SOLVER.iterations
        calls.append((conv, scoped, memo))
        gap = {(False, False): own_global, (False, True): own_scoped, (True, False): conv_global}
        gap = gap.get((conv, scoped), conv_scoped)
        per_window = gap * (1 + 0.1 * (np.arange(len(held.start)) % 3))
        effect = "none" if gap >= 1.0 else "joint_friction"
        found = {"effect": effect, "scope": "global", "values": [1.0], "gap": float(per_window.mean())}
        return {**found, "per_window": per_window, "nominal_gap": 1.2}, f"memo {conv}"

    monkeypatch.setattr(solver_check, "best_candidate", best_candidate)
    monkeypatch.setattr(solver_check, "is_converged", lambda resim: False)
    monkeypatch.setattr(solver_check, "Resimulator", _StubResimulator)
    choice = solver_check.choose_solver(_StubResimulator(), None, held, PhysicsParams(), FitConfig(), progress=False)
    assert choice.check["taken"] == taken, choice.check["reason"]
    assert [c[:2] for c in calls[:2]] == [(False, False), (True, False)]
    assert (len(calls) == 4) == scoped_fitted
    if scoped_fitted:  # the scoped search starts from the globals' fits
        assert calls[2] == (False, True, "memo False") and calls[3] == (True, True, "memo True")
    assert choice.check["reason"].startswith("fitted alone" if scoped_fitted else "in their global forms")


@pytest.mark.parametrize(("selected_again", "taken"), [(0.0126, "own"), (0.0032, "converged")])
def test_a_selection_under_the_converged_solve_that_loses_the_named_effects_is_not_taken(selected_again, taken):
    """The named effects refitted under the converged solve leave 0.003 (materially less than under the sim env's own
    solver). Selected again under it, the effects named there leave `selected_again`: four times that (an effect in
    the knees lost to PD gains) keeps the own solver's selection; about the same takes the converged one."""
    check = {
        "checked": True,
        "taken": "converged",
        "reason": "fitted alone ...; but refitted together ...",
        "named_set": {"taken": "converged", "held_out_gap_converged": 0.003},
    }
    out = solver_check.lost_in_reselection(check, np.full((32, 2), selected_again))
    assert out["taken"] == taken and out["reselection"]["kept"] == taken
    assert out["reselection"]["held_out_gap"] == pytest.approx(selected_again)
    assert out["reason"].startswith(check["reason"]) and (taken == "own") == (out["reason"] != check["reason"])


@pytest.mark.parametrize(
    ("global_gap", "scoped_gap", "every_scope_if_none", "best", "scoped_every"),
    [
        (1.2, 0.3, True, "joint_type", True),
        (1.2, 0.95, True, "none", True),
        (1.2, 0.3, False, "none", False),
        (0.8, 0.3, True, "global", False),
    ],
)
def test_the_own_solver_gets_every_scope_before_the_check_gives_it_up(
    monkeypatch, global_gap, scoped_gap, every_scope_if_none, best, scoped_every
):
    """The nominal held-out gap is 1.0. Global friction leaves `global_gap`; per joint type it leaves `scoped_gap` but
    is fitted only by `scope.every_scope`. Where no effect lowers the gap (1.2) and the solver is the sim env's own,
    every scope is fitted and the per-joint-type form is its best where it explains more than its charge (0.3), not
    where it explains less (0.95); a converged solve gets no such search (its best stays the nominal simulator); where
    global friction lowers the gap (0.8) every scope is not fitted."""
    held = SimpleNamespace(episode=np.repeat(np.arange(4), 8), start=np.tile(np.arange(0, 160, 20), 4))
    gaps = {"nominal": 1.0, "global": global_gap, "joint_type": scoped_gap}

    def fit(scope):
        explained = 1.0 - gaps[scope] / gaps["nominal"]
        return SimpleNamespace(
            effect="joint_friction",
            scope=scope,
            values=[4.0],
            status="ok",
            gap_mean=gaps[scope],
            score=explained - 0.1 * (scope != "global"),
            p_value=0.001,
        )

    effect = {s: SimpleNamespace(physics=lambda values, base, s=s: s) for s in ("global", "joint_type")}
    called = []

    def every_scope(fits, done, effects, inputs, memo):
        called.append(done)
        return [(effect["joint_type"], fit("joint_type"))]

    monkeypatch.setattr(solver_check, "vocabulary", lambda spec, xml, solver: {"joint_friction": effect["global"]})
    monkeypatch.setattr(solver_check, "gap_per_window", lambda spec, sim, held: np.full((32, 2), gaps[sim]))
    monkeypatch.setattr(solver_check, "fit_all", lambda effects, inputs, progress, memo: [fit("global")])
    monkeypatch.setattr(solver_check, "scope_candidates", lambda fits, effects, inputs, memo: [])
    monkeypatch.setattr(solver_check, "every_scope", every_scope)
    resim = _ConvergedStub()
    base = "nominal"
    found, _ = solver_check.best_candidate(resim, None, held, base, FitConfig(), False, every_scope_if_none)
    assert found["scope" if best != "none" else "effect"] == best
    assert found["gap"] == pytest.approx(min(gaps[best if best != "none" else "nominal"], 1.0))
    assert called == ([set()] if scoped_every else [])


class _ConvergedStub(_StubResimulator):
    """A converged re-simulator whose rollout hands the physics to the stubbed gap (`_recheck_inputs`)."""

    def rollout(self, windows, params):
        return params


def _recheck_inputs(monkeypatch, converged_gap: np.ndarray, refitted: list):
    """Held-out windows of 4 episodes, a check that kept the sim env's own solver with a converged alternative, and a
    converged solve whose every window's gap is `converged_gap` (W,); the refit under it returns its start and
    records the parameter names it fitted in `refitted`."""
    held = SimpleNamespace(episode=np.repeat(np.arange(4), 8), start=np.tile(np.arange(0, 160, 20), 4))

    def fit_effect(effect, resim, train, base, config, start, bracket, max_evaluations=None):
        refitted.append(([p.name for p in effect.parameters], np.asarray(start)))
        return SimpleNamespace(status="ok", values=np.asarray(start))

    monkeypatch.setattr(solver_check, "fit_effect", fit_effect)
    monkeypatch.setattr(solver_check, "gap_per_window", lambda spec, sim, held: np.outer(converged_gap, [1, 1]))
    other = _ConvergedStub()
    choice = solver_check.SolverChoice(
        _StubResimulator(), {"checked": True, "taken": "own", "reason": "fitted alone"}, "own memo"
    )
    return held, other, dataclasses.replace(choice, converged=(other, "converged memo"))


@pytest.mark.parametrize(("converged_gap", "taken"), [(0.6, "converged"), (0.9, "own")])
def test_solver_recheck_takes_a_converged_solve_where_the_named_effects_fit_materially_better(
    monkeypatch, converged_gap, taken
):
    """The check kept the sim env's own solver; the selection under it named two effects, which leave a held-out
    gap of about 1.0 per window. Refitted together under the converged solve (from their values under the own) they
    leave `converged_gap` times that: 40 % less takes the converged solve and its first step's fits, 10 % less keeps
    the own; the check records the test either way."""
    ripple = 1 + 0.1 * (np.arange(32) % 3)
    refitted = []
    held, other, choice = _recheck_inputs(monkeypatch, converged_gap * ripple, refitted)
    vocab = vocabulary(SPEC, None, None)
    named = [(vocab[n], SimpleNamespace(values=v)) for n, v in (("joint_friction", [2.0]), ("motor_strength", [0.8]))]
    gap_after = np.outer(ripple, [1, 1])
    rechecked = solver_check.recheck_with_named(choice, named, None, held, PhysicsParams(), gap_after, FitConfig())
    assert refitted[0][0] == ["joint_friction", "motor_strength"]
    np.testing.assert_allclose(refitted[0][1], [2.0, 0.8])
    named_set = rechecked.check["named_set"]
    assert named_set["effects"] == ["joint_friction", "motor_strength"] and named_set["taken"] == taken
    assert rechecked.check["taken"] == taken, named_set["reason"]
    assert (rechecked.resim is other, rechecked.first_step) == (
        (True, "converged memo") if taken == "converged" else (False, "own memo")
    )


@pytest.mark.parametrize(
    ("named", "converged_gap", "taken"),
    [(["joint_friction"], 0.6, "converged"), (["joint_friction"], 0.9, "own"), ([], 0.6, "own")],
)
def test_where_the_own_solver_names_nothing_a_converged_selection_that_names_and_fits_better_is_taken(
    named, converged_gap, taken
):
    """The own solver named nothing with the gap above the floor (about 1.0 per held-out window); the selection under
    the converged solve named `named` and left `converged_gap` times that. It is taken where it names something and
    leaves materially less; the check records the test either way."""
    held = SimpleNamespace(episode=np.repeat(np.arange(4), 8), start=np.tile(np.arange(0, 160, 20), 4))
    ripple = 1 + 0.1 * (np.arange(32) % 3)
    vocab = vocabulary(SPEC, None, None)
    check = {"checked": True, "taken": "own", "reason": "fitted alone"}
    out = solver_check.named_only_under_converged(
        check,
        np.outer(ripple, [1, 1]),
        [(vocab[n], SimpleNamespace(values=[2.0])) for n in named],
        np.outer(converged_gap * ripple, [1, 1]),
        held,
        FitConfig(),
    )
    record = out["unexplained_under_own"]
    assert (out["taken"], record["taken"], record["named"]) == (taken, taken, named), record["reason"]
    assert check["taken"] == "own"  # the check handed in is left as it was


@pytest.mark.parametrize(
    ("iterations", "converged_gap", "taken"), [(40, 0.95, "converged"), (40, 1.05, "own"), (4, 0.5, None)]
)
def test_solver_recheck_after_a_finer_contact_solver_was_named(monkeypatch, iterations, converged_gap, taken):
    """Joint friction and a contact solver of `iterations` were named under the sim env's own solver (4 iterations).
    More iterations already say the own solver is too coarse: friction alone is refitted under the converged solve,
    which is taken where it leaves no more than the named pair (no material margin needed). A contact solver of the
    own iteration count (no-slip or cone only) is no change a converged solve makes, so there is nothing to test."""
    refitted = []
    held, other, choice = _recheck_inputs(monkeypatch, np.full(32, converged_gap), refitted)
    vocab = vocabulary(SPEC, None, SolverSettings(iterations=4))
    named = [
        (vocab["joint_friction"], SimpleNamespace(values=[2.0])),
        (vocab["contact_solver"], SimpleNamespace(values=[iterations, 0, 0])),
    ]
    gap_after = np.ones((32, 2))
    rechecked = solver_check.recheck_with_named(choice, named, None, held, PhysicsParams(), gap_after, FitConfig())
    if taken is None:
        assert rechecked is choice and not refitted
        return
    assert [names for names, _ in refitted] == [["joint_friction"]]
    assert rechecked.check["named_set"]["refitted"] == ["joint_friction"]
    assert rechecked.check["taken"] == taken, rechecked.check["named_set"]["reason"]
    assert (rechecked.resim is other) == (taken == "converged")


@pytest.mark.slow
@pytest.mark.parametrize("name", NAMED_AT_DEFAULT)
def test_workflow_defaults_name_hidden_effect(tmp_path, name):
    """Every effect under the workflow's defaults (the sim env's own solver, and the solver check)."""
    _hidden_and_check(tmp_path, name, episodes=DEFAULT_EPISODES.get(name, 6), config=GapConfig())


@pytest.mark.slow  # three selections' worth of fitting, for a verdict of none (the fit itself: test_gap_effects)
def test_torque_speed_limit_is_fitted_but_shows_in_too_few_windows_to_name(tmp_path):
    """A drive losing 15 N·m per rad/s above 1.5 rad/s: the excitation policy rarely drives a joint fast and hard at
    once, so the gap sits in a few windows. Its fit is right (14.0 N·m·s/rad) and removes three quarters of the
    held-out gap, but the floor's rank test on 6 episodes gives p = 0.93 (0.19 on 9) and the cross-fitted test 0.25
    (0.13), short of p < 0.01 / candidates, so the workflow names nothing."""
    effect = EFFECTS["torque_speed_limit"]
    data = make_measured(
        {"torque_speed_limit": effect.values_from_magnitude(15.0)}, 6, tmp_path / "m.h5", max_steps=150, progress=False
    )
    report = run_gap(SIM, data, tmp_path / "report", progress=False)
    best = report["candidates"][0]
    assert best["effect"] == "torque_speed_limit" and abs(best["values"][0] - 15.0) <= 0.25 * 15.0, best
    assert best["gap_mean"] <= 0.5 * report["gap_before"]
    assert report["identifiability"]["torque_speed_limit"]["identifiable"]


def test_a_robot_that_collapses_within_a_second_is_scored_on_the_steps_it_has(tmp_path):
    """Torque limit at 8 N·m (10 % of the data sheet's): every episode ends in a fall after about 20 steps, shorter
    than the last gap horizon (25). The held-out windows are cut to the shortest held-out episode, not refused."""
    data = make_measured({"torque_limit": [8.0]}, 9, tmp_path / "m.h5", max_steps=150, progress=False)
    assert max(Dataset.load(data).episode_lengths) < 2 + 1 + 25
    report = run_gap(SIM, data, tmp_path / "report", config=CONVERGED, progress=False)
    assert report["gap_horizons"][:2] == [1, 5] and 5 < report["gap_horizons"][2] < 25
    assert list(report["gap_before_per_horizon"]) == [str(h) for h in report["gap_horizons"]]
    assert report["effect"] == "torque_limit", report["reason"]
    assert abs(report["parameters"]["torque_limit"] - 8.0) <= 0.25 * (80.0 - 8.0)
    assert report["gap_after"] <= 0.3 * report["gap_before"]


def test_backlash_workflow_and_world_model_rows(tmp_path):
    """Backlash hidden: named, fitted, written as an env option; then the world-model rows with a tiny model."""
    report = _hidden_and_check(
        tmp_path,
        "backlash",
        episodes=EPISODES["backlash"],
        world_model=_tiny_world_model(tmp_path / "tiny.safetensors"),
    )
    corrected = json.loads(open(report["corrected"]["physics"]).read())["physics"]
    assert corrected["backlash"] == pytest.approx(report["parameters"]["backlash"])
    assert "backlash" in open(report["corrected"]["mjcf"]).read().split("<mujoco")[0]
    wm = report["world_model"]
    assert set(wm["error"]) == {
        "nominal_sim",
        "corrected_sim",
        "world_model_nominal",
        "world_model_corrected",
        "world_model_control",
    }
    assert list(wm["windows"]) == ["1", "5", "25"] and all(n > 0 for n in wm["windows"].values())
    for n in wm["windows"]:
        assert wm["error"]["corrected_sim"][n] < wm["error"]["nominal_sim"][n]
        assert wm["error"]["world_model_corrected"][n] != wm["error"]["world_model_nominal"][n]
    assert wm["config"]["iterations"] == 20 and (tmp_path / "report" / "world_model_error.png").is_file()
    assert "world_model_corrected" in (tmp_path / "report" / "report.md").read_text()


def test_per_leg_form_of_joint_effects():
    assert leg_groups(SPEC) == {"LF": [0, 1, 2], "RF": [3, 4, 5], "LH": [6, 7, 8], "RH": [9, 10, 11]}
    leg = per_leg(EFFECTS["joint_friction"], SPEC)
    assert [p.name for p in leg.parameters] == [
        "joint_friction_LF",
        "joint_friction_RF",
        "joint_friction_LH",
        "joint_friction_RH",
    ]
    assert leg.physics([1.0, 2.0, 3.0, 4.0]).joint_friction == (1.0,) * 3 + (2.0,) * 3 + (3.0,) * 3 + (4.0,) * 3
    assert per_leg(EFFECTS["torque_limit"], SPEC).physics([10, 20, 30, 40]).torque_limit[3:6] == (20.0,) * 3
    assert per_leg(EFFECTS["payload"], SPEC) is None and per_leg(EFFECTS["action_delay"], SPEC) is None


@pytest.mark.parametrize(
    "config",
    [
        pytest.param(CONVERGED, id="converged"),
        # the check's own case for fitting the per-group forms under both solvers (`gap.solver_check`)
        pytest.param(GapConfig(), id="defaults", marks=pytest.mark.slow),
    ],
)
def test_workflow_finds_friction_in_one_leg(tmp_path, config):
    true = [6.0] * 3 + [0.0] * 9  # N·m, the LF leg only
    data = make_measured(
        {}, 6, tmp_path / "m.h5", max_steps=150, extra_physics={"joint_friction": true}, progress=False
    )
    report = run_gap(SIM, data, tmp_path / "report", config=config, progress=False)
    assert (report["effect"], report["scope"]) == ("joint_friction", "leg"), report["reason"]
    fitted = report["parameters"]
    assert abs(fitted["joint_friction_LF"] - 6.0) <= 0.25 * 6.0
    assert max(fitted[f"joint_friction_{leg}"] for leg in ("RF", "LH", "RH")) < 1.0
    assert report["gap_after"] <= 0.5 * report["gap_before"]
    corrected = json.loads(open(report["corrected"]["physics"]).read())["physics"]["joint_friction"]
    assert corrected[:3] == [pytest.approx(fitted["joint_friction_LF"])] * 3


def test_cli_without_effect_says_none(tmp_path, capsys):
    measured, out = tmp_path / "m.h5", tmp_path / "report"
    assert main(["make-measured", "--episodes", "6", "--max-steps", "150", "--out", str(measured)]) == 0
    assert main(["gap", "--sim", SIM, "--measured", str(measured), "--out", str(out), "--world-model", "none"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["effect"] == "none" and report["parameters"] == {} and report["effects"] == []
    floor = report["noise_floor"]  # no effect: the gap is not above the sensor-noise floor
    assert not floor["above_floor"] and floor["floor"] > 0 and "Wilcoxon" in floor["test"]
    assert "is not above the sensor-noise floor" in report["reason"]
    assert ("< 1.2" in report["reason"]) == (floor["ratio"] < 1.2)  # the reason names the parts of the test that failed
    assert (">= 0.01" in report["reason"]) == (floor["p_value"] >= 0.01)
    assert report["learned_correction"] is None and set(report["identifiability"]) == set(EFFECT_NAMES)
    assert report["solver"]["check"]["checked"]  # the defaults: the sim env's own solver, checked
    missing = tmp_path / "missing.safetensors"
    assert main(["gap", "--measured", str(measured), "--out", str(out), "--world-model", str(missing)]) == 2
    assert "missing.safetensors not found" in capsys.readouterr().err
    assert main(["gap", "--measured", str(measured), "--out", str(out), "--joint-candidates", "-1"]) == 2
    assert "argument --joint-candidates: must be >= 0, got -1" in capsys.readouterr().err
    assert (out / "report.md").is_file() and (out / "residual_channels.png").is_file()


_KNOWN_LIMITS = {
    ("torque_limit", 0.5): "56 N·m is reached in few windows: on 6 episodes even the cross-fitted test misses "
    "p < 0.01 / candidates (p = 0.004), so none; the grid's 9 episodes name it",
    ("torque_limit", 2.0): "clipped to 8 N·m the robot collapses: no episode is long enough for held-out windows",
    ("backlash", 0.5): "0.015 rad lies at the sensor-noise floor: named on the grid's 9 episodes, not always on 6",
}


@pytest.mark.slow
@pytest.mark.parametrize(
    "name,scale",
    [
        pytest.param(n, s, marks=pytest.mark.xfail(reason=_KNOWN_LIMITS[n, s], strict=False))
        if (n, s) in _KNOWN_LIMITS
        else (n, s)
        for s in (0.5, 2.0)
        for n in ROBOT_EFFECTS
    ],
)
def test_workflow_other_magnitudes(tmp_path, name, scale):
    _hidden_and_check(tmp_path, name, scale, episodes=DEFAULT_EPISODES.get(name, 6), config=GapConfig())

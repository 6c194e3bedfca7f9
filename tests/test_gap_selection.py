"""The gap workflow's second round: blow-ups rejected with a reason, the sensor-noise floor, scopes from joint names,
two effects named in order, an effect outside the vocabulary (unexplained, then learned), and ordinary-policy logs."""

from __future__ import annotations

import dataclasses
import json
import warnings
from types import SimpleNamespace

import mujoco
import numpy as np
import pytest

from rwm_gym.cli import main
from rwm_gym.data.dataset import Dataset
from rwm_gym.gap.cross_fit import CrossFit, cross_fitted_p_value
from rwm_gym.gap.effects import vocabulary
from rwm_gym.gap.fit import (
    FitConfig,
    FitInputs,
    FitMemo,
    fit_all,
    fit_effect,
    gap_per_window,
    score_fit,
    screen_grid,
)
from rwm_gym.gap.identifiability import identifiability
from rwm_gym.gap.judge import resolve_rivals
from rwm_gym.gap.learned import (
    LearnedCorrectionConfig,
    LinearResidualTorque,
    group_matrix,
    load_correction,
    save_correction,
)
from rwm_gym.gap.measured import SensorNoise, make_measured, write_spring_model
from rwm_gym.gap.noise_floor import FloorConfig, noise_floor
from rwm_gym.gap.refit import joint_candidates, named_params
from rwm_gym.gap.resim import Resimulator, SimulationDiverged, make_windows, normalised_residual
from rwm_gym.gap.scope import JOINT_EFFECTS, joint_groups, outlying_joint, per_joint_brackets, scope_candidates, scoped
from rwm_gym.gap.step import Search
from rwm_gym.gap.workflow import GapConfig, run_gap
from rwm_gym.physics.params import CONVERGED_SOLVER, PhysicsParams, build_model
from rwm_gym.spec import load_spec

SPEC = load_spec("anymal_d")
EFFECTS = vocabulary(SPEC)
SIM = "AnymalD-MuJoCo-v0"
CONVERGED = GapConfig(solver=CONVERGED_SOLVER)
"""A converged re-simulation, as make-measured's robot is solved: no solver to check (see test_gap.CONVERGED)."""


@pytest.fixture(scope="module")
def nominal_data(tmp_path_factory):
    path = tmp_path_factory.mktemp("nominal") / "m.h5"
    return Dataset.load(make_measured({}, 3, path, max_steps=60, progress=False))


def test_blow_up_is_rejected_with_mujocos_reason(nominal_data, capfd):
    """Damping of 500 N·m·s/rad makes MuJoCo's integration blow up (and reset the simulation) in some windows: the
    re-simulation raises with MuJoCo's warning, and the fit rejects that point and the candidate, saying why."""
    windows = make_windows(nominal_data, np.arange(3), 25, 5)
    resim = Resimulator(SPEC)
    handler = mujoco.get_mju_user_warning()  # None, or one that another library installed (dm_control does)
    with pytest.raises(SimulationDiverged, match="QACC") as err:
        resim.rollout(windows, PhysicsParams(joint_damping=500.0))
    assert 0 < err.value.windows.sum() < len(windows)  # only some windows blew up, and they are marked
    assert "QACC" not in "".join(capfd.readouterr())  # said once, in the reason, not printed by MuJoCo as well
    assert mujoco.get_mju_user_warning() is handler  # the handler in place before is back
    damping = EFFECTS["joint_damping"]
    train = make_windows(nominal_data, np.arange(3), 5, 8)
    rejected: list[str] = []
    fit = fit_effect(
        damping,
        resim,
        train,
        PhysicsParams(),
        FitConfig(max_evaluations=3),
        np.array([500.0]),
        (499.0, 500.0),
        rejected,
    )
    assert rejected and all("joint_damping=" in r and "QACC" in r for r in rejected)
    before = gap_per_window(SPEC, resim.rollout(windows, PhysicsParams()), windows)
    fit.values = [500.0]
    assert score_fit(fit, damping, resim, windows, PhysicsParams(), before, FitConfig()) is before
    assert fit.status.startswith("rejected: the simulation blows up") and fit.score == -np.inf


def test_noise_floor_of_exact_simulator_matches_nominal_gap(nominal_data):
    """On data of the nominal robot the nominal gap is noise only: the floor is of the same size, and without
    sensor noise both vanish."""
    windows = make_windows(nominal_data, np.arange(3), 25, 5)
    resim = Resimulator(SPEC)
    floor = noise_floor(resim, windows, PhysicsParams(), SensorNoise())
    gap = gap_per_window(SPEC, resim.rollout(windows, PhysicsParams()), windows)
    assert 0.4 < gap.mean() / floor.mean() < 2.5
    assert noise_floor(resim, windows, PhysicsParams(), SensorNoise(scale=0.0)).mean() < 1e-6 < floor.mean()


def test_a_window_whose_every_noise_draw_blows_up_has_no_floor_and_no_warning(nominal_data):
    """Where the noisy twin of a window blows up in every draw, its floor is NaN (left out of the test), the other
    windows' floors are the mean of their draws, and no warning reaches the user."""
    windows = make_windows(nominal_data, np.arange(2), 25, 10)
    resim = Resimulator(SPEC)
    rollout = resim.rollout

    def first_window_blows_up(twin, params, **kw):
        if len(twin) == len(windows):
            raise SimulationDiverged("blew up", np.arange(len(twin)) == 0)
        return rollout(twin, params, **kw)

    resim.rollout = first_window_blows_up
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        floor = noise_floor(resim, windows, PhysicsParams(), SensorNoise())
    assert np.isnan(floor[0]).all() and np.isfinite(floor[1:]).all() and (floor[1:] > 0).all()


def test_fits_made_once_are_taken_again_only_on_the_same_inputs(nominal_data):
    """The solver check hands its step-1 fits on (`fit.FitMemo`): asked again on the same windows, simulator and
    base, the memo answers with copies of the same fits and only an effect it has not seen is fitted; on another
    base it answers nothing."""
    train, held = make_windows(nominal_data, np.arange(2), 5, 8), make_windows(nominal_data, [2], 25, 5)
    resim, config, base = Resimulator(SPEC), FitConfig(refine_top=1, max_evaluations=3), PhysicsParams()
    before = gap_per_window(SPEC, resim.rollout(held, base), held)
    inputs = FitInputs(resim, train, held, base, before, config)
    memo = FitMemo(inputs)
    names = ("armature", "motor_strength")
    first = fit_all({n: EFFECTS[n] for n in names}, inputs, False, memo=memo)
    rollouts = []
    rollout = resim.rollout
    resim.rollout = lambda windows, params, **kw: rollouts.append(params) or rollout(windows, params, **kw)
    effects = {n: EFFECTS[n] for n in (*names, "joint_damping")}
    again = fit_all(effects, inputs, False, memo=memo)
    assert rollouts and all(p.joint_damping != 0 or p == base for p in rollouts)  # only the new effect was fitted
    by_name = {f.effect: f for f in again}
    assert [json.dumps(dataclasses.asdict(by_name[f.effect])) for f in first] == [
        json.dumps(dataclasses.asdict(f)) for f in first
    ]
    by_name["armature"].values[0] = -1.0  # a caller changing a fit changes no memo
    third = fit_all(effects, inputs, False, memo=memo)
    assert next(f for f in third if f.effect == "armature").values[0] != -1.0
    rollouts.clear()
    other = PhysicsParams(armature=0.01)
    fit_all({"armature": EFFECTS["armature"]}, dataclasses.replace(inputs, base=other), False, memo=memo)
    assert rollouts  # another base: fitted afresh, not answered from the memo


@pytest.mark.parametrize("stride", [2, 1])
def test_the_coarse_grid_is_screened_on_every_other_fitting_window_and_refined_on_all(tmp_path, stride):
    """Screening only ranks effects and brackets their refinement: it re-simulates every `screen_stride`-th fitting
    window (its nominal cost on the same ones); the refinement then fits every window."""
    armature = EFFECTS["armature"].values_from_magnitude(0.1)
    data = Dataset.load(make_measured({"armature": armature}, 3, tmp_path / "m.h5", max_steps=60, progress=False))
    train, held = make_windows(data, np.arange(2), 5, 4), make_windows(data, [2], 25, 5)
    resim, base = Resimulator(SPEC), PhysicsParams()
    config = FitConfig(refine_top=1, max_evaluations=3, screen_stride=stride)
    inputs = FitInputs(resim, train, held, base, gap_per_window(SPEC, resim.rollout(held, base), held), config)
    fitted = []  # windows of each re-simulation of fitting windows (the held-out ones are 25 steps long)
    rollout = resim.rollout
    resim.rollout = lambda windows, params, **kw: (
        (fitted.append(len(windows)) if windows.horizon == 5 else None) or rollout(windows, params, **kw)
    )
    (fit,) = fit_all({"armature": EFFECTS["armature"]}, inputs, False)
    screened = len(range(0, len(train), stride))
    grid = len(screen_grid(EFFECTS["armature"], config.grid_fractions))  # the nominal point's cost is the first
    assert len(train) == 28 and fitted[:grid] == [screened] * grid and len(fitted) > grid
    assert fitted[grid:] == [len(train)] * (len(fitted) - grid) and not np.isnan(fit.uncertainty[0])  # refined
    with pytest.raises(ValueError, match="screen_stride must be >= 1"):
        FitConfig(screen_stride=0)


@pytest.mark.parametrize(
    ("config", "field", "value", "rule"),
    [
        (FitConfig, "max_evaluations", 0, ">= 1"),
        (FitConfig, "significance", 1.0, "> 0 and < 1"),
        (FitConfig, "spread_points", 1, ">= 2"),
        (GapConfig, "fit_stride", 0, ">= 1"),
        (GapConfig, "warmup", -1, ">= 0"),
        (FloorConfig, "draws", 0, ">= 1"),
    ],
)
def test_a_gap_setting_out_of_range_is_refused_by_name(config, field, value, rule):
    with pytest.raises(ValueError, match=f"{config.__name__}.{field} must be {rule}, got {value}"):
        config(**{field: value})


def test_joint_groups_come_from_the_joint_names():
    assert joint_groups(SPEC, "joint_type") == {"HAA": [0, 3, 6, 9], "HFE": [1, 4, 7, 10], "KFE": [2, 5, 8, 11]}
    assert joint_groups(SPEC, "leg")["RH"] == [9, 10, 11] and len(joint_groups(SPEC, "joint")) == 12
    other = SimpleNamespace(actuator=SimpleNamespace(joints=["left_hip", "left_knee", "right_hip", "right_knee"]))
    assert joint_groups(other, "leg") == {"left": [0, 1], "right": [2, 3]}
    assert joint_groups(other, "joint_type") == {"hip": [0, 2], "knee": [1, 3]}
    flat = SimpleNamespace(actuator=SimpleNamespace(joints=["a", "b", "c"]))
    assert joint_groups(flat, "leg") == {} and len(joint_groups(flat, "joint")) == 3
    kfe = scoped(EFFECTS["armature"], SPEC, "joint_type")
    assert [p.name for p in kfe.parameters] == ["armature_HAA", "armature_HFE", "armature_KFE"]
    assert kfe.physics([0.0, 0.1, 0.2]).armature == (0.0, 0.1, 0.2) * 4
    assert scoped(EFFECTS["payload"], SPEC, "joint_type") is None


def test_spring_model_edits_the_mjcf(tmp_path):
    path = write_spring_model(SPEC, tmp_path / "spring.xml", "KFE", 30.0)
    model = mujoco.MjModel.from_xml_path(str(path))
    kfe = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, j) for j in SPEC.actuator.joints if j.endswith("KFE")]
    assert np.count_nonzero(model.jnt_stiffness) == 4 and np.all(model.jnt_stiffness[kfe] == 30.0)
    with pytest.raises(ValueError, match="no actuated joint"):
        write_spring_model(SPEC, tmp_path / "x.xml", "ELBOW", 1.0)


@pytest.mark.slow  # a known limit that costs ~50 s: kept out of the default run
@pytest.mark.xfail(
    strict=False,
    reason="measured on 6 episodes with the pyramidal-cone MJCF: 'unexplained' (global "
    "friction 21 %, p=0.12); the 9-episode grid case named it (KFE, error 9 %)",
)
def test_friction_in_one_joint_type_is_named_per_joint_type(tmp_path):
    true = [0.0, 0.0, 4.0] * 4  # N·m, the knees (KFE) only
    data = make_measured(
        {}, 6, tmp_path / "m.h5", max_steps=150, extra_physics={"joint_friction": true}, progress=False
    )
    report = run_gap(SIM, data, tmp_path / "report", progress=False, fit_config=FitConfig(scopes=("joint_type",)))
    assert report["noise_floor"]["above_floor"]
    assert (report["effect"], report["scope"]) == ("joint_friction", "joint_type"), report["reason"]
    fitted = report["parameters"]
    assert abs(fitted["joint_friction_KFE"] - 4.0) <= 0.25 * 4.0
    assert max(fitted["joint_friction_HAA"], fitted["joint_friction_HFE"]) < 1.0
    assert report["gap_after"] <= 0.5 * report["gap_before"]


@pytest.mark.slow  # two selection steps and a joint refit on 9 episodes: the heaviest gap test
def test_two_effects_are_named_in_order_with_their_shares(tmp_path):
    data = make_measured(
        {"joint_friction": [3.0], "payload": [8.0, 0.1, 0.0]}, 9, tmp_path / "m.h5", max_steps=150, progress=False
    )
    report = run_gap(
        SIM,
        data,
        tmp_path / "report",
        progress=False,
        fit_config=FitConfig(scopes=()),
        config=GapConfig(learned_correction=False),
    )
    named = [e["effect"] for e in report["effects"]]
    assert sorted(named) == ["joint_friction", "payload"], report["reason"]
    assert sum(e["share_of_explained_gap"] for e in report["effects"]) == pytest.approx(1.0)
    assert abs(report["parameters"]["joint_friction"] - 3.0) <= 0.75
    assert abs(report["parameters"]["payload_mass"] - 8.0) <= 3.5  # measured 10.4 kg: mass and offset trade off
    assert not report["residual"]["above_floor"]


def test_what_is_left_is_judged_against_the_corrected_simulators_floor(tmp_path):
    """Floor friction 0.3 under the walking gait: the feet slip, and the same sensor noise carries about 3x further
    than in the nominal simulator. Named and fitted right, the effect leaves a gap above the nominal floor that is
    noise under the corrected simulator; it is judged against that floor, so no residual torque is learned for it."""
    data = make_measured({"ground_friction": [0.3]}, 9, tmp_path / "m.h5", max_steps=150, policy="gait", progress=False)
    one = FitConfig(max_effects=1)  # the residual test after the named effect is what is checked here
    report = run_gap(SIM, data, tmp_path / "report", config=CONVERGED, fit_config=one, progress=False)
    assert report["effect"] == "ground_friction", report["reason"]
    assert abs(report["parameters"]["ground_friction"] - 0.3) <= 0.25 * 0.7
    residual, nominal_floor = report["residual"], report["noise_floor"]["floor"]
    assert residual["floor_of"] == "the corrected simulator"
    assert residual["floor"] > 2.0 * nominal_floor
    assert report["gap_after"] > 2.0 * nominal_floor  # above the nominal simulator's floor ...
    assert not residual["above_floor"] and report["learned_correction"] is None  # ... but not above its own


def test_spring_outside_the_vocabulary_is_unexplained_then_learned(tmp_path):
    """A knee spring is no effect of the vocabulary: the gap is far above the noise floor, nothing is named (not
    `none`), and the learned residual torque shrinks the held-out gap; the report says it is learned, and its knee
    weight is the spring (N·m per rad of deflection), while the other joint types get none. Walking data."""
    xml = write_spring_model(SPEC, tmp_path / "spring.xml", "KFE", 30.0)
    data = make_measured(
        {}, 6, tmp_path / "m.h5", max_steps=150, env_kwargs={"xml_file": str(xml)}, policy="gait", progress=False
    )
    # a knee spring: the scope that could stand in for it; no spread check (on these data a slippery floor covers
    # the spring's misfit and is not named: test_gap_spread); the best screened effects refined and in their scopes
    # only (refining every effect and scope before `unexplained` is tested with stubs below; it halves this test)
    knee = FitConfig(scopes=("joint_type",), spread_check=False, refine_every_effect=False, every_scope=False)
    report = run_gap(SIM, data, tmp_path / "report", config=CONVERGED, fit_config=knee, progress=False)
    assert report["noise_floor"]["above_floor"] and report["noise_floor"]["ratio"] > 2
    assert report["effect"] == "unexplained" and report["effects"] == [], report["reason"]
    learned = report["learned_correction"]
    assert learned["status"] == "ok" and "not a named effect" in learned["kind"]
    assert learned["gap_after"] <= 0.5 * learned["gap_before"] and learned["kept"]
    weights = learned["training"]["weights"]
    assert abs(weights["KFE"]["deflection (N·m/rad)"] + 30.0) <= 0.25 * 30.0, weights
    assert max(abs(weights[g]["deflection (N·m/rad)"]) for g in ("HAA", "HFE")) < 5.0, weights
    saved = load_correction(tmp_path / "report" / "learned_correction.safetensors", SPEC)
    assert saved.weights[2, 0] == pytest.approx(weights["KFE"]["deflection (N·m/rad)"], abs=1e-4)
    assert "Learned correction (not a named effect)" in (tmp_path / "report" / "report.md").read_text()


def test_walking_policy_data_and_identifiability(tmp_path, capsys):
    """make-measured --policy gait: an ordinary walking log; the identifiability section says, per effect, whether
    such data can reveal it at all."""
    out = tmp_path / "walk.h5"
    assert main(["make-measured", "--policy", "gait", "--episodes", "2", "--max-steps", "60", "--out", str(out)]) == 0
    assert "(hidden: nothing)" in capsys.readouterr().out
    data = Dataset.load(out)
    assert data.info.policy == "unknown" and data.num_episodes == 2
    heavy = ["--physics", '{"payload_mass": 5.0}', "--effect", "action_delay", "--out", str(tmp_path / "heavy.h5")]
    assert main(["make-measured", "--policy", "gait", "--episodes", "1", "--max-steps", "5", *heavy]) == 0
    assert "(hidden: action_delay, payload_mass)" in capsys.readouterr().out
    assert main(["make-measured", "--policy", "dance", "--out", str(tmp_path / "x.h5")]) == 2
    assert "unknown policy 'dance'" in capsys.readouterr().err
    windows = make_windows(data, np.arange(2), 25, 10)
    resim = Resimulator(SPEC)
    nominal = resim.rollout(windows, PhysicsParams())
    table = identifiability(EFFECTS, resim, windows, PhysicsParams(), nominal, 1e-3)
    assert set(table) == set(EFFECTS)
    assert all(v["signal"] >= 0 and v["identifiable"] == (v["signal_to_floor"] >= 1.0) for v in table.values())
    assert table["ground_friction"]["signal"] > table["backlash"]["signal"]
    json.dumps(table)


def test_per_joint_brackets_reach_an_effect_held_by_one_joint_of_a_group():
    friction = EFFECTS["joint_friction"].parameters[0]  # 0 .. 8 N·m
    leg_fit = SimpleNamespace(scope="leg", values=[2.0, 0.0, 0.0, 0.0])  # LF fitted 2: one LF joint may hold 6
    brackets = per_joint_brackets(SPEC, leg_fit, friction)
    assert brackets[:3] == [(0.0, 8.0)] * 3 and brackets[3:] == [(0.0, 2.0)] * 9


def test_friction_in_one_joint_is_found_at_that_joint(tmp_path):
    """Friction in the LF knee only explains next to nothing spread over all joints, a leg or a joint type, but the
    knee's residual stands out from every other joint's (`outlying_joint`), so every joint effect is also fitted at
    that joint alone: friction there finds the true value and explains more of the held-out gap than any other."""
    knee = SPEC.actuator.joints.index("LF_KFE")
    true = np.zeros(12)
    true[knee] = 6.0  # N·m
    data = Dataset.load(
        make_measured(
            {}, 8, tmp_path / "m.h5", max_steps=150, extra_physics={"joint_friction": true.tolist()}, progress=False
        )
    )
    train_ids, held_ids = data.split_episodes(GapConfig.val_fraction, GapConfig.split_seed)
    train, held = make_windows(data, train_ids, 5, GapConfig.fit_stride), make_windows(data, held_ids, 25, 5)
    resim, base, config = Resimulator(SPEC), PhysicsParams(), FitConfig()
    assert outlying_joint(SPEC, resim, train, base) == knee
    before = gap_per_window(SPEC, resim.rollout(held, base), held)
    forms = scope_candidates([], EFFECTS, FitInputs(resim, train, held, base, before, config))
    assert {(e.name, f.scope) for e, f in forms} == {(name, "joint") for name in JOINT_EFFECTS}
    best = max((f for _, f in forms), key=lambda f: f.score)
    assert (best.effect, best.names) == ("joint_friction", ["joint_friction_LF_KFE"])
    assert abs(best.values[0] - 6.0) <= 0.25 * 6.0 and best.explained_fraction > 0.5


def test_no_joint_stands_out_on_nominal_data(nominal_data):
    train = make_windows(nominal_data, np.arange(3), 5, 8)
    assert outlying_joint(SPEC, Resimulator(SPEC), train, PhysicsParams()) is None


def test_the_deviant_joint_is_measured_against_the_same_joint_in_the_other_legs(monkeypatch):
    """A hip flexion joint whose residual is 1.5x its siblings' but below every knee's stands out against its type
    (`deviant_joint`) though not against every joint (`outlying_joint`); it gets the single-joint fits beside the
    outlier's, and a joint that is both is fitted once."""
    from rwm_gym.gap import scope

    joints = list(SPEC.actuator.joints)
    err = np.array([0.3 if j.endswith("HAA") else 0.4 if j.endswith("HFE") else 1.0 for j in joints])
    err[joints.index("RF_KFE")] = 1.1
    err[joints.index("LF_HFE")] = 0.6
    monkeypatch.setattr(scope, "_joint_residuals_under", lambda *args: err)
    assert scope.outlying_joint(SPEC, None, None, None) is None
    assert scope.deviant_joint(SPEC, None, None, None) == joints.index("LF_HFE")
    fitted = []
    monkeypatch.setattr(scope, "_single_joint_fits", lambda joint, effects, inputs: fitted.append(joint) or ["fits"])
    inputs = FitInputs(SimpleNamespace(spec=SPEC), None, None, PhysicsParams(), None, FitConfig())
    assert scope.single_joint_candidates(EFFECTS, inputs) == ["fits"] and fitted == [joints.index("LF_HFE")]
    err[joints.index("RF_KFE")] = 3.0  # an outlier (3x every other joint, 3x its siblings) beside the deviant
    err[[i for i, j in enumerate(joints) if j.endswith("HFE") and j != "LF_HFE"]] = 0.1  # joint (6x its siblings)
    assert scope.outlying_joint(SPEC, None, None, None) == joints.index("RF_KFE")
    fitted.clear()
    assert scope.single_joint_candidates(EFFECTS, inputs) == ["fits", "fits"]
    assert fitted == [joints.index("RF_KFE"), joints.index("LF_HFE")]
    err[joints.index("LF_HFE")] = 9.0  # the deviant joint is also the outlier: fitted once
    fitted.clear()
    assert scope.single_joint_candidates(EFFECTS, inputs) == ["fits"] and fitted == [joints.index("LF_HFE")]
    off = dataclasses.replace(inputs, config=FitConfig(scopes=("leg", "joint_type")))
    assert scope.single_joint_candidates(EFFECTS, off) == []


def test_solver_settings_are_an_env_option_and_the_gap_default():
    assert build_model(SPEC).opt.iterations == 4  # the fast MJCF for PPO
    model = build_model(SPEC, solver=CONVERGED_SOLVER)
    assert (model.opt.iterations, model.opt.ls_iterations, model.opt.noslip_iterations) == (100, 50, 2)
    from rwm_gym.physics.locomotion import make_core

    assert make_core("anymal_d", 1, solver={"iterations": 30}).model.opt.iterations == 30
    with pytest.raises(ValueError, match="unknown solver setting"):
        make_core("anymal_d", 1, solver={"tolerance": 1e-9})
    assert Resimulator(SPEC).model(PhysicsParams()).opt.iterations == 100
    assert GapConfig().solver is None  # the workflow re-simulates with the sim env's own settings


def test_the_gap_is_that_of_the_simulator_as_it_runs(tmp_path):
    """Data from the package's fast physics on a slippery floor: the sim env's own solver at the true friction
    reproduces them, with 4 replayed steps; a converged solver does not. The solver's warm start is state outside
    qpos/qvel that the replayed steps rebuild: with one, a window at a touchdown is left far off (`resim.WARMUP`)."""
    hidden = {"ground_friction": [0.35]}
    path = make_measured(
        hidden, 2, tmp_path / "m.h5", max_steps=60, policy="gait", solver=None, noise=SensorNoise(scale=0.0),
        progress=False,
    )  # fmt: skip
    data = Dataset.load(path)
    truth = PhysicsParams(ground_friction=0.35)

    def error(solver, warmup: int = 4) -> float:
        windows = make_windows(data, np.arange(2), 5, 1, warmup)
        return float(np.abs(Resimulator(SPEC, solver=solver).rollout(windows, truth) - windows.target).max())

    errors = {"own": error(None), "converged": error(CONVERGED_SOLVER), "own, one replayed step": error(None, 1)}
    assert errors["own"] < 1e-3 < min(errors["converged"], errors["own, one replayed step"]), errors


def test_contact_solver_is_an_effect_charged_for_its_parameters(tmp_path):
    """Nominal: the simulator's own settings; its values change the compiled solver (also through the model cache);
    fitted on noise-free data of a converged robot, a finer solve is found."""
    effect = EFFECTS["contact_solver"]
    assert [p.nominal for p in effect.parameters] == [4, 2, 0.0] and effect.physics(effect.nominal) == PhysicsParams()
    assert vocabulary(SPEC, solver=CONVERGED_SOLVER)["contact_solver"].parameters[0].nominal == 100
    params = effect.physics([100, 4, 1])
    for model in (build_model(SPEC, params=params), Resimulator(SPEC, solver=None).model(params)):
        assert (model.opt.iterations, model.opt.ls_iterations, model.opt.noslip_iterations) == (100, 50, 4)
        assert model.opt.cone == mujoco.mjtCone.mjCONE_ELLIPTIC
    assert PhysicsParams.from_dict(json.loads(json.dumps(params.to_dict()))) == params
    path = make_measured({}, 2, tmp_path / "m.h5", max_steps=40, noise=SensorNoise(scale=0.0), progress=False)
    data = Dataset.load(path)
    windows = make_windows(data, np.arange(2), 5, 6)
    resim, config = Resimulator(SPEC, solver=None), FitConfig()
    fit = fit_effect(effect, resim, windows, PhysicsParams(), config, effect.nominal, (4, 100))
    nominal = float(np.mean(normalised_residual(SPEC, resim.rollout(windows, PhysicsParams()), windows.target) ** 2))
    assert fit.values[0] > 4 and fit.train_cost < 1e-3 * nominal, (fit.values, fit.train_cost, nominal)
    assert len(fit.values) == 3  # the score charges penalty_per_parameter for the two beyond the first


def test_the_two_best_joint_effects_that_reduce_the_gap_are_fitted_in_their_scopes(monkeypatch):
    """Friction in a few joints, spread over all of them, may rank below another joint effect that mimics it: the
    two best joint effects get their scoped fits; non-joint effects, rejected fits and forms that explain nothing
    get none."""
    from rwm_gym.gap import scope
    from rwm_gym.gap.fit import CandidateFit

    def fitted(name, score, status="ok"):
        return CandidateFit(
            name, [name], ["1"], [1.0], [0.1], 0.0, explained_fraction=score, score=score, status=status
        )

    fits = [
        fitted("payload", 0.5),
        fitted("joint_damping", 0.2),
        fitted("joint_friction", 0.1),
        fitted("motor_strength", 0.05),
        fitted("armature", -0.3),
        fitted("backlash", 0.4, status="rejected: blew up"),
    ]
    tried = []
    monkeypatch.setattr(scope, "_scoped_fits", lambda best, effect, *args: tried.append(effect.name) or [])
    monkeypatch.setattr(scope, "single_joint_candidates", lambda *args: [])
    no_sim = SimpleNamespace(spec=SPEC)  # nothing is simulated: the fits are stubbed
    scope.scope_candidates(fits, EFFECTS, FitInputs(no_sim, None, None, PhysicsParams(), None, FitConfig()))
    assert tried == ["joint_damping", "joint_friction"]
    tried.clear()
    inputs = FitInputs(no_sim, None, None, PhysicsParams(), None, FitConfig(scoped_effects=5))
    scope.scope_candidates(fits, EFFECTS, inputs)
    assert tried == ["joint_damping", "joint_friction", "motor_strength"]  # not armature: it explains nothing
    tried.clear()
    scope.scope_candidates(fits, EFFECTS, dataclasses.replace(inputs, config=FitConfig(scoped_effects=1)))
    assert tried == ["joint_damping"]


def test_a_large_gap_on_short_held_out_episodes_can_still_be_significant():
    """Two held-out episodes of 6 windows fall into 4 blocks of 25 rows: an exact Wilcoxon test on 4 blocks cannot go
    below 1/16, so a gap 60x the floor was called `none`. Smaller blocks give the test the power to see it."""
    from rwm_gym.gap.significance import MIN_BLOCKS, paired_p_value

    windows = SimpleNamespace(episode=np.repeat([0, 1], 6), start=np.tile(np.arange(0, 30, 5), 2))
    floor = np.full(12, 0.01)
    gap = floor + np.linspace(1.0, 2.0, 12)  # every window far above the floor
    assert paired_p_value(gap, floor, windows, block_rows=25) < 0.01
    assert 2.0**-MIN_BLOCKS < 0.01
    assert paired_p_value(floor, gap, windows, block_rows=25) > 0.5  # and a gap below it is not


def test_with_too_few_windows_for_the_rank_test_the_size_of_the_gap_decides():
    """A robot that falls at once leaves five held-out windows: no rank test on 5 blocks reaches p < 0.01 (its floor is
    2^-5 = 0.031), so a gap 500x the floor was called `none`. There the t-test on log ratios decides: a gap hundreds of
    times the floor is significant, one that wanders around the floor is not."""
    from rwm_gym.gap.significance import paired_p_value, paired_test

    windows = SimpleNamespace(episode=np.arange(5), start=np.zeros(5, dtype=int))
    floor = np.array([0.006, 0.008, 0.007, 0.009, 0.008])
    assert "t-test" in paired_test(windows, 25, 0.01)
    assert paired_p_value(floor * np.array([400, 700, 500, 600, 550]), floor, windows, 25) < 0.01
    assert paired_p_value(floor * np.array([1.3, 0.8, 1.1, 0.9, 1.2]), floor, windows, 25) > 0.1
    many = SimpleNamespace(episode=np.arange(12), start=np.zeros(12, dtype=int))
    assert "Wilcoxon" in paired_test(many, 25, 0.01)


def test_later_steps_refit_the_best_candidates_with_the_named_effects(monkeypatch):
    """A first effect fitted alone can soak up part of a second; on top of it, frozen, the second explains too little.
    The best `joint_candidates` candidates are fitted again together with the named effects: where that scores better
    on held-out windows, the candidate carries the named effects' refitted values; elsewhere it stays as it was."""
    from rwm_gym.gap.fit import CandidateFit

    def fitted(name, values, score):
        return CandidateFit(
            name,
            [name] * len(values),
            ["1"] * len(values),
            list(values),
            [0.1] * len(values),
            0.0,
            explained_fraction=score,
            score=score,
        )

    named = [(EFFECTS["armature"], fitted("armature", [0.1], 0.8))]
    candidates = [
        (EFFECTS["action_delay"], fitted("action_delay", [0.005], 0.10)),
        (EFFECTS["payload"], fitted("payload", [1.0, 0.0, 0.0], 0.05)),
        (EFFECTS["joint_damping"], fitted("joint_damping", [0.5], 0.01)),
    ]
    joint_gap = {"action_delay": 0.2, "payload": 0.99}  # held-out gap of each joint fit, `current` being 1.0
    seen = []

    def fake_fit(effect, resim, train, base, config, start, bracket, max_evaluations=None):
        seen.append(effect.name)
        assert base == PhysicsParams() and bracket is None
        values = list(start)
        values[0] = 0.05  # the named armature, refitted
        return CandidateFit(effect.name, [], [], values, [0.01] * len(values), 0.0)

    def fake_score(fit, effect, resim, held, base, before, config):
        fit.gap_mean = joint_gap[effect.name.split("+")[1]]
        fit.explained_fraction, fit.p_value = 1.0 - fit.gap_mean, 1e-4

    _patch(monkeypatch, "fit_effect", fake_fit)
    _patch(monkeypatch, "score_fit", fake_score)
    out = joint_candidates(candidates, named, [], None, None, None, PhysicsParams(), np.ones((4, 3)), FitConfig())
    assert seen == ["armature+action_delay", "armature+payload"]  # the two best, not joint_damping
    delay, payload, damping = (fit for _, fit in out)
    assert delay.named_refit == [[0.05]] and delay.values == [0.005]
    assert delay.score == pytest.approx(0.8) and delay.p_value == 1e-4
    assert payload is candidates[1][1]  # 1 - 0.99 x 1.2 charged for its 3 parameters: worse than fitted alone
    assert damping is candidates[2][1] and damping.named_refit is None
    assert named_params(named, out[0], PhysicsParams(), PhysicsParams()) == EFFECTS["armature"].physics(
        [0.05], PhysicsParams()
    )
    # the best of the step before (not named, here joint_damping) is fitted jointly too, from its value there
    seen.clear()
    earlier = [
        (EFFECTS["armature"], fitted("armature", [0.1], 0.8)),
        (EFFECTS["joint_damping"], fitted("joint_damping", [0.7], 0.6)),
    ]
    joint_gap["joint_damping"] = 0.5
    starts = []
    _patch(
        monkeypatch,
        "fit_effect",
        lambda effect, *args, **kwargs: starts.append(list(args[4])) or fake_fit(effect, *args, **kwargs),
    )
    out = joint_candidates(candidates, named, earlier, None, None, None, PhysicsParams(), np.ones((4, 3)), FitConfig())
    assert seen == ["armature+action_delay", "armature+payload", "armature+joint_damping"]
    assert starts[-1] == [0.1, 0.7] and out[2][1].named_refit == [[0.05]]


@pytest.mark.parametrize(
    "p_value,floor_ratio,explained,named",
    [
        (1e-4, 1.2, 0.25, True),  # the whole gap is not above the floor, but the candidate's own test is, Bonferroni
        (5e-3, 1.2, 0.25, False),  # significant alone, not over the step's candidates: none
        (1e-4, 0.9, 0.25, False),  # the gap is below the floor: nothing is left to explain
        (5e-3, 3.0, 0.25, True),  # above the floor: a quarter of the gap is 37 % of what lies above it
        (5e-3, 3.0, 0.15, False),  # ... but 15 % of the gap is 22 % of that: too little
    ],
)
def test_a_gap_near_the_floor_is_judged_by_the_candidates_own_test(monkeypatch, p_value, floor_ratio, explained, named):
    """A small backlash or torque limit shows in a few windows: the gap as a whole is not significantly above the
    sensor-noise floor, though fitting the effect removes a significant part of it. Step 1 asks each candidate's own
    held-out test then (at the significance over the number of candidates); the share it must explain is of the gap
    above the floor, which no effect can remove."""
    from rwm_gym.gap import select
    from rwm_gym.gap.fit import CandidateFit

    before, floor = np.ones((20, 3)), np.full((20, 3), 1.0 / floor_ratio)
    above = floor_ratio >= 2.0

    def test_floor(gap, floor, held, block_rows, config):
        return {
            "gap": float(gap.mean()),
            "floor": float(floor.mean()),
            "ratio": floor_ratio,
            "p_value": 0.3,
            "above_floor": above and gap.mean() > 0.9,
        }

    def fits(effects, *args):
        out = []
        for i, name in enumerate(effects):
            fit = CandidateFit(
                name,
                [name],
                ["1"],
                [1.0],
                [0.1],
                0.0,
                gap_mean=1.0 - (explained if i == 0 else 0.0),
                p_value=p_value if i == 0 else 1.0,
            )
            fit.explained_fraction = fit.score = 1.0 - fit.gap_mean
            out.append(fit)
        return out

    _patch(monkeypatch, "compare_with_floor", test_floor)
    _patch(monkeypatch, "fit_all", fits)
    _patch(monkeypatch, "scope_candidates", lambda *args: [])
    _patch(monkeypatch, "every_scope", lambda *args: [])
    _patch(monkeypatch, "gap_per_window", lambda spec, sim, held: np.full((20, 3), 1.0 - explained))
    resim = SimpleNamespace(spec=SPEC, rollout=lambda held, params: None)
    effects = {n: EFFECTS[n] for n in ("backlash", "joint_friction", "armature", "payload")}
    config = FitConfig(near_the_floor_after_naming=False)  # step 1 is tested here
    selection = select.select_effects(
        effects, SPEC, resim, None, None, PhysicsParams(), before, floor, config, progress=False
    )
    assert selection.verdict == ("backlash" if named else "none" if not above else "unexplained"), selection.reason
    if not above:
        assert "Bonferroni" in selection.reason and "p < 0.0025" in selection.reason


def _patch(monkeypatch, name: str, value) -> None:
    """Stub `name` in every module of the selection that looks it up (the final choice, the search, a step, the
    judge, the cross-fitting, the refits, pairs and sets)."""
    from rwm_gym.gap import cross_fit, judge, pairs, refit, search, select, sets, step

    for module in (cross_fit, judge, pairs, refit, search, select, sets, step):
        if hasattr(module, name):
            monkeypatch.setattr(module, name, value)


def _fit_of(name: str, gap: float, gap_mean: float, p_value: float):
    """A fitted candidate (every parameter at 0.7) that takes a held-out gap of mean `gap` to `gap_mean`."""
    from rwm_gym.gap.fit import CandidateFit

    size = len(EFFECTS[name].parameters)
    fit = CandidateFit(name, [name] * size, ["1"] * size, [0.7] * size, [0.1] * size, 0.0, gap_mean=gap_mean)
    fit.p_value = p_value
    fit.explained_fraction = fit.score = 1.0 - gap_mean / gap
    return fit


def _stub_selection(monkeypatch, fits, above, gap_of, cross_p: float) -> list[str]:
    """Selection's fits, floor test, re-simulated gaps and cross-fitted test stubbed: `fits(name, gap)` gives each
    effect's (gap_mean, p_value) on top of a simulator of held-out gap `gap`, `above(gap, windows)` the floor test's
    verdict,
    `gap_of(params)` a simulator's held-out gap; returns the effects the cross-fitted test is asked about."""

    def fit_all(effects, inputs, *args, **kwargs):
        gap = float(inputs.before.mean())
        return [_fit_of(name, gap, *fits(name, gap)) for name in effects]

    tested = []
    _patch(
        monkeypatch,
        "compare_with_floor",
        lambda gap, floor, windows, *args: {
            "gap": float(gap.mean()),
            "floor": float(floor.mean()),
            "ratio": float(gap.mean() / floor.mean()),
            "p_value": 0.02,
            "above_floor": above(float(gap.mean()), windows),
        },
    )
    _patch(monkeypatch, "fit_all", fit_all)
    _patch(monkeypatch, "scope_candidates", lambda *args, **kwargs: [])
    _patch(monkeypatch, "every_scope", lambda *args, **kwargs: [])
    _patch(monkeypatch, "gap_per_window", lambda spec, params, held: np.full((20, 3), gap_of(params)))
    _patch(
        monkeypatch,
        "joint_refit",
        lambda named, resim, train, held, base, current, config: (named, base, current, None),
    )
    _patch(monkeypatch, "cross_fitted_p_value", lambda candidate, *args: tested.append(candidate[1].effect) or cross_p)
    return tested


EFFECTS_OF_STUBS = ("torque_limit", "joint_friction", "armature", "payload")


def _select(floor: float, config: FitConfig, names=EFFECTS_OF_STUBS, held=None, **kwargs):
    """`select_effects` over `names` from a nominal held-out gap of 1 and a noise floor `floor`, resimulation
    stubbed (`_stub_selection`)."""
    from rwm_gym.gap import select

    effects = {n: EFFECTS[n] for n in names}
    resim = SimpleNamespace(spec=SPEC, rollout=lambda held, params: params)
    return select.select_effects(
        effects,
        SPEC,
        resim,
        None,
        held,
        PhysicsParams(),
        np.ones((20, 3)),
        np.full((20, 3), floor),
        config,
        progress=False,
        **kwargs,
    )


@pytest.mark.parametrize(
    "cross_p,with_cross,named,best_gap",
    [
        (1e-4, True, True, 0.75),  # fails on the held-out third alone (p=5e-3 > 0.0025), passes on every episode
        (5e-3, True, False, 0.75),  # the cross-fitted test is not stronger: none
        (1e-4, False, False, 0.75),  # no swapped windows: the held-out test alone decides
        (1e-4, True, False, 1.0),  # the best explains nothing (a nominal case): no second test, nothing built for it
    ],
)
def test_near_the_floor_the_best_candidate_is_tested_again_cross_fitted(
    monkeypatch, cross_p, with_cross, named, best_gap
):
    """A 0.5x torque limit removes most of a gap near the floor, but three held-out episodes hold too few blocks for
    p < 0.01 over the step's candidates. The best candidate is then tested on every episode (2-fold cross-fitting),
    and named if that test passes at the same Bonferroni level; the reason says which test decided."""

    def fits(name, gap):
        return (best_gap, 5e-3) if name == "torque_limit" else (1.0, 1.0)

    tested = _stub_selection(monkeypatch, fits, lambda gap, windows: False, lambda params: 0.75, cross_p)
    built = []
    cross = (lambda: built.append(1) or CrossFit(None, None)) if with_cross else None
    selection = _select(0.8, FitConfig(near_the_floor_after_naming=False), cross=cross)  # step 1 is tested here
    needed = with_cross and best_gap < 1.0
    assert tested == (["torque_limit"] if needed else [])
    assert built == ([1] if needed else [])  # the swapped windows are built once, and only when the test needs them
    assert selection.verdict == ("torque_limit" if named else "none"), selection.reason
    assert ("cross-fitted p=" in selection.reason) == needed


@pytest.mark.parametrize(
    "after_naming,own_floor,above_on_every_episode",
    [(True, 0.3, True), (False, 0.3, True), (True, 0.1, True), (True, 0.3, False)],
)
def test_a_later_step_near_its_floor_tests_the_candidates_cross_fitted(
    monkeypatch, after_naming, own_floor, above_on_every_episode
):
    """A triple's third effect in 9 walking episodes: after two named, the rest was 3x its floor, but the held-out
    third gave p = 0.017 and selection stopped. A step after the first near its floor tests its gap again on every
    episode; above the floor there, it is judged as step 1 is near the floor: each candidate's own test over the
    step's candidates, the best cross-fitted on every episode. A pick that lowers the gap only by lowering its
    simulator's floor (a contact solver after friction and a payload) is not named."""

    def fits(name, gap):
        return {"torque_limit": (0.5, 1e-5), "joint_friction": (0.7 * gap, 5e-3)}.get(name, (gap, 1.0))

    def gap_of(params):
        return 0.35 if params.joint_friction else 0.5 if params.torque_limit else 1.0

    def above(gap, windows):
        return gap > 0.9 or (windows == "every episode" and above_on_every_episode)

    tested = _stub_selection(monkeypatch, fits, above, gap_of, 1e-5)
    selection = _select(
        0.3,
        FitConfig(joint_candidates=0, near_the_floor_after_naming=after_naming, drop_idle=False),  # stubbed rollouts
        held=SimpleNamespace(join=lambda other: "every episode"),
        cross=lambda: CrossFit(None, None),
        floor_of=lambda params, windows=None: np.full((20, 3), own_floor if params.joint_friction else 0.3),
    )
    named = [e.name for e, _ in selection.named]
    if not above_on_every_episode:  # the rest is not above the floor on every episode either: nothing is fitted
        assert named == ["torque_limit"] and tested == [] and "; on every episode: gap 0.5 is not" in selection.reason
    elif own_floor < 0.3:  # 0.35 left, 0.25 above its own floor: more than the 0.2 the step's gap had above its floor
        assert named == ["torque_limit"] and tested == ["joint_friction"]
        assert "against its own noise floor 0.1" in selection.steps[1]["decision"]
    elif after_naming:  # 0.15 of the 0.2 above the floor; p = 5e-3 on the held-out third, 1e-5 on every episode
        assert named == ["torque_limit", "joint_friction"] and tested == ["joint_friction"]
        assert "Bonferroni" in selection.steps[1]["decision"] and "cross-fitted p=" in selection.steps[1]["decision"]
    else:
        assert named == ["torque_limit"] and tested == []


@pytest.mark.parametrize("cross_p,verdict", [(1e-4, "torque_limit"), (0.05, "unexplained")])
def test_step_1_cross_fits_its_best_before_calling_a_gap_unexplained(monkeypatch, cross_p, verdict):
    """A torque limit 2x on walking data explained 89 % of a gap 300x the floor, but at p = 0.034 on the held-out
    third (a few windows carry it), and the gap was called `unexplained`. Before that, the best candidate is tested
    again on every episode, cross-fitted; one that explains too little is not."""

    def fits(name, gap):
        return (0.11, 0.034) if name == "torque_limit" else (1.0, 1.0)

    tested = _stub_selection(monkeypatch, fits, lambda gap, windows: gap > 0.9, lambda params: 0.11, cross_p)
    config = FitConfig(near_the_floor_after_naming=False)
    selection = _select(1.0 / 300, config, cross=lambda: CrossFit(None, None))
    assert selection.verdict == verdict and tested == ["torque_limit"], selection.reason
    assert "cross-fitted p=" in selection.steps[0]["decision"]


def test_cross_fitting_scores_every_episode_with_a_fit_that_did_not_see_it(monkeypatch):
    """The swapped fit is made on the held-out episodes' windows and scored on the fitting episodes' ones; the test
    pools both, so it runs on the blocks of every episode."""
    from rwm_gym.gap.fit import CandidateFit
    from rwm_gym.gap.resim import Windows

    def windows(episodes, rows=4):
        w = len(episodes) * rows
        return Windows(
            np.repeat(episodes, rows),
            np.tile(np.arange(rows) * 25, len(episodes)),
            np.zeros((w, 3, 2)),
            np.zeros((w, 3, 2)),
            np.zeros((w, 27, 12)),
            np.zeros((w, 5)),
            np.zeros((w, 25, 5)),
            np.zeros((w, 4)),
            horizon=25,
            warmup=2,
        )

    held, fit_here, score_here = windows([7, 8]), windows([7, 8]), windows([0, 1, 2, 3])
    fitted_on, seen = [], {}
    effect = EFFECTS["torque_limit"]

    def fake_fit(effect, resim, train, base, config, start, bracket):
        fitted_on.append(train)
        return CandidateFit(effect.name, ["t"], ["N·m"], [50.0], [1.0], 0.0)

    def fake_p(larger, smaller, both, block_rows, significance):
        seen.update(larger=larger, smaller=smaller, episodes=set(both.episode.tolist()))
        return 1e-5

    rollout_of = {id(held): 1.0, id(score_here): 2.0}
    _patch(monkeypatch, "fit_effect", fake_fit)
    _patch(monkeypatch, "paired_p_value", fake_p)
    _patch(monkeypatch, "gap_per_window", lambda spec, sim, w: np.full((len(w), 3), sim))
    resim = SimpleNamespace(
        spec=SPEC, rollout=lambda w, params: rollout_of[id(w)] * (0.5 if params.torque_limit is not None else 1.0)
    )
    candidate = (effect, CandidateFit("torque_limit", ["t"], ["N·m"], [56.0], [1.0], 0.0))
    p = cross_fitted_p_value(
        candidate,
        resim,
        held,
        CrossFit(fit_here, score_here),
        PhysicsParams(),
        np.ones((len(held), 3)),
        FitConfig(),
        0.001,
    )
    assert p == 1e-5 and fitted_on == [fit_here]
    assert seen["episodes"] == {0, 1, 2, 3, 7, 8}
    np.testing.assert_allclose(seen["larger"], [1.0] * 8 + [2.0] * 16)  # nominal: held, then the fitting episodes
    np.testing.assert_allclose(seen["smaller"], [0.5] * 8 + [1.0] * 16)  # with the effect at each direction's fit


def test_every_joint_effect_is_scoped_before_a_gap_is_called_unexplained(monkeypatch):
    """Armature in the hip flexion joints alone: no global form explains anything, so none was scoped and the gap was
    `unexplained`. Before saying so, step 1 fits every joint effect in its scopes; a gap near the floor (nothing to
    explain yet) and later steps do not pay for it."""
    from rwm_gym.gap import scope, select
    from rwm_gym.gap.fit import CandidateFit

    def fitted(name, explained, status="ok", scope_name="global", p_value=1.0):
        return CandidateFit(
            name,
            [name],
            ["1"],
            [0.0],
            [0.1],
            0.0,
            gap_mean=1.0 - explained,
            explained_fraction=explained,
            score=explained,
            p_value=p_value,
            status=status,
            scope=scope_name,
        )

    tried = []
    monkeypatch.setattr(scope, "_scoped_fits", lambda best, effect, *args: tried.append(effect.name) or [])
    fits = [
        fitted("payload", 0.0),
        fitted("joint_damping", 0.0),
        fitted("armature", -0.1),
        fitted("backlash", 0.0, status="rejected: blew up"),
        fitted("joint_friction", 0.2),
    ]
    no_sim = SimpleNamespace(spec=SPEC)  # nothing is simulated: the fits are stubbed
    scope.every_scope(
        fits, {"joint_friction"}, EFFECTS, FitInputs(no_sim, None, None, PhysicsParams(), None, FitConfig())
    )
    assert tried == ["joint_damping", "armature"]

    above = [True]
    calls = []

    def every(fits, scoped, *args):
        calls.append(sorted(scoped))
        return [
            (
                scope.scoped(EFFECTS["armature"], SPEC, "joint_type"),
                fitted("armature", 0.5, scope_name="joint_type", p_value=1e-4),
            )
        ]

    _patch(
        monkeypatch,
        "compare_with_floor",
        lambda gap, *args: {
            "gap": float(gap.mean()),
            "floor": 0.2,
            "ratio": 5.0,
            "p_value": 1e-4 if above[0] else 0.3,
            "above_floor": above[0] and gap.mean() > 0.9,
        },
    )
    _patch(monkeypatch, "fit_all", lambda effects, *args: [fitted(n, 0.0) for n in effects])
    _patch(monkeypatch, "scope_candidates", lambda *args: [])
    _patch(monkeypatch, "every_scope", every)
    _patch(
        monkeypatch,
        "joint_refit",
        lambda named, resim, train, held, base, current, config: (named, base, current, None),
    )
    _patch(monkeypatch, "gap_per_window", lambda spec, sim, held: np.full((20, 3), 0.5))
    resim = SimpleNamespace(spec=SPEC, rollout=lambda held, params: None)
    effects = {n: EFFECTS[n] for n in ("armature", "joint_damping", "payload")}

    def run(config=FitConfig(near_the_floor_after_naming=False)):  # step 1 is tested here
        return select.select_effects(
            effects,
            SPEC,
            resim,
            None,
            None,
            PhysicsParams(),
            np.ones((20, 3)),
            np.full((20, 3), 0.2),
            config,
            progress=False,
        )

    selection = run()
    assert (selection.verdict, selection.named[0][1].scope) == ("armature", "joint_type")
    assert calls == [[]]  # once, at step 1
    assert run(FitConfig(every_scope=False, near_the_floor_after_naming=False)).verdict == "unexplained"
    assert len(calls) == 1
    above[0] = False
    assert run().verdict == "none" and len(calls) == 1
    # a single-joint form (one value, scope "joint") among the step's candidates leaves its effect's groups unfitted
    above[0] = True
    single = fitted("armature", 0.0, scope_name="joint")
    _patch(monkeypatch, "scope_candidates", lambda *args: [(EFFECTS["armature"], single)])
    assert run().verdict == "armature" and calls[-1] == []


def test_every_effect_is_refined_before_a_gap_is_called_unexplained(monkeypatch):
    """Motor strength 0.8 and ground friction 0.3 on walking data: ground friction ranked below the 3 refined effects
    on the coarse grid and stayed at 0.67, explaining 11 %. Before calling the gap `unexplained`, step 1 refines every
    effect; a step that names something without it does not pay for it."""
    from rwm_gym.gap import select
    from rwm_gym.gap.fit import CandidateFit

    def fitted(name, explained, p_value=1.0):
        return CandidateFit(
            name,
            [name],
            ["1"],
            [0.0],
            [0.1],
            0.0,
            gap_mean=1.0 - explained,
            explained_fraction=explained,
            score=explained,
            p_value=p_value,
        )

    refine_calls = []

    def fit_all(effects, inputs, progress=True, refine_top=None):
        refine_calls.append(refine_top)
        if refine_top is None:  # the usual step: the ground friction fit is a coarse grid point
            return [fitted("motor_strength", 0.15, 0.1), fitted("ground_friction", 0.1 * len(effects) / 4)]
        return [fitted("motor_strength", 0.15, 0.1), fitted("ground_friction", 0.6, 1e-4)]

    _patch(
        monkeypatch,
        "compare_with_floor",
        lambda gap, *args: {
            "gap": float(gap.mean()),
            "floor": 0.01,
            "ratio": 50.0,
            "p_value": 1e-4,
            "above_floor": gap.mean() > 0.9,
        },
    )
    _patch(monkeypatch, "fit_all", fit_all)
    _patch(monkeypatch, "scope_candidates", lambda *args: [])
    _patch(monkeypatch, "every_scope", lambda *args: [])
    _patch(monkeypatch, "gap_per_window", lambda spec, sim, held: np.full((20, 3), 0.5))
    resim = SimpleNamespace(spec=SPEC, rollout=lambda held, params: None)
    effects = {n: EFFECTS[n] for n in ("motor_strength", "ground_friction", "payload", "armature")}

    def run(config=None):
        refine_calls.clear()
        return select.select_effects(
            effects,
            SPEC,
            resim,
            None,
            None,
            PhysicsParams(),
            np.ones((20, 3)),
            np.full((20, 3), 0.01),
            dataclasses.replace(config or FitConfig(), near_the_floor_after_naming=False),  # step 1 is tested here
            progress=False,
        )

    selection = run()
    assert selection.verdict == "ground_friction" and refine_calls == [None, 4]
    assert run(FitConfig(refine_every_effect=False)).verdict == "unexplained" and refine_calls == [None]
    assert run(FitConfig(refine_top=4)).verdict == "unexplained" and refine_calls == [None]  # all were refined


def test_a_lone_named_effect_of_several_parameters_is_refitted(monkeypatch):
    """Armature in the hip flexion joints on walking data: fitted one joint type at a time, it kept 0.006 kg·m² in the
    other two and explained 51 % of the gap (67 % at the true values). A lone named effect of several parameters gets
    the joint refit that a set of named effects gets; one of a single parameter does not need it."""
    from rwm_gym.gap import select
    from rwm_gym.gap.fit import CandidateFit
    from rwm_gym.gap.scope import scoped

    per_type = scoped(EFFECTS["armature"], SPEC, "joint_type")

    def fitted(name, explained, values, scope_name="global"):
        return CandidateFit(
            name,
            [name] * len(values),
            ["kg·m²"] * len(values),
            values,
            [0.1] * len(values),
            0.0,
            gap_mean=1.0 - explained,
            explained_fraction=explained,
            score=explained,
            p_value=1e-4,
            scope=scope_name,
        )

    refits = []
    _patch(
        monkeypatch,
        "compare_with_floor",
        lambda gap, *args: {
            "gap": float(gap.mean()),
            "floor": 0.01,
            "ratio": 50.0,
            "p_value": 1e-4,
            "above_floor": gap.mean() > 0.9,
        },
    )
    _patch(monkeypatch, "fit_all", lambda effects, *args: [fitted(n, 0.0, [0.0]) for n in effects])
    _patch(
        monkeypatch,
        "joint_refit",
        lambda named, resim, train, held, base, current, config: (
            refits.append([e.name for e, _ in named]) or (named, base, current, {"kept": True})
        ),
    )
    _patch(monkeypatch, "gap_per_window", lambda spec, sim, held: np.full((20, 3), 0.5))
    resim = SimpleNamespace(spec=SPEC, rollout=lambda held, params: None)
    effects = {n: EFFECTS[n] for n in ("armature", "joint_damping")}

    def run(candidate, config):
        refits.clear()
        _patch(monkeypatch, "scope_candidates", lambda *args: [candidate])
        return select.select_effects(
            effects,
            SPEC,
            resim,
            None,
            None,
            PhysicsParams(),
            np.ones((20, 3)),
            np.full((20, 3), 0.01),
            dataclasses.replace(config, near_the_floor_after_naming=False),  # one effect is named
            progress=False,
        )

    lone = (per_type, fitted("armature", 0.5, [0.006, 0.083, 0.006], "joint_type"))
    assert run(lone, FitConfig()).joint_refit == {"kept": True} and refits == [["armature"]]
    assert run(lone, FitConfig(refit_single_effect=False)).joint_refit is None and refits == []
    one_parameter = (EFFECTS["joint_damping"], fitted("joint_damping", 0.5, [1.0]))
    assert run(one_parameter, FitConfig()).verdict == "joint_damping" and refits == []


@pytest.mark.parametrize(
    "floor,best_explains,rival_explains,ambiguous",
    [
        (0.43, 0.18, 0.0, False),  # ground friction at half its default on walking data: a gap 2.3x the floor
        (0.02, 0.50, 0.45, True),  # far above the floor: half the gap and 45 % of it are alike
        (0.43, 0.18, 0.15, True),  # ... and near it, 18 % and 15 %
    ],
)
def test_rivals_are_alike_in_the_gap_they_leave_above_the_floor(floor, best_explains, rival_explains, ambiguous):
    """A candidate that explains nothing is no rival of one that removes a third of what lies above the floor, however
    close the floor is: the remaining gaps are compared above it."""
    from rwm_gym.gap.fit import CandidateFit
    from rwm_gym.gap.judge import name_step

    def fitted(name, explained, p_value):
        fit = CandidateFit(
            name,
            [name],
            ["1"],
            [0.0],
            [0.1],
            0.0,
            gap_mean=1.0 - explained,
            explained_fraction=explained,
            score=explained,
            p_value=p_value,
        )
        fit.excess_explained = explained / (1.0 - floor)
        return (EFFECTS[name], fit)

    candidates = [fitted("ground_friction", best_explains, 4e-4), fitted("action_delay", rival_explains, 0.5)]
    pick, reason, rival = name_step(candidates, FitConfig(), 0.01, 1.0, floor)
    assert (pick is None) == ambiguous and (rival is not None) == ambiguous, reason
    assert ("ambiguous" in reason) == ambiguous


def test_a_candidate_that_explains_nothing_is_no_rival_of_a_penalised_one():
    """A base-velocity bias (three parameters) on walking data explained 20 % of a gap 1.75x the floor (47 % of what
    lies above it); charged for its two extra parameters, its penalised remaining gap came within 25 % of that of an
    action delay that explained nothing, and the gap was called `unexplained`. A rival must explain something."""
    from rwm_gym.gap.fit import CandidateFit
    from rwm_gym.gap.judge import judge

    def fitted(name, explained, parameters, p_value):
        score = 1.0 - (1.0 - explained) * (1.0 + FitConfig().penalty_per_parameter * (parameters - 1))
        return (
            EFFECTS[name],
            CandidateFit(
                name,
                [name],
                ["1"],
                [0.0] * parameters,
                [0.1] * parameters,
                0.0,
                gap_mean=1.0 - explained,
                explained_fraction=explained,
                score=score,
                p_value=p_value,
            ),
        )

    gap, floor = 1.0, 1.0 / 1.75
    bias, delay = fitted("base_velocity_bias", 0.2, 3, 1e-4), fitted("action_delay", 0.0, 1, 1.0)
    pick, reason, rival = judge([bias, delay], gap, floor, FitConfig(), 0.01)
    assert pick is bias and rival is None, reason
    pick, reason, rival = judge([bias, delay], gap, floor, FitConfig(rival_excess_explained=0.0), 0.01)
    assert pick is None and rival[1] is delay[1] and "ambiguous" in reason  # the rule it replaces


@pytest.mark.parametrize("to_beat,fitted_scopes", [(-1.0, ["leg", "joint_type"]), (0.87, ["joint_type"]), (0.95, [])])
def test_a_scope_that_cannot_beat_the_best_candidate_is_not_fitted(monkeypatch, to_beat, fitted_scopes):
    """A scoped form scores at most 1 less its charge (per leg 4 values: 0.85, per joint type 3: 0.90) even if it left
    no gap at all; where the step's best candidate already scores more, fitting it could never change the verdict."""
    from rwm_gym.gap import scope
    from rwm_gym.gap.fit import CandidateFit

    fitted = []

    def fake_fit(form, *args, **kwargs):
        fitted.append(form.scope)
        return CandidateFit(form.name, [], [], [0.0] * len(form.parameters), [], 0.0, scope=form.scope)

    def fake_score(fit, *args):
        fit.score = 0.5

    monkeypatch.setattr(scope, "fit_coordinatewise", fake_fit)
    monkeypatch.setattr(scope, "score_fit", fake_score)
    best = CandidateFit("joint_friction", ["f"], ["N m"], [1.0], [0.1], 0.0, score=0.6)
    inputs = FitInputs(SimpleNamespace(spec=SPEC), [], None, PhysicsParams(), None, FitConfig())
    out = scope._scoped_fits(best, EFFECTS["joint_friction"], inputs, to_beat)
    assert fitted == fitted_scopes and [f.scope for _, f in out] == fitted_scopes


def test_learned_torque_is_the_groups_linear_law_and_round_trips(tmp_path):
    """Each joint gets its group's weights on (deflection, position error, velocity, 1); the file keeps them and
    refuses another robot's joints or another format with a one-line error."""
    names, membership = group_matrix(SPEC, "joint_type")
    assert names == ["HAA", "HFE", "KFE"] and membership.sum(0).tolist() == [4.0, 4.0, 4.0]
    weights = np.zeros((3, 4))
    weights[1] = [-20.0, 0.0, -1.5, 2.0]  # HFE: a spring, a damper and an offset
    default = np.asarray(SPEC.actuator.default_pose)
    correction = LinearResidualTorque(weights, membership, default, names)
    rng = np.random.default_rng(0)
    q, qd = default + rng.normal(0, 0.2, (5, 12)), rng.normal(0, 1.0, (5, 12))
    torque = correction.torque(q, qd, default)
    hfe = membership[:, 1] > 0
    np.testing.assert_allclose(torque[:, hfe], -20.0 * (q - default)[:, hfe] - 1.5 * qd[:, hfe] + 2.0)
    assert not torque[:, ~hfe].any()
    save_correction(correction, tmp_path / "c.safetensors", LearnedCorrectionConfig(), SPEC)
    loaded = load_correction(tmp_path / "c.safetensors", SPEC)
    np.testing.assert_array_equal(loaded.torque(q, qd, default), torque)
    assert loaded.groups == names
    other = dataclasses.replace(
        SPEC, actuator=dataclasses.replace(SPEC.actuator, joints=tuple(reversed(SPEC.actuator.joints)))
    )
    with pytest.raises(ValueError, match="joints differ"):
        load_correction(tmp_path / "c.safetensors", other)
    from safetensors.numpy import save_file

    save_file({"weights": weights}, str(tmp_path / "w.safetensors"))
    with pytest.raises(ValueError, match="not a learned correction"):
        load_correction(tmp_path / "w.safetensors", SPEC)


@pytest.mark.parametrize("delay_on_armature, named", [(0.40, True), (0.47, False)])
def test_a_rival_that_the_best_holds_is_resolved_for_the_best(monkeypatch, delay_on_armature, named):
    """An action delay and armature explain a step's gap alike (they mimic each other). Armature refitted on top of
    the delay explains little more; if the delay on top of armature still explains a third of the rest above the
    floor, the delay holds all armature explains and is named; if it too explains little, the two are confusable."""
    from rwm_gym.gap.fit import CandidateFit

    def gap_of(params):  # a stand-in simulator: each effect's held-out gap, from 1.0 with neither
        delay, armature = params.action_delay > 0, params.armature > 0
        return {(False, False): 1.0, (True, False): 0.40, (False, True): 0.50, (True, True): None}[delay, armature]

    def score(fit, effect, resim, held, on_top, after, config):
        both = {"armature": 0.38, "action_delay": delay_on_armature}[effect.name]  # refitted on top of the other
        fit.gap_mean, fit.p_value, fit.status = both, 1e-4 if float(after.mean()) - both > 0.05 else 0.3, "ok"

    _patch(monkeypatch, "fit_effect", lambda effect, resim, train, base, config, start, bracket: fitted(effect))
    _patch(monkeypatch, "score_fit", score)
    _patch(monkeypatch, "gap_per_window", lambda spec, params, held: np.full((10, 3), gap_of(params)))
    resim = SimpleNamespace(spec=SPEC, rollout=lambda held, params: params)

    def fitted(effect):
        return CandidateFit(effect.name, [effect.name], ["1"], [effect.parameters[0].default], [0.1], 0.0)

    delay, armature = EFFECTS["action_delay"], EFFECTS["armature"]
    best, rival = (delay, fitted(delay)), (armature, fitted(armature))
    floor = np.full((10, 3), 0.2)
    out = resolve_rivals(best, rival, resim, None, None, PhysicsParams(), None, floor, FitConfig())
    assert (out is not None) == named
    if named:
        assert out[0] is best and "action_delay is named" in out[1]

    # where the held-out third alone is not significant, the test runs again on every episode (cross-fitted)
    _patch(monkeypatch, "cross_fitted_p_value", lambda candidate, *args: 1e-3)
    weak = {"armature": 0.38, "action_delay": delay_on_armature}  # as above, but every held-out p 0.3

    def score_weakly(fit, effect, resim, held, on_top, after, config):
        fit.gap_mean, fit.p_value, fit.status = weak[effect.name], 0.3, "ok"

    _patch(monkeypatch, "score_fit", score_weakly)
    no_cross = resolve_rivals(best, rival, resim, None, None, PhysicsParams(), None, floor, FitConfig())
    crossed = resolve_rivals(
        best, rival, resim, None, None, PhysicsParams(), None, floor, FitConfig(), cross=lambda: "swapped windows"
    )
    assert no_cross is None and (crossed is not None) == named


@pytest.mark.parametrize(
    "payload_on_armature,look_ahead,named",
    [(0.15, True, ["armature", "payload"]), (0.47, True, []), (0.15, False, [])],
)
def test_rivals_that_stay_alike_are_told_apart_by_where_each_leads(monkeypatch, payload_on_armature, look_ahead, named):
    """Joint friction and armature explain step 1's gap alike, and neither holds the other. Followed to its end, naming
    armature lets the payload explain most of the rest, naming friction leaves the gap where it was: the armature
    branch is taken, as it leaves clearly less above the floor. Where both branches end alike (or selection does not
    look ahead), nothing is named and the gap is `unexplained`."""

    nominal = PhysicsParams()
    gaps = {  # each simulator's held-out gap, by the effects in it
        frozenset(): 1.0,
        frozenset({"joint_friction"}): 0.5,
        frozenset({"armature"}): 0.52,
        frozenset({"armature", "payload_mass", "payload_com"}): payload_on_armature,
    }

    def gap_of(params):
        fields = dataclasses.fields(params)
        return gaps[frozenset(f.name for f in fields if getattr(params, f.name) != getattr(nominal, f.name))]

    def fits(name, gap):  # on top of a simulator of held-out gap `gap`: each effect's gap and p
        explains = {1.0: {"joint_friction": 0.5, "armature": 0.52}, 0.52: {"payload": payload_on_armature}}
        explained = explains.get(round(gap, 3), {}).get(name)
        return (gap, 0.5) if explained is None else (explained, 1e-4)

    _stub_selection(monkeypatch, fits, lambda gap, windows: gap > 0.3, gap_of, 1.0)
    _patch(monkeypatch, "resolve_rivals", lambda *args, **kwargs: None)  # neither holds the other
    _patch(monkeypatch, "joint_candidates", lambda candidates, *args: candidates)
    _patch(  # worse windows wherever the gap is larger
        monkeypatch, "paired_p_value", lambda larger, smaller, *args: 1e-4 if larger.mean() > smaller.mean() else 0.5
    )
    selection = _select(
        0.1, FitConfig(look_ahead=look_ahead, drop_idle=False, pair_candidates=0)
    )  # gaps stubbed per named set
    assert [e.name for e, _ in selection.named] == named, selection.reason
    assert selection.verdict == (named[0] if named else "unexplained")
    first = selection.steps[0]
    assert first["decision"].startswith("ambiguous: joint_friction (50%) and armature (48%) explain the gap alike")
    if not look_ahead:
        assert "look_ahead" not in first
        return
    branches = first["look_ahead"]["branches"]
    assert [b["named"] for b in branches] == [
        ["joint_friction (global)"],
        ["armature (global)", "payload (global)"] if named else ["armature (global)"],
    ]
    assert first["look_ahead"]["taken"] == (1 if named else None)
    assert ("armature is named" if named else "still alike") in first["decision"]
    if named:  # the taken branch's steps follow: step 2 named the payload
        assert first["named"] == "armature (global)" and selection.steps[1]["named"] == "payload (global)"
    else:
        assert first["named"] is None and "still alike" in selection.reason


@pytest.mark.parametrize("own_floor,named", [(True, ["joint_damping", "armature"]), (False, ["joint_damping"])])
def test_later_steps_test_the_gap_against_the_floor_of_the_simulator_so_far(monkeypatch, own_floor, named):
    """Armature + damping + ground compliance on excitation data: the damped robot carries start noise a quarter as far
    as the nominal one, so after damping and compliance the 0.0029 left looked under the nominal floor (0.0049, ratio
    0.6) while it stood 2.5x above the corrected simulator's own (0.0012), and armature was never fitted. Step 2 tests
    the gap of the simulator with the named effects against that simulator's floor; from two named effects on, that
    simulator has them refitted together."""
    from rwm_gym.gap import select
    from rwm_gym.gap.fit import CandidateFit

    level = [1.0]  # the held-out gap of the simulator with the effects named so far
    explains = {"joint_damping": 0.5, "armature": 0.5}

    def fits(effects, *args):
        first = next(iter(effects), None)
        out = []
        for name in effects:
            share = explains[name] if name == first else 0.0
            gap_mean = level[0] * (1.0 - share)
            out.append(CandidateFit(name, [name], ["1"], [1.0], [0.1], 0.0, gap_mean=gap_mean, p_value=1e-4))
            out[-1].explained_fraction = out[-1].score = share
        return out

    def name(search, pick, named, params):
        named.append(pick)
        level[0] *= 1.0 - explains[pick[0].name]
        return params.replace(joint_damping=float(len(named))), np.full((20, 3), level[0])

    _patch(
        monkeypatch,
        "compare_with_floor",
        lambda gap, floor, *args: {
            "gap": float(gap.mean()),
            "floor": float(floor.mean()),
            "ratio": float(gap.mean() / floor.mean()),
            "p_value": 1e-4,
            "above_floor": gap.mean() > 1.2 * floor.mean(),
        },
    )
    _patch(monkeypatch, "fit_all", fits)
    _patch(monkeypatch, "scope_candidates", lambda *args: [])
    _patch(monkeypatch, "every_scope", lambda *args: [])
    _patch(monkeypatch, "joint_candidates", lambda candidates, *args: candidates)
    _patch(monkeypatch, "_name", name)
    refits = []

    def joint_refit(named, resim, train, held, base, current, config):
        refits.append(len(named))
        return named, base.replace(joint_damping=float(len(named))), current, None

    _patch(monkeypatch, "joint_refit", joint_refit)
    _patch(monkeypatch, "effect_shares", lambda *args: {})
    asked = []

    def floor_of(params):  # the damped simulator's floor is a third of the nominal one
        asked.append(params.joint_damping)
        return np.full((20, 3), 0.15)

    selection = select.select_effects(
        {n: EFFECTS[n] for n in explains},
        SPEC,
        SimpleNamespace(spec=SPEC, rollout=lambda held, params: None),
        None,
        None,
        PhysicsParams(),
        np.ones((20, 3)),
        np.full((20, 3), 0.45),  # 0.5 left after damping: under 1.2x the nominal floor
        FitConfig(near_the_floor_after_naming=False, drop_idle=False),  # the floor test alone decides step 2
        progress=False,
        floor_of=floor_of if own_floor else None,
    )
    assert [e.name for e, _ in selection.named] == named, selection.reason
    assert asked == ([1.0, 2.0] if own_floor else [])  # each later step asks the floor of its own simulator
    assert refits == ([2] if own_floor else [])  # two named effects are refitted together before step 3
    if own_floor:
        assert selection.steps[1]["floor_test"]["floor"] == pytest.approx(0.15)
    else:  # a lone effect's reason also says why step 2 stopped
        assert selection.reason.startswith("explains 91%") and "; then: held-out gap 0.5 is not" in selection.reason


@pytest.mark.parametrize(
    "p_value,costs,named",
    [
        (0.4, (0.30, 0.34), "motor_strength"),  # held-out gaps alike
        (1e-4, (0.30, 0.29), "pd_gains"),  # the training costs are recorded; the held-out test decides
    ],
)
def test_a_named_effect_gives_way_to_a_simpler_one_it_holds_that_fits_alike(monkeypatch, p_value, costs, named):
    """Motor strength 0.8 + joint friction + encoder offsets on excitation data: PD gains (kp 0.77, kd 1.00) were
    named in place of the weaker motor, the extra parameter absorbing part of the friction. The simpler effect,
    fitted in its place and refitted with the others, is named where its held-out gap is not significantly larger;
    both sets' training costs (`costs`: named, simpler) are recorded beside."""
    from rwm_gym.gap import select
    from rwm_gym.gap.fit import CandidateFit

    def fitted(name, values):
        return CandidateFit(name, [name] * len(values), ["1"] * len(values), values, [0.1] * len(values), 0.0)

    refits = []

    def joint_refit(named, resim, train, held, base, current, config):
        refits.append([e.name for e, _ in named])
        return named, base.replace(motor_strength=0.8), np.full((20, 3), 0.21), None

    _patch(monkeypatch, "fit_all", lambda effects, *args, **kw: [fitted(n, [0.8]) for n in effects])
    _patch(monkeypatch, "joint_refit", joint_refit)
    _patch(monkeypatch, "gap_per_window", lambda spec, sim, held: np.full((20, 3), 0.3))
    _patch(monkeypatch, "paired_p_value", lambda larger, smaller, *args: p_value)
    _patch(monkeypatch, "training_cost", lambda search, params: costs[params.motor_strength == 0.8])
    effects = {n: EFFECTS[n] for n in ("encoder_offset", "pd_gains", "motor_strength")}
    search = Search(
        effects,
        SPEC,
        SimpleNamespace(spec=SPEC, rollout=lambda held, params: None),
        None,
        None,
        PhysicsParams(),
        np.full((20, 3), 0.1),
        FitConfig(),
        False,
        None,
    )
    found = [
        (EFFECTS["encoder_offset"], fitted("encoder_offset", [0.03])),
        (EFFECTS["pd_gains"], fitted("pd_gains", [0.8, 1.05])),
    ]
    result, params, gap, checks = select.prefer_simpler(found, search, PhysicsParams(), np.full((20, 3), 0.2))
    assert refits == [["encoder_offset", "motor_strength"]]  # fitted in place, beside the other named effect
    assert [e.name for e, _ in result] == ["encoder_offset", named]
    assert [(c["effect"], c["simpler"], c["named"]) for c in checks] == [("pd_gains", "motor_strength", named)]
    assert checks[0]["gap_simpler"] == pytest.approx(0.21) and checks[0]["gap"] == pytest.approx(0.2)
    assert (checks[0]["training_cost"], checks[0]["training_cost_simpler"]) == costs
    alike = named == "motor_strength"
    assert (params.motor_strength == 0.8) == alike and (gap.mean() == pytest.approx(0.21)) == alike


def test_the_floor_of_a_simulator_is_computed_once_for_the_step_and_the_residual_test(monkeypatch):
    """The residual test asks for the floor of the simulator the last selection step tested: it is not simulated
    again, nor after one more simulator's floor was asked (a pick checked against its own floor); a third one's is."""
    from rwm_gym.gap import workflow

    computed = []
    monkeypatch.setattr(
        workflow, "noise_floor", lambda resim, held, params, noise, config: computed.append(params) or np.ones((4, 3))
    )
    floor_of = workflow._floor_of(None, None, SensorNoise(), None)
    damped = PhysicsParams(joint_damping=1.0)
    stiff, slow = PhysicsParams(joint_damping=2.0), PhysicsParams(action_delay=0.02)
    for params in (damped, PhysicsParams(joint_damping=1.0), stiff, damped, slow, damped):
        floor_of(params)
    assert computed == [damped, stiff, slow, damped]  # the last two are kept


def test_the_training_cost_of_a_simulator_is_what_the_fits_minimise(tmp_path):
    """`select.training_cost` of the simulator with an effect at given values is that effect's fit cost there, and
    lower at the hidden truth (a weak motor) than at the nominal robot."""
    from rwm_gym.gap import select

    data = Dataset.load(make_measured({"motor_strength": [0.8]}, 2, tmp_path / "m.h5", max_steps=40, progress=False))
    config = FitConfig()
    train = make_windows(data, np.arange(2), config.fit_horizon, 8)
    resim = Resimulator(SPEC)
    search = Search(EFFECTS, SPEC, resim, train, None, PhysicsParams(), None, config, False, None)
    effect = EFFECTS["motor_strength"]
    fit = fit_effect(effect, resim, train, PhysicsParams(), config, np.array([0.8]), (0.75, 0.85))
    assert select.training_cost(search, effect.physics(np.array(fit.values))) == pytest.approx(fit.train_cost)
    assert select.training_cost(search, effect.physics(np.array([0.8]))) < select.training_cost(search, PhysicsParams())


@pytest.mark.parametrize("spread_check", [True, False])
def test_an_effect_named_by_its_spread_ends_selection_unrefitted(monkeypatch, spread_check):
    """Step 1 names nothing by least squares; where an effect's own noise spread covers the data (`gap.spread`), it
    is named, selection stops there, and its values stay as the spread search found them (a refit by least squares
    would take them back towards the nominal robot). Without the check the gap is `unexplained`."""

    _stub_selection(monkeypatch, lambda name, gap: (gap, 0.5), lambda gap, windows: True, lambda params: 1.0, 0.5)
    spread_fit = _fit_of("payload", 1.0, 1.4, 1e-4)  # a larger gap than the nominal one, and several parameters
    spread_fit.spread = {"effect": "payload", "named": True}
    asked = []

    def name_by_spread(effects, *args):
        asked.append(sorted(effects))
        record = {
            "own_floor_test": {"ratio": 0.8, "p_value": 0.9},
            "systematic_misfit": {"explained": 0.8},
            "likelihood": {"p_value": 1e-4},
        }
        spread_fit.spread.update(record)
        return (EFFECTS["payload"], spread_fit), [spread_fit.spread]

    def no_refit(*args, **kwargs):
        raise AssertionError("an effect named by its spread was refitted")

    _patch(monkeypatch, "name_by_spread", name_by_spread)
    _patch(monkeypatch, "joint_refit", no_refit)
    _patch(monkeypatch, "prefer_simpler", no_refit)
    floor_of = lambda params, windows=None: np.full((20, 3), 0.1)  # noqa: E731
    selection = _select(0.1, FitConfig(spread_check=spread_check), floor_of=floor_of)
    if not spread_check:
        assert selection.verdict == "unexplained" and not asked and "spread" not in selection.steps[0]
        return
    assert asked == [sorted(EFFECTS_OF_STUBS)]
    assert selection.verdict == "payload" and len(selection.steps) == 1
    assert selection.named[0][1].values == [0.7, 0.7, 0.7] and selection.shares == [1.0]
    assert "named by its spread" in selection.steps[0]["decision"]
    assert selection.steps[0]["spread"] == [spread_fit.spread]
    assert "its own noise floor" in selection.reason


@pytest.mark.parametrize(
    "gap_without_damping,p_value,dropped",
    [
        (1.0, 1.0, True),  # nothing changes without it: it was named for what the refit of the armature did
        (1.5, 0.05, False),  # half of what then lies above the floor: kept, though not significant alone
        (1.1, 1e-4, False),  # a small share, but significant
        (1.1, 0.05, True),  # a small share, not significant
    ],
)
def test_a_named_effect_that_adds_nothing_at_the_final_values_is_dropped(
    monkeypatch, gap_without_damping, p_value, dropped
):
    from rwm_gym.gap import select

    def gap(spec, params, held):  # the stubbed rollout hands the simulator through
        both = params.armature > 0 and params.joint_damping > 0
        return np.full((20, 3), 1.0 if both else gap_without_damping if params.armature > 0 else 3.0)

    _patch(monkeypatch, "gap_per_window", gap)
    _patch(monkeypatch, "paired_p_value", lambda without, with_all, *a: p_value if without[0] < 2 else 1e-6)
    named = [
        (EFFECTS["armature"], SimpleNamespace(values=[0.1])),
        (EFFECTS["joint_damping"], SimpleNamespace(values=[0.5])),
    ]
    params = EFFECTS["joint_damping"].physics([0.5], EFFECTS["armature"].physics([0.1], PhysicsParams()))
    search = SimpleNamespace(
        config=FitConfig(),
        base=PhysicsParams(),
        spec=SPEC,
        held=None,
        resim=SimpleNamespace(rollout=lambda held, p: p),
        floor_at=lambda k, p: np.full((20, 3), 0.5),
    )
    kept, params_after, gap_after, checks = select.drop_idle(named, search, params, np.ones((20, 3)))
    assert [e.name for e, _ in kept] == (["armature"] if dropped else ["armature", "joint_damping"])
    assert (params_after.joint_damping == 0) == dropped
    assert gap_after.mean() == pytest.approx(gap_without_damping if dropped else 1.0)
    assert checks[0]["effect"] == "joint_damping" and checks[0]["dropped"] == dropped
    assert checks[0]["share_above_floor"] == pytest.approx((gap_without_damping - 1.0) / (gap_without_damping - 0.5))
    assert len(checks) == (1 if dropped else 2) and not any(c["dropped"] for c in checks[1:])  # armature stays


def test_a_lone_one_parameter_effect_refitted_without_a_bracket_searches_its_range(tmp_path):
    """The joint refit and the solver check refit the named effects together with no bracket of their own: a lone
    one-parameter effect is then searched over its whole range, not pinned at zero (joint friction 1.5 N·m hidden in
    noise-free data is found again)."""
    path = make_measured(
        {"joint_friction": [1.5]}, 2, tmp_path / "m.h5", max_steps=40, noise=SensorNoise(scale=0.0), progress=False
    )
    windows = make_windows(Dataset.load(path), np.arange(2), 5, 6)
    effect = EFFECTS["joint_friction"]
    resim = Resimulator(SPEC, solver=CONVERGED_SOLVER)  # the measured robot's own solve
    fit = fit_effect(effect, resim, windows, PhysicsParams(), FitConfig(), np.array([1.0]), None)
    assert abs(fit.values[0] - 1.5) < 0.15, fit.values


def test_one_window_a_candidate_loses_does_not_outweigh_the_rest():
    """Viscous damping hidden: the damping candidate matches 19 of 20 held-out windows and loses the 20th (a fall the
    solver resolves otherwise, 100x the nominal simulator's gap there), Coulomb friction halves every window's
    error. Uncapped, that one window outweighs the other 19 and friction is named; each window's gap counted at most
    the nominal simulator's worst (`gap_ceiling`), damping explains most and is named."""
    from rwm_gym.gap.fit import CandidateFit, gap_ceiling
    from rwm_gym.gap.judge import judge
    from rwm_gym.gap.resim import Windows

    w, horizon, size = 20, 25, SPEC.state_dim
    held = Windows(
        np.zeros(w, int),
        np.arange(w) * 25,
        np.zeros((w, 3, 2)),
        np.zeros((w, 3, 2)),
        np.zeros((w, horizon + 2, 12)),
        np.zeros((w, size)),
        np.zeros((w, horizon, size)),
        np.zeros((w, 4)),
        horizon=horizon,
        warmup=2,
    )
    spread = 1.0 + 0.02 * np.arange(w)  # each window's nominal error, in state stds

    def rollout(windows, params):
        own = spread[windows.start // 25]
        if params.joint_damping:
            off = np.where(windows.start // 25 == w - 1, 10.0, 0.05) * own
        else:
            off = own * (0.5 if params.joint_friction else 1.0)
        return off[:, None, None] * SPEC.state_std * np.ones((len(windows), horizon, size))

    resim = SimpleNamespace(spec=SPEC, rollout=rollout)
    names = ("joint_damping", "joint_friction")
    config = FitConfig()

    def named(windows):
        before = gap_per_window(SPEC, rollout(windows, PhysicsParams()), windows)
        candidates = []
        for name in names:
            fit = CandidateFit(name, [name], ["1"], [1.5], [0.0], 0.0)
            score_fit(fit, EFFECTS[name], resim, windows, PhysicsParams(), before, config)
            candidates.append((EFFECTS[name], fit))
        pick, reason, _ = judge(candidates, float(before.mean()), 0.01, config, config.significance)
        return pick[0].name if pick else reason

    assert named(held) == "joint_friction"  # uncapped: the lost window decides
    capped = gap_ceiling(resim, held, PhysicsParams())
    np.testing.assert_allclose(capped.gap_ceiling, spread[-1] ** 2)
    assert named(capped) == "joint_damping"
    assert named(capped.subset(np.arange(w) < w - 1)) == "joint_damping"  # the ceiling travels with the windows


@pytest.mark.parametrize(
    "pair_gap,pairs,named",
    [
        (0.45, 3, ["joint_friction", "payload"]),  # together 61 % of the gap above the floor, each adds a third
        (0.70, 3, []),  # together 33 %, but the payload adds 6 % on top of the friction: it is the friction alone
        (0.45, 0, []),  # no pairs tried
    ],
)
def test_where_no_single_effect_passes_a_pair_that_does_is_named(monkeypatch, pair_gap, pairs, named):
    """Three effects at once, each explaining about a quarter of the gap above the floor alone (a step needs 30 %):
    the best unrelated effects are fitted together in pairs, and a pair is named where it explains enough and each of
    its effects adds to the other."""
    from rwm_gym.gap import pairs as pairs_module
    from rwm_gym.gap.fit import CandidateFit

    alone = {"joint_friction": 0.75, "payload": 0.78, "armature": 0.80}

    def gap_of(params: PhysicsParams) -> float:
        present = {
            n
            for n, on in (
                ("joint_friction", np.any(np.asarray(params.joint_friction) != 0)),
                ("payload", params.payload_mass != 0),
                ("armature", np.any(np.asarray(params.armature) != 0)),
            )
            if on
        }
        if present == {"joint_friction", "payload"}:
            return pair_gap
        if len(present) == 2:
            return 0.70
        return alone[present.pop()] if present else 1.0

    def fits(name, gap):
        return (alone.get(name, 1.0), 1e-6) if gap == 1.0 else (gap, 1.0)

    def fit_effect(effect, resim, train, base, config, start, bracket, *args, **kwargs):
        names = [p.name for p in effect.parameters]
        return CandidateFit(effect.name, names, ["1"] * len(names), list(start), [0.1] * len(names), 0.0)

    def score_fit(fit, effect, resim, held, base, before, config):
        fit.gap_mean, fit.p_value = gap_of(effect.physics(np.asarray(fit.values), base)), 1e-6
        fit.score = 1.0 - fit.gap_mean / float(before.mean())
        return np.full((20, 3), fit.gap_mean)

    _stub_selection(monkeypatch, fits, lambda gap, windows: gap > 0.3, gap_of, 1.0)
    for name, value in (("fit_effect", fit_effect), ("score_fit", score_fit), ("paired_p_value", lambda *a: 1e-6)):
        monkeypatch.setattr(pairs_module, name, value)
    monkeypatch.setattr(pairs_module, "gap_per_window", lambda spec, params, held: np.full((20, 3), gap_of(params)))
    selection = _select(0.1, FitConfig(pair_candidates=pairs, spread_check=False, joint_candidates=0, drop_idle=False))
    assert [e.name for e, _ in selection.named] == named, selection.reason
    assert selection.verdict == (named[0] if named else "unexplained")
    if pairs:
        tried = selection.steps[0]["pairs"]["pairs"]
        assert [p["effects"] for p in tried] == [
            ["joint_friction", "payload"],
            ["joint_friction", "armature"],
            ["payload", "armature"],
        ]
    if named:
        assert "both are named" in selection.reason or "named in order" in selection.reason
        assert selection.named[0][1].values == [0.7] and selection.params.payload_mass != 0


@pytest.mark.parametrize(
    "all_three_gap,sets,named",
    [
        (0.20, True, ["joint_friction", "armature", "payload"]),  # each adds 44-78 % on top of the other two
        (0.58, True, []),  # the payload adds 2 % on top of the other two: no set
        (0.20, False, []),  # no set built
    ],
)
def test_where_no_effect_and_no_pair_passes_a_set_built_step_by_step_is_named(monkeypatch, all_three_gap, sets, named):
    """Three effects that hide one another: the friction explains 28 % of the gap above the floor alone (a step needs
    30 %), the armature and the payload 3-6 %, so no pair has two members that explain 15 % alone; on top of the
    friction the armature lowers the gap, and on top of both the payload. The set is named where each of its effects
    adds to the others."""
    gaps = {
        frozenset(): 1.0,
        frozenset({"joint_friction"}): 0.75,
        frozenset({"armature"}): 0.95,
        frozenset({"payload"}): 0.97,
        frozenset({"joint_friction", "armature"}): 0.60,
        frozenset({"joint_friction", "payload"}): 0.70,
        frozenset({"armature", "payload"}): 0.90,
        frozenset({"joint_friction", "armature", "payload"}): all_three_gap,
    }

    def present(params: PhysicsParams) -> frozenset:
        on = {
            "joint_friction": np.any(np.asarray(params.joint_friction) != 0),
            "armature": np.any(np.asarray(params.armature) != 0),
            "payload": params.payload_mass != 0,
        }
        return frozenset(n for n, v in on.items() if v)

    def fits(name, gap):
        """Each effect's gap on top of the simulator whose gap is `gap` (the named set is the one with that gap)."""
        base = next(s for s, g in gaps.items() if np.isclose(g, gap))
        if name == "torque_limit" or name in base:
            return gap, 1.0
        return gaps[base | {name}], 1e-6

    _stub_selection(monkeypatch, fits, lambda gap, windows: gap > 0.3, lambda params: gaps[present(params)], 1.0)
    _patch(monkeypatch, "paired_p_value", lambda *args: 1e-6)
    refitted = []

    def fit_effect(effect, resim, train, base, config, start, bracket, *args, **kwargs):
        refitted.append(effect.name)
        return _fit_of(effect.name, 1.0, 1.0, 1.0)

    _patch(monkeypatch, "fit_effect", fit_effect)
    config = FitConfig(spread_check=False, joint_candidates=0, drop_idle=False, stepwise_sets=sets)
    selection = _select(0.1, config)
    assert [e.name for e, _ in selection.named] == named, selection.reason
    if sets:
        built = selection.steps[0]["set"]
        assert [b["effect"] for b in built["built"]] == ["joint_friction", "armature", "payload"]
        assert built["passes"] == bool(named)
        assert refitted == ["joint_friction", "armature", "payload"]  # each refitted on top of the others, once
    if named:
        assert "all are named" in selection.reason and selection.params.payload_mass != 0
    else:
        assert selection.verdict == "unexplained"

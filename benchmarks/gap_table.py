"""The gap workflow over a grid of hidden cases, on excitation data and on an ordinary walking policy's data.

The grid: every effect of the vocabulary at 0.5x, 1x and 2x its realistic default; a robot lighter than its model
(a negative payload of 5, 10 and 15 % of its total mass); per-leg, per-joint-type and one-joint variants (values in
some joints only, hidden through per-joint `PhysicsParams`; friction in one joint of each type at 2, 4 and 6 N·m);
pairs and triples of effects; effects outside the vocabulary (a torsion spring in one joint type, edited into the
MJCF directly, `measured.write_spring_model`); and no effect, also with half and twice the sensor noise the workflow
assumes. Every case is measured with sensor noise from both data sources (`--sources`: `excitation`, and `gait` or an
SB3 `.zip` for the walking policy) and run through `rwm-gym gap --world-model none`.

Per case: the named effects (order, scope), the fitted magnitude and its error relative to the true distance from
nominal, the explained fraction of the held-out gap (and the learned correction's where one was fitted), whether what
the named effects leave is at the corrected simulator's own noise floor (`rest_at_floor`), false namings.

The robot stands in for a real one in two ways (`--robots`): `converged` solves each of its physics steps to
convergence; `fast` is the package's own physics as users train in it (the MJCF's solver settings), the case of a user
who checks the workflow with `rwm-gym collect --physics`. Either way the workflow judges `AnymalD-MuJoCo-v0` as
configured. A row's `source` is the policy, with `-fast` appended for the fast robot.

Each finished case is kept in `<out>/cases/<source>__<case>.json` and reused when its settings match (resume; run
disjoint `--shard i/n` processes in parallel: a shard takes every n-th case). Jobs run case by case, every source and
robot of a case together, so a partial run compares like with like. The summary (`summary.json`, `gap_table.md`,
`gap_table.png`) covers whatever cases have finished.

    python benchmarks/gap_table.py --out results/gap_table [--episodes 9] [--steps 150] [--sources excitation gait]
        [--robots converged fast] [--cases none friction_1x ...] [--shard 0/2] [--summary-only]
        [--reuse cross-fitting-cannot-change results/gap_v21 ...]
    python benchmarks/gap_table.py --out results/gap_table --oracle [--cases ...]   # the true simulator's share
"""

from __future__ import annotations

import argparse
import json
import re
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import mujoco
import numpy as np

from rwm_gym.atomic import write_json, write_text
from rwm_gym.data.collect import make_physics_core
from rwm_gym.data.dataset import Dataset
from rwm_gym.gap.effects import EFFECT_NAMES, combined_physics, vocabulary
from rwm_gym.gap.fit import FitConfig, gap_per_window
from rwm_gym.gap.measured import SensorNoise, make_measured, write_spring_model
from rwm_gym.gap.noise_floor import FloorConfig, compare_with_floor, noise_floor
from rwm_gym.gap.resim import Resimulator
from rwm_gym.gap.scope import joint_groups
from rwm_gym.gap.workflow import GapConfig, drop_diverged, held_out_windows, run_gap
from rwm_gym.physics.params import CONVERGED_SOLVER, build_model
from rwm_gym.spec import load_spec

SPEC = load_spec("anymal_d")
EFFECTS = vocabulary(SPEC)
ROBOT_MASS_KG = mujoco.mj_getTotalmass(build_model(SPEC))
SIM = "AnymalD-MuJoCo-v0"
ROBOT_SOLVERS = {"converged": CONVERGED_SOLVER, "fast": None}
"""How the stand-in robot's physics is solved (`make_measured`'s solver): to convergence, or as the sim env is."""


def label(source: str, robot: str) -> str:
    """A row's source: the policy's name, `-fast` appended for data from the package's own fast physics."""
    return Path(source).stem + ("" if robot == "converged" else f"-{robot}")


@dataclass(frozen=True)
class Case:
    """One hidden configuration. `truth`: {effect: full parameter vector} of the vocabulary's global effects;
    `per_joint`: (effect, scope, group, value): the effect in one joint group only, nominal elsewhere;
    `spring`: (joint type, N·m/rad)."""

    name: str
    kind: str
    """single, leg, joint_type, joint, pair, triple, outside, none."""
    truth: dict[str, list[float]] = field(default_factory=dict)
    per_joint: tuple[str, str, str, float] | None = None
    spring: tuple[str, float] | None = None
    noise_scale: float = 1.0
    """The measured data's sensor noise, a multiple of the package's default (the workflow assumes 1 and checks it)."""
    episodes: int | None = None
    """Measured episodes when the case needs more than `--episodes` (the per-joint scope is tried only with
    `scope.MIN_WINDOWS_PER_PARAMETER` fitting windows per parameter: 12 episodes give 8 x 18 = 144 for 12 joints)."""
    steps: int | None = None
    """Policy steps per measured episode when the case needs more than `--steps`."""

    def true_names(self) -> set[str]:
        return set(self.truth) | ({self.per_joint[0]} if self.per_joint else set())


ROBOT_EFFECTS = tuple(n for n in EFFECT_NAMES if n != "contact_solver")
"""The effects a robot can hide: `contact_solver` is the simulator's own accuracy, measured by the `--robots` axis
(a converged robot judged by the fast simulator), not a property of a robot."""


LONGER_DATA = {"episodes": 16, "steps": 250}
"""The measured data of the cases that need more than 9 episodes of 150 steps: effects that act in a few windows only
(a torque-speed limit, at high joint speed; a torque limit, at high torque) or below the sensor noise of each sample
(a base-velocity bias), and triples, which split the data's evidence three ways. At 9 x 150 the workflow named the
torque-speed limit in 4 of 12 such cases, the torque limit at 0.5x (70 % of the drive's peak) in 1 of 4, the
base-velocity bias in 9 of 12 and all three of a triple in 4 of 12."""

SPARSE_EFFECTS = ("torque_speed_limit", "torque_limit", "base_velocity_bias")
"""Effects whose single cases are measured on `LONGER_DATA`."""


JOINT_LOSSES = ("joint_damping", "joint_friction")
"""Viscous and Coulomb joint loss, which mimic each other (torque x joint speed, or x its sign): each also at 1.5x
its default, between the 1x and 2x rows."""


def single(name: str, scale: float) -> Case:
    """The effect `name` alone at `scale` x its default distance from nominal (on `LONGER_DATA` if it is sparse)."""
    data = LONGER_DATA if name in SPARSE_EFFECTS else {}
    return Case(f"{name}_{scale}x", "single", {name: magnitude(name, scale)}, **data)


def magnitude(name: str, scale: float) -> list[float]:
    """The effect at `scale` x its default distance from nominal (first parameter; clipped, on its step)."""
    p = EFFECTS[name].parameters[0]
    value = float(np.clip(p.nominal + scale * (p.default - p.nominal), p.low, p.high))
    value = round(value / p.step) * p.step if p.step else value
    return EFFECTS[name].values_from_magnitude(value).tolist()


LIGHTER_SHARES = (0.05, 0.10, 0.15)
"""A robot lighter than its model by these shares of its total mass (a battery out, a lighter shell)."""


ONE_JOINT_FRICTION = {"LF_HAA": (2.0, 4.0, 6.0), "LF_HFE": (2.0, 4.0, 6.0), "LF_KFE": (2.0, 4.0)}
"""Friction (N·m) in one joint of each type, the rest nominal: a worn joint (`friction_LF_KFE_6` is among the
first cases)."""


def one_joint(joint: str, friction: float) -> Case:
    """Coulomb friction in `joint` alone (12 episodes: enough fitting windows for the per-joint scope)."""
    name = f"friction_{joint}_{friction:g}"
    return Case(name, "joint", per_joint=("joint_friction", "joint", joint, friction), episodes=12)


def lighter(share: float) -> Case:
    """The robot lighter by `share` of its total mass (read from its model): a negative payload at the base origin."""
    removed = share * ROBOT_MASS_KG
    payload = EFFECTS["payload"].values_from_magnitude(-removed).tolist()
    return Case(f"lighter_{round(100 * share)}pct", "single", {"payload": payload})


def grid() -> list[Case]:
    """Every case, in run order: the most informative first, so a partial run covers every kind."""
    first = [
        Case("none", "none"),
        Case("spring_KFE_30", "outside", spring=("KFE", 30.0)),
        single("action_delay", 1),
        Case("friction_KFE_4", "joint_type", per_joint=("joint_friction", "joint_type", "KFE", 4.0)),
        Case(
            "friction+payload",
            "pair",
            {"joint_friction": magnitude("joint_friction", 1.5), "payload": magnitude("payload", 1.0)},
        ),
        Case("friction_LF_6", "leg", per_joint=("joint_friction", "leg", "LF", 6.0)),
        one_joint("LF_KFE", 6.0),
        Case(
            "delay+armature",
            "pair",
            {"action_delay": magnitude("action_delay", 1.0), "armature": magnitude("armature", 1.0)},
        ),
    ]
    first += [single(n, 1) for n in ROBOT_EFFECTS if n != "action_delay"]
    rest = [single(n, s) for s in (0.5, 2.0) for n in ROBOT_EFFECTS]
    rest += [single(n, 1.5) for n in JOINT_LOSSES]
    rest += [
        Case("strength_RH_0.6", "leg", per_joint=("motor_strength", "leg", "RH", 0.6)),
        Case("armature_HFE_0.1", "joint_type", per_joint=("armature", "joint_type", "HFE", 0.1)),
        Case(
            "strength+ground",
            "pair",
            {"motor_strength": magnitude("motor_strength", 1.0), "ground_friction": magnitude("ground_friction", 1.0)},
        ),
        Case(
            "damping+backlash",
            "pair",
            {"joint_damping": magnitude("joint_damping", 1.5), "backlash": magnitude("backlash", 1.0)},
        ),
        Case("spring_HFE_20", "outside", spring=("HFE", 20.0)),
        Case("spring_HFE_40", "outside", spring=("HFE", 40.0)),
        Case("none_seed1", "none"),
        Case("none_noise_0.5x", "none", noise_scale=0.5),
        Case("none_noise_2x", "none", noise_scale=2.0),
    ]
    triples = [
        Case(
            "delay+payload+ground",
            "triple",
            {n: magnitude(n, 1.0) for n in ("action_delay", "payload", "ground_friction")},
            **LONGER_DATA,
        ),
        Case(
            "strength+friction+encoder",
            "triple",
            {n: magnitude(n, 1.0) for n in ("motor_strength", "joint_friction", "encoder_offset")},
            **LONGER_DATA,
        ),
        Case(
            "armature+damping+compliance",
            "triple",
            {n: magnitude(n, 1.0) for n in ("armature", "joint_damping", "ground_compliance")},
            **LONGER_DATA,
        ),
    ]
    joints = [one_joint(joint, value) for joint, values in ONE_JOINT_FRICTION.items() for value in values]
    return first + triples + rest + [lighter(share) for share in LIGHTER_SHARES] + joints


CASES = {case.name: case for case in grid()}


def hidden_physics(case: Case) -> dict:
    """The PhysicsParams fields a per-joint case hides beside its global effects (`make_measured`'s extra_physics)."""
    if not case.per_joint:
        return {}
    name, scope, group, value = case.per_joint
    p = EFFECTS[name].parameters[0]
    values = np.full(12, p.nominal)
    values[joint_groups(SPEC, scope)[group]] = value
    return {EFFECTS[name].apply(np.array([p.default])).popitem()[0]: values.tolist()}


def measure(case: Case, source: str, args: argparse.Namespace, tmp: Path, robot: str = "converged") -> Path:
    """The case's measured data from `source` on the `robot` solver (the same file for the same settings)."""
    env_kwargs = {}
    if case.spring:
        env_kwargs["xml_file"] = str(write_spring_model(SPEC, tmp / f"{case.name}.xml", *case.spring))
    seed = args.seed + (1 if case.name.endswith("seed1") else 0)
    return make_measured(
        case.truth,
        case.episodes or args.episodes,
        tmp / f"{label(source, robot)}_{case.name}.h5",
        max_steps=case.steps or args.steps,
        seed=seed,
        policy=source,
        env_kwargs=env_kwargs,
        extra_physics=hidden_physics(case),
        noise=SensorNoise(scale=case.noise_scale),
        solver=ROBOT_SOLVERS[robot],
        progress=False,
        overwrite=True,
    )


def solver_check_row(check: dict) -> dict:
    """What a row keeps of the solver check: the best single effect and its held-out gap under each solver, and
    whether the named effects' refit under a converged solve decided (so that a later change to the check can tell
    which rows it reaches)."""
    out = {"checked": check["checked"], "taken": check["taken"]}
    for name in ("own", "converged"):
        if name in check:
            out[name] = {k: check[name][k] for k in ("best_effect", "scope", "held_out_gap")}
    if "named_set" in check:
        out["named_set_taken"] = check["named_set"]["taken"]
    if "reselection" in check:
        out["reselection_kept"] = check["reselection"]["kept"]
    return out


def run_case(case: Case, source: str, args: argparse.Namespace, tmp: Path, robot: str = "converged") -> dict:
    """Measure the case from `source` on the `robot` solver, run the workflow, score the verdict."""
    start = time.time()
    try:
        data = measure(case, source, args, tmp, robot)
        report = run_gap(SIM, data, tmp / f"{label(source, robot)}_{case.name}", progress=False)
    except ValueError as err:  # a robot that falls at once (no episode long enough) or whose physics blows up
        return {
            "case": case.name,
            "kind": case.kind,
            "source": source,
            "error": str(err),
            "settings": settings(args, case),
        }
    named = [(e["effect"], e["scope"]) for e in report["effects"]]
    true = case.true_names()
    errors, fitted_first = {}, {}
    for item in report["effects"]:
        name = item["effect"]
        if name in case.truth:
            p = EFFECTS[name].parameters[0]
            fitted = item["parameters"].get(p.name)
            if fitted is not None:
                errors[name] = abs(fitted - case.truth[name][0]) / abs(case.truth[name][0] - p.nominal)
                fitted_first[name] = fitted
        elif case.per_joint and name == case.per_joint[0] and item["scope"] == case.per_joint[1]:
            _, _, group, value = case.per_joint
            p = EFFECTS[name].parameters[0]
            fitted = item["parameters"][f"{p.name}_{group}"]
            errors[name] = abs(fitted - value) / abs(value - p.nominal)
    learned = report["learned_correction"]
    return {
        "case": case.name,
        "kind": case.kind,
        "source": source,
        "true": sorted(true),
        "episodes": case.episodes or args.episodes,
        "steps": case.steps or args.steps,
        "truth": case.truth,
        "per_joint": case.per_joint,
        "spring": case.spring,
        "verdict": report["effect"],
        "named": named,
        "reason": report["reason"],
        "correct": (
            sorted({n for n, _ in named}) == sorted(true)
            if case.kind not in ("outside", "none")
            else report["effect"] == ("unexplained" if case.kind == "outside" else "none")
        ),
        "scope_correct": (
            any(n == case.per_joint[0] and s == case.per_joint[1] for n, s in named) if case.per_joint else None
        ),
        "false_namings": sorted({n for n, _ in named} - true),
        "magnitude_error": errors,
        "fitted_magnitude": fitted_first,
        "explained_fraction": report["explained_fraction"],
        "gap_measure": report["gap_measure"],
        "learned_explained_fraction": learned["explained_fraction"] if learned and learned["status"] == "ok" else None,
        "learned_total_explained": (1.0 - learned["gap_after"] / report["gap_before"])
        if learned and learned["status"] == "ok"
        else None,
        "gap_before": report["gap_before"],
        "floor": report["noise_floor"]["floor"],
        "floor_corrected": report["residual"]["floor"],
        "rest_at_floor": not report["residual"]["above_floor"],
        "floor_ratio": report["noise_floor"]["ratio"],
        "above_floor": report["noise_floor"]["above_floor"],
        "identifiable": {k: v["identifiable"] for k, v in report["identifiability"].items()},
        "signal_to_floor": {k: v["signal_to_floor"] for k, v in report["identifiability"].items()},
        "rejected_points": len(report["rejected"]),
        "solver_taken": report["solver"]["check"]["taken"],
        "solver_check": solver_check_row(report["solver"]["check"]),
        "wall_s": time.time() - start,
        "settings": settings(args, case),
    }


def oracle(case: Case, source: str, args: argparse.Namespace, tmp: Path) -> dict:
    """What the true simulator leaves on the case's held-out windows (the workflow's split, horizons and sensor-noise
    floor): the best any correction can do on these data. Cases with vocabulary effects only. The true simulator is
    the converged robot's: its hidden physics, solved to convergence as its data were."""
    data = measure(case, source, args, tmp)
    config = GapConfig()
    _, _, held = held_out_windows(Dataset.load(data), config)
    resim = Resimulator(SPEC, solver=ROBOT_SOLVERS["converged"])
    base = make_physics_core(SIM, 1).params
    held, _ = drop_diverged(resim, held, base, data)  # as the workflow drops them
    true = combined_physics(case.truth, SPEC, base.replace(**hidden_physics(case)))
    before, after = (gap_per_window(SPEC, resim.rollout(held, p), held) for p in (base, true))
    floor = noise_floor(resim, held, true, SensorNoise(), FloorConfig())
    rest = compare_with_floor(after, floor, held, FitConfig().block_rows, FloorConfig())
    return {
        "case": case.name,
        "source": source,
        "kind": case.kind,
        "gap_nominal": float(before.mean()),
        "gap_true": float(after.mean()),
        "true_explained": float(1.0 - after.mean() / before.mean()),
        "true_floor": rest["floor"],
        "true_rest_above_its_floor": rest["above_floor"],
        "settings": settings(args, case),
    }


def settings(args: argparse.Namespace, case: Case) -> dict:
    """What a row of `case` was run with: its measured data and the workflow's version."""
    # version 2: make-measured and the re-simulations solve each physics step to convergence (CONVERGED_SOLVER)
    # version 3: the two best joint effects are fitted in their scopes (FitConfig.scoped_effects)
    # version 4: ... of those whose global form reduces the held-out gap, one sweep per group fit
    # version 5: two sweeps per group fit again (FitConfig.group_sweeps: one left knee friction unexplained)
    # version 6: joint effects are also fitted at one joint alone where its residual stands out (scope.outlying_joint)
    # version 7: later selection steps also fit the best candidates together with the named effects (joint_candidates)
    # version 8: with too few held-out blocks for the rank test to reach p < 0.01, a t-test on log ratios decides
    #            (significance.paired_p_value); only cases with fewer than 7 held-out blocks can differ from version 7
    # version 9: the learned correction is fitted to the base and joint velocities' one-step miss, weight decay 1e-3
    #            (gap.learned); only cases with a learned correction can differ from version 8
    # version 10: where the whole gap is not above the noise floor, step 1 still tests each candidate's own reduction
    #             (Bonferroni over the step's candidates); at every step a candidate must explain 30 % of the gap above
    #             the floor, not of the whole gap (select); re-simulation models come from one compile (ModelCache)
    # version 11: rivals are alike in the penalised gap they leave above the floor, not in the whole gap they leave
    #             (judge.name_step); any step that ended on an ambiguity can differ, so every case reruns
    # version 12: a scoped form that could not beat the step's best candidate even with no gap left is not fitted
    #             (scope._scoped_fits); it could never be named, so no verdict should differ from version 11
    # version 13: near the floor, step 1's best candidate that fails only its held-out test is tested again on every
    #             episode, 2-fold cross-fitted (cross_fit.cross_fitted_p_value); only cases whose whole gap is not above
    #             the floor can differ from version 12
    # version 14: the learned correction is a linear residual torque per joint type, fitted through 5-step
    #             re-simulation (gap.learned); only cases with a learned correction can differ from version 13
    # version 15: where no held-out episode reaches the last gap horizon (a robot that falls within a second), the
    #             held-out windows are cut to the shortest one (workflow.scored_horizon); only cases that were errors
    #             can differ from version 14
    # version 16: before step 1 calls a gap `unexplained`, every effect is refined, not only the 3 best screened
    #             (FitConfig.refine_every_effect); only cases that were `unexplained` can differ from version 15
    # version 17: what named effects leave is tested against the corrected simulator's own noise floor
    #             (`rest_at_floor`); only the residual test and the learned correction after named effects can differ
    # version 18: a lone named effect of several parameters is refitted by least squares, kept if the held-out gap
    #             does not grow (FitConfig.refit_single_effect); only such runs can differ from version 17
    # version 19: the workflow re-simulates with the sim env's own solver and checks it against a converged solve
    #             (gap.solver_check); the noise floor uses the noise estimated from the data where it disagrees with
    #             the assumed model (gap.noise_estimate); the vocabulary has the drive, floor and sensor effects and the
    #             contact solver; every case reruns. Also in 19: an unrelated candidate is a rival only if it
    #             explains FitConfig.rival_excess_explained itself, and a rival that the best holds (the best
    #             still explains enough on top of it, not the other way round) is resolved for the best
    #             (judge.resolve_rivals), each test cross-fitted on every episode where the held-out third alone is
    #             not significant; rows run before these differ only if they end `ambiguous`, and those ran again
    # version 20: a step after the first tests the gap against the noise floor of the simulator with the effects named
    #             so far, not the nominal one's (select.select_effects, floor_of); a named effect gives way to a
    #             simpler one it holds that fits alike (select.prefer_simpler: PD gains -> motor strength); only runs
    #             where step 1 named an effect can differ from version 19 (`--reuse nothing-named`)
    # version 21: from two named effects on, they are refitted together after each naming, before the next step
    #             (select.select_effects); only runs that named two or more can differ from version 20
    #             (`--reuse at-most-one-named`); rows of version 19 that named one effect of one parameter and left
    #             the rest at the corrected floor stop at step 2 of versions 20 and 21 alike
    #             (`--reuse one-effect-left-at-its-floor`)
    # version 22: a step after the first whose gap is not significantly above its floor tests it again on every
    #             episode, and where it is above the floor there, fits the candidates and tests each one's own
    #             reduction, the best cross-fitted on every episode (as step 1 does; FitConfig.near_the_floor_after_
    #             naming); its pick must leave less above its own simulator's floor (step._against_its_own_floor).
    #             Before step 1 calls a gap `unexplained`, a best candidate that explains enough but fails only its
    #             held-out test is tested cross-fitted. Only rows that stopped at a later step's floor test, or were
    #             `unexplained` so, can differ from version 21 (`--reuse cross-fitting-cannot-change`)
    # version 23: the torque-speed limit, base-velocity bias and triple cases are measured on 16 episodes of 250
    #             steps (LONGER_DATA); the settings hold each case's own episodes and steps, and no other row can
    #             differ from version 22 (`--reuse same-measured-data`)
    # version 24: a multi-parameter effect's least-squares fit starts from a Brent search of its first parameter
    #             within the screening bracket (fit.first_along_bracket); every row can differ from version 23
    # version 25: where that search moved the start, least squares also runs from the screened point and the cheaper
    #             end is kept (fit.cheapest_least_squares); every row can differ from version 24
    # version 26: where the solver check kept the sim env's own solver and effects were named, they are refitted
    #             together under a converged solve, and the selection runs again under it where that fits
    #             materially better (solver_check.recheck_with_named); only rows that named an effect can differ
    #             from version 25
    # version 27: where a step's best candidate and an unrelated rival stay alike, both are followed to the end of
    #             selection and the branch that leaves clearly less is taken (search._look_ahead); only rows whose
    #             reason says `ambiguous` can differ from version 26
    # version 28: where step 1 would call a gap above the floor `unexplained`, an effect whose own noise spread covers
    #             the data is named (step._by_spread, gap.spread); only rows `unexplained` at step 1 without an
    #             ambiguous rival can differ from version 27
    # version 29: the base-velocity bias is refined by least squares on the windows' mean residual
    #             (Effect.fit_on_mean); its own cases can differ from version 28, and any row where it was refined as a
    #             candidate could
    # version 30: where no single effect lowers the held-out gap under the sim env's own solver, the solver check fits
    #             every joint effect in its scopes under it before it compares the solvers
    #             (solver_check.best_candidate); only rows where the check took the converged solve can differ from
    #             version 29 (`--reuse own-solver-kept`); and where the named effects' refit took the converged
    #             solve but the selection under it leaves materially more than they did, the own solver's selection
    #             stands (solver_check.lost_in_reselection), which also reaches only rows that took the converged solve
    # version 31: of several named effects, one that adds nothing at the final values is dropped (select.drop_idle);
    #             only rows that named two or more effects can differ from version 30 (`--reuse at-most-one-named`)
    # version 32: the payload's mass reaches below zero (a robot lighter than its model, down to half its base body's
    #             mass), so its screening grid and searches differ wherever it is a candidate: every row can differ
    #             from version 31
    # version 33: no held-out window's gap counts for more than the nominal simulator's worst at that horizon
    #             (fit.gap_ceiling); joint damping and joint friction also at 1.5x; every row can differ from version 32
    # version 34: where step 1 would call a gap above the floor `unexplained`, every joint effect is also fitted at the
    #             joint that stands out most against the same joint in the other legs (then deviant_joint_fits);
    #             only rows whose step 1 reached that search (`unexplained`, or named there by a scoped form, the
    #             cross-fitted test or an effect's spread) can differ from version 33
    # version 35: that joint's single-joint fits are offered at every step, beside the outlying joint's
    #             (scope.single_joint_candidates); every row can differ from version 34
    # version 36: those single-joint forms no longer count as their effect's group scopes in step 1's last search
    #             (scope.every_scope fitted nothing wherever they were offered); only rows whose step 1 reached that
    #             search (`unexplained`, or named there by a scoped form, the cross-fitted test or an effect's spread)
    #             can differ from version 35
    # version 37: where a step with its gap above the floor names nothing, the best unrelated effects are fitted
    #             together in pairs and a pair whose every effect adds to the other is named (gap.pairs); only rows
    #             that ended on such a step (`unexplained` at step 1, or stopped above a later step's floor) can differ
    #             from version 36. Re-simulation also keeps its last rollouts and skips a forward pass that changed
    #             nothing (the same states)
    # version 38: where no pair passes either, a set built step by step whose every effect adds to the others is
    #             named (gap.sets); and where the own solver names nothing with the gap above the floor, the selection
    #             under the converged solve is taken where it names something and leaves materially less; the same
    #             rows as version 37 can differ from it
    # version 39: the solver check fits the scoped forms only where the global forms leave the choice of solver open
    #             (solver_check.choose_solver); a row can differ from version 38 only where the solver taken differs
    # version 40: the coarse grid is screened on every other fitting window (FitConfig.screen_stride); every row can
    #             differ
    # version 41: screening on every fitting window again, as at version 39 (at version 40 friction + payload on the
    #             converged robot's excitation data named a third, false effect); version 39's rows stand
    #             (`--reuse version-39`)
    return {
        "episodes": case.episodes or args.episodes,
        "steps": case.steps or args.steps,
        "seed": args.seed,
        "version": 41,
    }


def summarise(rows: list[dict]) -> dict:
    """The must-reach figures per data source over the finished cases."""
    out = {}
    for source in sorted({r["source"] for r in rows}):
        rs = [r for r in rows if r["source"] == source and "error" not in r]
        out[source] = {
            "cases": len(rs),
            "errors": len([r for r in rows if r["source"] == source and "error" in r]),
            **_where_named(rs),
            **_by_kind(rs),
            "median_minutes_per_case": median_minutes(rs),
            "median_minutes_one_effect": median_minutes([r for r in rs if r["kind"] == "single"]),
        }
    return out


def median_minutes(rs: list[dict]) -> float | None:
    """The median wall time of these cases' workflow runs, in minutes (None where none recorded it)."""
    times = [r["wall_s"] for r in rs if r.get("wall_s") is not None]
    return float(np.median(times)) / 60.0 if times else None


def _where_named(rs: list[dict]) -> dict:
    """Of one source's cases with an effect: how often it was named, and how well where it was."""
    effect = [r for r in rs if r["kind"] in ("single", "leg", "joint_type", "joint", "pair", "triple")]
    named_right = [r for r in effect if r["correct"]]
    errs = [e for r in named_right for e in r["magnitude_error"].values()]
    explained = [r["explained_fraction"] for r in named_right]
    excess = [excess_explained(r) for r in named_right]
    return {
        "named_correctly": frac([r["correct"] for r in effect]),
        "magnitude_within_25pct_of_named": frac([e <= 0.25 for e in errs]),
        "explained_ge_70pct_where_named": frac([x >= 0.7 for x in explained]),
        "mean_explained_where_named": float(np.mean(explained)) if explained else None,
        "excess_explained_ge_70pct_where_named": frac([x >= 0.7 for x in excess]),
        # rows reused from before version 17 (`--reuse above-floor`) have no rest_at_floor
        "explained_ge_70pct_or_rest_at_its_floor_where_named": frac(
            [x >= 0.7 or r.get("rest_at_floor", False) for x, r in zip(explained, named_right)]
        ),
        # the gap by the report's own measure (`gap.distribution.headline`), in rows that record it
        "report_gap_falls_where_named": frac(
            [r["gap_measure"]["explained_fraction"] > 0 for r in rs if r.get("named") and "gap_measure" in r]
        ),
    }


def _by_kind(rs: list[dict]) -> dict:
    """Of one source's cases: the figures of each kind of case (unexplained, none, outside, pairs, triples, scoped)
    and the false namings."""
    unnamed = [r for r in rs if r["verdict"] == "unexplained" and r["learned_total_explained"] is not None]
    return {
        "learned_ge_50pct_where_unexplained": frac([r["learned_total_explained"] >= 0.5 for r in unnamed]),
        "none_on_nominal": frac([r["verdict"] == "none" for r in rs if r["kind"] == "none"]),
        "outside_not_named": frac([not r["named"] for r in rs if r["kind"] == "outside"]),
        "both_named_in_pairs": frac([r["correct"] for r in rs if r["kind"] == "pair"]),
        "all_three_named_in_triples": frac([r["correct"] for r in rs if r["kind"] == "triple"]),
        "scope_right_where_grouped": frac([r["scope_correct"] for r in rs if r.get("scope_correct") is not None]),
        "false_namings": sum(len(r["false_namings"]) for r in rs),
        "cases_with_false_namings": sum(bool(r["false_namings"]) for r in rs),
    }


def fast_vs_converged(rows: list[dict]) -> dict:
    """Per policy: the share of cases judged right on data of the fast robot and of the converged one, over the cases
    both finished (the aim: the fast robot's within 5 points of the converged one's)."""
    by = {(r["source"], r["case"]): r for r in rows if "error" not in r}
    out = {}
    for source in sorted({s for s, _ in by if not s.endswith("-fast")}):
        both = [c for s, c in by if s == source and (f"{source}-fast", c) in by]
        if both:
            out[source] = {
                "cases": len(both),
                "converged_correct": float(np.mean([by[source, c]["correct"] for c in both])),
                "fast_correct": float(np.mean([by[f"{source}-fast", c]["correct"] for c in both])),
                "differ": sorted(c for c in both if by[source, c]["correct"] != by[f"{source}-fast", c]["correct"]),
            }
    return out


def identifiability_table(rows: list[dict]) -> str:
    """Each effect's signal at its default over the noise floor on the nominal robot's data, per source: which data
    could reveal which effect (`gap.identifiability`; the `none` case's report)."""
    nominal = {r["source"]: r["signal_to_floor"] for r in rows if r["case"] == "none" and "signal_to_floor" in r}
    if not nominal:
        return ""
    sources = sorted(nominal)
    lines = ["| effect at its default: signal / floor | " + " | ".join(sources) + " |", "|---|" + "---|" * len(sources)]
    for name in nominal[sources[0]]:
        lines.append(f"| {name} | " + " | ".join(f"{nominal[s][name]:.1f}" for s in sources) + " |")
    return "\n".join(lines) + "\n"


def excess_explained(row: dict) -> float:
    """Share of the gap above the noise floor that the named effects remove (the floor itself cannot be removed)."""
    before, floor = row["gap_before"], row["floor"]
    return row["explained_fraction"] * before / (before - floor) if before > floor else float("nan")


def frac(flags: list[bool]) -> dict | None:
    return {"fraction": float(np.mean(flags)), "n": len(flags)} if flags else None


def markdown(rows: list[dict], summary: dict) -> str:
    header = (
        "| source | case | kind | named (scope) | correct | magnitude error | explained | learned | gap / floor | min |"
    )
    lines = [header, "|---|---|---|---|---|---|---|---|---|---|"]
    for r in sorted(rows, key=lambda r: (r["source"], r["kind"], r["case"])):
        if "error" in r:
            lines.append(f"| {r['source']} | {r['case']} | {r['kind']} | error: {r['error'][:60]} | | | | | | |")
            continue
        named = ", ".join(f"{n} ({s})" for n, s in r["named"]) or r["verdict"]
        err = ", ".join(f"{v:.0%}" for v in r["magnitude_error"].values()) or "-"
        learned = f"{r['learned_total_explained']:.0%}" if r["learned_total_explained"] is not None else "-"
        minutes = f"{r['wall_s'] / 60:.1f}" if r.get("wall_s") is not None else "-"
        lines.append(
            f"| {r['source']} | {r['case']} | {r['kind']} | {named} | {'yes' if r['correct'] else 'no'} | "
            f"{err} | {r['explained_fraction']:.0%} | {learned} | {r['floor_ratio']:.2f} | {minutes} |"
        )
    lines += ["", "| figure | " + " | ".join(summary) + " |", "|---|" + "---|" * len(summary)]
    keys = next(iter(summary.values()), {}).keys()
    for key in keys:
        cells = []
        for s in summary.values():
            v = s[key]
            cells.append(
                f"{v['fraction']:.0%} (n={v['n']})"
                if isinstance(v, dict)
                else "-"
                if v is None
                else f"{v:.2f}"
                if isinstance(v, float)
                else str(v)
            )
        lines.append(f"| {key} | " + " | ".join(cells) + " |")
    for source, c in fast_vs_converged(rows).items():
        lines += [
            "",
            f"{source}: judged right on {c['converged_correct']:.0%} of {c['cases']} cases from the converged robot, "
            f"{c['fast_correct']:.0%} from the fast one; differ: {', '.join(c['differ']) or 'none'}.",
        ]
    table = identifiability_table(rows)
    if table:
        lines += ["", table.rstrip("\n")]
    reused = sorted({r["reused_version"] for r in rows if "reused_version" in r})
    if reused:
        count = sum("reused_version" in r for r in rows)
        lines += [
            "",
            f"{count} of {len(rows)} cases were run at version {', '.join(map(str, reused))} and reused "
            "(`--reuse`: the change cannot reach them).",
        ]
    return "\n".join(lines) + "\n"


def side_by_side(rows: list[dict]) -> str:
    """One line per case, the data sources side by side (the README's table)."""
    sources = sorted({r["source"] for r in rows})
    by = {(r["case"], r["source"]): r for r in rows}
    order = [c.name for c in grid()]
    cases = sorted({r["case"] for r in rows}, key=lambda c: order.index(c) if c in order else len(order))

    def cell(r: dict | None) -> str:
        if r is None:
            return "not run"
        if "error" in r:
            return "error"
        named = ", ".join(f"{n}" + (f" ({s})" if s != "global" else "") for n, s in r["named"]) or r["verdict"]
        err = "; ".join(f"err {v:.0%}" for v in r["magnitude_error"].values())
        learned = f"; learned {r['learned_total_explained']:.0%}" if r["learned_total_explained"] is not None else ""
        mark = "✓" if r["correct"] else "✗"
        above = f" ({excess_explained(r):.0%} above floor)" if r["named"] else ""
        above += "; rest at its floor" if r["named"] and r.get("rest_at_floor") else ""
        return (
            f"{mark} {named}" + (f"; {err}" if err else "") + f"; expl. {r['explained_fraction']:.0%}{above}{learned}"
        )

    lines = ["| case | " + " | ".join(sources) + " |", "|---|" + "---|" * len(sources)]
    lines += [f"| {c} | " + " | ".join(cell(by.get((c, s))) for s in sources) + " |" for c in cases]
    return "\n".join(lines) + "\n"


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    kinds = ["single", "leg", "joint_type", "joint", "pair", "triple", "outside", "none"]
    sources = sorted({r["source"] for r in rows})
    fig, axes = plt.subplots(1, 2, figsize=(12, 4))
    for i, source in enumerate(sources):
        acc = [
            np.mean(
                [r["correct"] for r in rows if r["source"] == source and r["kind"] == k and "error" not in r]
                or [np.nan]
            )
            for k in kinds
        ]
        width = 0.8 / len(sources)
        axes[0].bar(np.arange(len(kinds)) + width * (i + 0.5) - 0.4, acc, width, label=source)
        pts = [
            (r["explained_fraction"], r["learned_total_explained"] or r["explained_fraction"])
            for r in rows
            if r["source"] == source and "error" not in r and r["kind"] != "none"
        ]
        if pts:
            axes[1].scatter(*zip(*pts), label=source, alpha=0.7)
    axes[0].set_xticks(range(len(kinds)), kinds)
    axes[0].set_ylabel("verdict correct (fraction of cases)")
    axes[0].set_ylim(0, 1.25)  # room above the bars for the legend
    axes[0].legend(loc="upper center", ncol=len(sources), fontsize="small")
    axes[1].set_xlabel("explained by named effects")
    axes[1].set_ylabel("explained with the learned correction")
    axes[1].plot([0, 1], [0, 1], "k:", lw=0.8)
    axes[1].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


REUSABLE = {
    "above-floor": lambda row: bool(row.get("above_floor")),
    "nothing-named": lambda row: "named" in row and not row["named"],
    "at-most-one-named": lambda row: "named" in row and len(row["named"]) <= 1,
    "one-effect-left-at-its-floor": lambda row: (
        len(row.get("named", [])) == 1
        and row["named"][0][1] == "global"
        and len(EFFECTS[row["named"][0][0]].parameters) == 1
        and row.get("rest_at_floor") is True
    ),
    "cross-fitting-cannot-change": lambda row: (
        "named" in row and not stopped_near_a_later_floor(row) and not unexplained_by_its_held_out_test(row)
    ),
    "same-measured-data": lambda row: "named" in row,
    "neither-ambiguous-nor-unexplained": lambda row: (
        "named" in row
        and row["verdict"] != "unexplained"
        and _ran_at(row) >= 25
        and (_ran_at(row) >= 26 or not row["named"])
        and (_ran_at(row) >= 27 or "ambiguous" not in row["reason"])
    ),
    "own-solver-kept": lambda row: row.get("solver_taken") == "own",
    "version-39": lambda row: row["settings"]["version"] == 39 or _ran_at(row) == 39,
}
"""`--reuse WHEN DIR`: which earlier rows a version's change cannot reach: one whose nominal gap was above the noise
floor (a change to gaps near the floor), one where step 1 named nothing (a change to the steps after it), one that
named at most one effect (a change to what follows a second), one that named one effect of one parameter and left
a gap not above the corrected simulator's floor (`rest_at_floor`: with nothing refitted, that is the test a step 2
against its own simulator's floor makes, so it stops there too), or one that neither stopped at the floor test of a
step after a naming nor was called `unexplained` where its best candidate failed only its held-out test (a change to
what such steps test), or any finished row where the change is to some cases' measured data only (the settings of
those cases differ, so they run again), or a row of version 25 or later that did not end `unexplained`, that named
nothing if it ran at version 25, and that did not end on an ambiguity if it ran before version 27 (versions 26, 27
and 28 change only what follows a naming, an ambiguity and an `unexplained` step 1; rows of version 24 or earlier
run again), or one where the solver check kept the sim env's own solver (a change that can only lower the own
solver's best in the check leaves a converged solve that was not materially better so; only one that was, and failed
the p-value alone, could differ; the selection under the own solver takes the same fits), or one that stood at
version 39, run there or taken there from earlier (version 41 undoes version 40's only change)."""


def _ran_at(row: dict) -> int:
    """The version a row ran at (a reused row keeps it in `reused_version`)."""
    return row.get("reused_version", row["settings"]["version"])


def stopped_near_a_later_floor(row: dict) -> bool:
    """Whether selection named an effect, then stopped at a step whose gap was not significantly above its floor (read
    from the row's reason: what follows the first step's decision, or the list of named effects)."""
    named = row.get("named", [])
    if not named or len(named) >= FitConfig().max_effects:
        return False
    marker = "; then: " if len(named) == 1 else "; "
    if marker not in row["reason"]:
        return False
    stop = row["reason"].split(marker, 1)[1]
    below = "not above" in stop or "not significantly above" in stop  # the wording of rows before version 25
    return stop.startswith("held-out gap") and below


def unexplained_by_its_held_out_test(row: dict) -> bool:
    """Whether step 1 called the gap `unexplained` where its best candidate explained enough of it and failed only the
    held-out test (read from the row's reason)."""
    if row.get("verdict") != "unexplained":
        return False
    found = re.match(r"best candidate .* explains (-?[\d.]+)% .*\(p=", row["reason"])
    return found is not None and float(found.group(1)) >= 100 * FitConfig().min_excess_explained


def reuse_row(earlier: Path, path: Path, args: argparse.Namespace, when: str) -> bool:
    """Copy an earlier run's finished case to `path` if `REUSABLE[when]` holds for it and its settings differ from
    these in the version only; the row keeps the version it ran at (`reused_version`)."""
    if not earlier.is_file():
        return False
    row = json.loads(earlier.read_text())
    new = settings(args, CASES[row["case"]])
    # rows before version 23 hold the grid's episodes in their settings, and their own in the row
    old = row.get("settings", {})
    old = {**old, "episodes": row.get("episodes", old.get("episodes")), "steps": row.get("steps", old.get("steps"))}
    if not REUSABLE[when](row) or {**old, "version": new["version"]} != new:
        return False
    write_json(path, {**row, "settings": new, "reused_version": row.get("reused_version", old["version"])})
    return True


def run_oracle(jobs: list[tuple[Case, str]], args: argparse.Namespace) -> None:
    """`--oracle`: one JSON per case and source (kept and reused like the workflow's cases), and a table."""
    folder = args.out / "oracle"
    folder.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        for case, source in jobs:
            path = folder / f"{Path(source).stem}__{case.name}.json"
            if not (path.is_file() and json.loads(path.read_text()).get("settings") == settings(args, case)):
                write_json(path, {**oracle(case, source, args, Path(tmp)), "source": Path(source).stem})
    rows = [json.loads(p.read_text()) for p in sorted(folder.glob("*.json"))]
    lines = [
        "| source | case | held-out gap explained by the true simulator | its rest above its own floor |",
        "|---|---|---|---|",
    ]
    lines += [
        f"| {r['source']} | {r['case']} | {r['true_explained']:.0%} | "
        f"{'yes' if r['true_rest_above_its_floor'] else 'no'} |"
        for r in rows
    ]
    write_text(args.out / "oracle.md", "\n".join(lines) + "\n")
    print("\n".join(lines))


def shard_jobs(cases: list[Case], robots: list[str], sources: list[str], shard: str) -> list[tuple[Case, str, str]]:
    """The (case, source, robot) jobs of `shard` "i/n": every n-th case from the i-th, each with all its robots and
    sources, so one shard runs a case's rows together and every shard gets both data sources (excitation rows take
    2-4x a walking row's time)."""
    i, n = (int(x) for x in shard.split("/"))
    return [(c, s, r) for c in cases[i::n] for r in robots for s in sources]


def run_jobs(jobs: list[tuple], folder: Path, args: argparse.Namespace) -> None:
    """Run each (case, source, robot) job into `folder`, except those already there with the same settings or taken
    from an earlier run (`--reuse`)."""
    with tempfile.TemporaryDirectory() as tmp:
        for case, source, robot in jobs:
            path = folder / f"{label(source, robot)}__{case.name}.json"
            if path.is_file() and json.loads(path.read_text()).get("settings") == settings(args, case):
                continue
            if any(reuse_row(Path(d) / "cases" / path.name, path, args, when) for when, d in args.reuse):
                continue
            row = run_case(case, source, args, Path(tmp), robot)
            row["source"] = label(source, robot)
            row["robot"] = robot
            write_json(path, row)
            print(
                f"{row['source']:10s} {case.name:22s} {row.get('verdict', 'error'):16s} "
                f"{row.get('named', row.get('error'))} {row.get('wall_s', 0):.0f}s",
                flush=True,
            )


def _parser() -> argparse.ArgumentParser:
    """The script's options."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("results/gap_table"))
    parser.add_argument("--episodes", type=int, default=9, help="measured episodes per case")
    parser.add_argument("--steps", type=int, default=150, help="policy steps per episode")
    parser.add_argument(
        "--sources",
        nargs="*",
        default=["excitation", "gait"],
        help="policies that produce the measured data (excitation, gait, random, an SB3 .zip)",
    )
    parser.add_argument(
        "--robots",
        nargs="*",
        choices=sorted(ROBOT_SOLVERS),
        default=["converged", "fast"],
        help="how the stand-in robot is solved: to convergence, or as the package's own (fast) physics",
    )
    parser.add_argument("--cases", nargs="*", default=None, help="case names (default: the whole grid)")
    parser.add_argument("--shard", default="0/1", help="i/n: run every n-th case starting at i")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--summary-only", action="store_true", help="only rebuild the summary from finished cases")
    parser.add_argument(
        "--oracle",
        action="store_true",
        help="instead of the workflow, the held-out gap the true simulator leaves per case "
        "(<out>/oracle/, oracle.md): how much any correction can explain on these data",
    )
    parser.add_argument(
        "--reuse",
        nargs=2,
        action="append",
        default=[],
        metavar=("WHEN", "DIR"),
        help=f"take the cases a version's change cannot reach from an earlier run's DIR/cases; WHEN: "
        f"{' or '.join(REUSABLE)} (see REUSABLE); repeat to try several runs in order; each reused row keeps "
        "its version in `reused_version`",
    )
    return parser


def main() -> None:
    parser = _parser()
    args = parser.parse_args()
    for when, _ in args.reuse:
        if when not in REUSABLE:
            parser.error(f"--reuse: unknown WHEN {when!r} (one of: {', '.join(REUSABLE)})")
    unknown = sorted(set(args.cases or []) - {c.name for c in grid()})
    if unknown:
        parser.error(f"unknown case(s): {', '.join(unknown)}")
    cases = [c for c in grid() if args.cases is None or c.name in args.cases]
    jobs = shard_jobs(cases, args.robots, args.sources, args.shard)
    if args.oracle:
        return run_oracle([(c, s) for c, s, r in jobs if (c.truth or c.per_joint) and r == "converged"], args)
    folder = args.out / "cases"
    folder.mkdir(parents=True, exist_ok=True)
    if not args.summary_only:
        run_jobs(jobs, folder, args)
    rows = [json.loads(p.read_text()) for p in sorted(folder.glob("*.json"))]
    rows = [
        r
        for r in rows
        if (r["case"] in CASES and r.get("settings") == settings(args, CASES[r["case"]])) or "error" in r
    ]
    summary = summarise(rows)
    write_json(
        args.out / "summary.json",
        {
            "summary": summary,
            "fast_vs_converged": fast_vs_converged(rows),
            "cases_finished": len(rows),
            "cases_in_grid": len(grid()) * len(args.sources) * len(args.robots),
            "rows": rows,
        },
    )
    write_text(args.out / "gap_table.md", markdown(rows, summary))
    write_text(args.out / "gap_table_side_by_side.md", side_by_side(rows))
    if rows:
        plot(rows, args.out / "gap_table.png")
    print(markdown(rows, summary))


if __name__ == "__main__":
    main()

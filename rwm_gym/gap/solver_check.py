"""Which solver the gap workflow re-simulates with: the sim env's own, or a converged solve.

The workflow judges the simulator as the user runs it, so it re-simulates with the sim env's own solver settings
(ANYmal D: 4 warm-started iterations, fast for PPO). Data from that same fast physics are reproduced exactly only so.
A real robot's physics is no unfinished solve, though, and on its data the fast solver does harm beyond its own small
gap: each step's solve stops after a few iterations, so a re-simulated window is a rough function of the parameters
(least squares stalls in a narrow valley, which `fit.first_along_bracket` searches first) and of the noisy start
state (the noise floor rises). So the first selection step is fitted under both solvers (`fit.fit_all` and the
scoped forms of the best joint effects, the same windows), and the converged solve is taken where the best candidate
under it leaves a held-out gap `MATERIAL` below the best under the sim's own, at p < `SIGNIFICANCE`
(`significance.paired_p_value`). The report says which was taken and why; the corrected robot then carries the
converged settings (`PhysicsParams.solver`). The fits under the solver taken are handed on (`fit.FitMemo`):
selection's first step takes them rather than fitting them again, so the check costs one first step, under the
other solver.

The global forms are fitted first under both solvers, and the scoped forms only where those leave the choice open.
Where the converged solve's best global effect leaves no less than the own solver's, the own solver is kept without
the converged solve's scoped forms; where it leaves `MATERIAL` less at p < `SIGNIFICANCE` and a global effect lowers
the gap under the own solver by `MATERIAL` too, the converged solve is taken without the own solver's scoped forms.
Either way the forms not fitted are those of the solver given up, whose step would be thrown away (a quarter of a
16 x 250 excitation case). Where no global effect lowers the own solver's gap by that much, the full check runs: its
scoped forms may explain what the globals cannot (below; with friction in the knees a payload lowered it by 0.4 %).

Where several effects are named, one effect fitted alone under each solver can understate what the converged
solve gives: with a weak motor, joint friction and encoder offsets on a converged robot's excitation data, the best
single effect under it is 17 % below the own solver's (short of `MATERIAL`), but the three named effects refitted
together under it leave 31 % less than under the own. So after a selection under the sim's own solver, the named
effects are refitted together under the converged solve (`recheck_with_named`), and the same test on that decides
whether the selection runs again under it (from the converged first step the check already fitted). Where the
selection under the converged solve then leaves `MATERIAL` more than the named effects refitted there, it lost them,
and the selection under the sim env's own solver stands (`lost_in_reselection`).

Before the check gives up the sim env's own solver, that solver gets the search its own selection makes before it
calls a gap `unexplained`: where no single effect and no scoped form of the best joint effects lowers the held-out
gap under it, every joint effect is fitted in its scopes (`scope.every_scope`). Friction of 4 N·m in the knees, on
walking data of the package's own fast physics: under its solver global friction halves the fitting cost but raises
the held-out gap (0.0241 against 0.0191), so no joint effect was scoped and the converged solve's best (PD gains,
0.0126) won; per joint type, friction leaves 0.0037 under the own solver (0.64 / 0.37 / 3.88 N·m in the hip
abduction, hip flexion and knee joints). A scoped form of this search counts only where it explains more than its
parameters are charged, at p < 0.01: with a base-velocity bias at 0.5x on the same robot's walking data, backlash per
leg fitted to noise lowered the own solver's gap by 17 %, enough to keep that solver, under which the bias is not
seen. The converged solve gets no such search: the check asks whether the simulator as the user runs it can be kept.

The scoped forms are part of the check because an effect held by a few joints is misfit in its global form under
either solver, so the global forms alone cannot tell the solvers apart; per group, the fast solve's rough cost leaks
the effect into the other groups (friction of 6 N·m in one leg: 1.3-1.9 N·m fitted in the others, and the per-leg
form then loses to the global one), where the converged solve fits it (5.8, the others below 0.5).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from rwm_gym.gap.effects import vocabulary
from rwm_gym.gap.fit import FitConfig, FitInputs, FitMemo, fit_all, fit_effect, gap_per_window, memo_for
from rwm_gym.gap.refit import Candidate, combine
from rwm_gym.gap.resim import Resimulator, SimulationDiverged, Windows
from rwm_gym.gap.scope import every_scope, scope_candidates
from rwm_gym.gap.significance import paired_p_value
from rwm_gym.physics.params import CONES, CONVERGED_SOLVER, PhysicsParams, SolverSettings

MATERIAL = 0.2
"""The converged solve is taken where its best held-out gap is at least this fraction below the sim's own best."""

SIGNIFICANCE = 0.05
"""p-value under which the converged solve's lower held-out gap counts (`significance.paired_p_value`). Looser
than naming an effect (`FitConfig.significance`): the check chooses between two simulators of the same parameters,
not whether something is there, and with two held-out episodes a per-leg friction fitted to within 3 % under the
converged solve (gap 63 % lower) reached p = 0.014 only."""


@dataclass(frozen=True)
class SolverChoice:
    """The re-simulator the workflow runs with, and the check's account of why."""

    resim: Resimulator
    check: dict
    """The report's account (`solver.check`): "checked", "taken" ("own" or "converged"), "reason", the best single
    effects under each solver and, after `recheck_with_named`, "named_set"."""
    first_step: FitMemo | None
    """Step 1's fits under `resim`'s solver, which selection takes rather than fitting them again (None where the
    check did not run)."""
    converged: tuple[Resimulator, FitMemo] | None = None
    """The converged solve and its step-1 fits, where the check ran and kept the sim env's own solver."""


def converged(solver: SolverSettings) -> SolverSettings:
    """`solver` with each step solved to convergence (`CONVERGED_SOLVER`'s iteration counts; cone and no-slip kept)."""
    return solver.then(CONVERGED_SOLVER)


def is_converged(resim: Resimulator) -> bool:
    """Whether the compiled nominal model already solves each step to convergence."""
    opt = resim.model(PhysicsParams()).opt
    return opt.iterations >= CONVERGED_SOLVER.iterations and opt.ls_iterations >= CONVERGED_SOLVER.ls_iterations


def best_candidate(
    resim: Resimulator,
    train: Windows,
    held: Windows,
    base: PhysicsParams,
    config: FitConfig,
    progress: bool,
    every_scope_if_none: bool = False,
    scoped: bool = True,
    memo: FitMemo | None = None,
) -> tuple[dict, FitMemo]:
    """Step 1 under `resim`'s solver: every effect but `contact_solver` fitted and scored, and (`scoped`) the scoped
    forms of the best joint effects (`scope.scope_candidates`); the best held-out gap {"effect", "scope", "values",
    "gap", "per_window" (W,), "nominal_gap"} (the nominal simulator's where no effect lowers it; "nominal_gap" the
    nominal simulator's either way), and the fits, which the selection's
    first step under this solver takes rather than fitting them again (`fit.FitMemo`; `memo`: one from an earlier
    call on the same windows, whose fits are taken from it).

    `every_scope_if_none`: where none of those lowers the held-out gap, every joint effect is fitted in its scopes too
    (`scope.every_scope`, as the selection does before it calls a gap `unexplained`); such a form counts where it
    explains more than its parameters are charged (`CandidateFit.score` > 0) at p < `config.significance`."""
    effects = {n: e for n, e in vocabulary(resim.spec, resim.xml_file, resim.solver).items() if n != "contact_solver"}
    before = gap_per_window(resim.spec, resim.rollout(held, base), held)
    nominal = float(before.mean())
    best = {"effect": "none", "scope": None, "values": [], "gap": nominal, "per_window": before.mean(1)}
    inputs = FitInputs(resim, train, held, base, before, config)
    memo = memo_for(memo, inputs) or FitMemo(inputs)
    fits = fit_all(effects, inputs, progress, memo=memo)
    forms = scope_candidates(fits, effects, inputs, memo) if scoped else []

    def lowest(candidates: list[tuple]) -> tuple | None:
        """The candidate with the lowest held-out gap below the nominal simulator's (the first of equals), or None."""
        lower = [(e, f) for e, f in candidates if f.status == "ok" and f.gap_mean < best["gap"]]
        return min(lower, key=lambda ef: ef[1].gap_mean, default=None)

    candidates = [(effects[f.effect], f) for f in fits] + forms
    found = lowest(candidates)
    if found is None and scoped and every_scope_if_none and config.every_scope:
        done = {f.effect for _, f in forms if f.scope != "global"}
        more = every_scope(fits, done, effects, inputs, memo)
        found = lowest([(e, f) for e, f in more if f.score > 0 and f.p_value < config.significance])
    if found is not None:
        effect, fit = found
        params = effect.physics(fit.values, base)
        best = {"effect": fit.effect, "scope": fit.scope, "values": fit.values, "gap": fit.gap_mean}
        best["per_window"] = gap_per_window(resim.spec, resim.rollout(held, params), held).mean(1)
    return {**best, "nominal_gap": nominal}, memo


def choose_solver(
    resim: Resimulator,
    train: Windows,
    held: Windows,
    base: PhysicsParams,
    config: FitConfig,
    progress: bool = True,
) -> SolverChoice:
    """The re-simulator to run the workflow with: `resim` (the sim env's own solver) or a converged one, where the
    best single effect under it fits the held-out windows materially better (see the module docstring)."""
    if is_converged(resim):
        return SolverChoice(
            resim, {"checked": False, "taken": "own", "reason": "the sim env's own solver is converged"}, None
        )
    other = Resimulator(resim.spec, resim.xml_file, resim.nthread, converged(resim.solver or SolverSettings()))
    own_best, own_memo = best_candidate(resim, train, held, base, config, progress, scoped=False)
    try:
        conv_best, conv_memo = best_candidate(other, train, held, base, config, progress, scoped=False)
        forms = "in their global forms"
        take, p = _converged_better(own_best, conv_best, held, config)
        own_at_a_loss = own_best["gap"] > (1.0 - MATERIAL) * own_best["nominal_gap"]
        decided = (take and not own_at_a_loss) or conv_best["gap"] >= own_best["gap"]
        if not decided:
            forms = "fitted alone"
            own_best, own_memo = best_candidate(
                resim, train, held, base, config, progress, every_scope_if_none=True, memo=own_memo
            )
            conv_best, conv_memo = best_candidate(other, train, held, base, config, progress, memo=conv_memo)
            take, p = _converged_better(own_best, conv_best, held, config)
    except SimulationDiverged as err:
        reason = f"the converged solve blows up ({err.reason})"
        return SolverChoice(resim, {"checked": True, "taken": "own", "reason": reason}, own_memo)
    summary = {
        name: {"best_effect": b["effect"], "scope": b["scope"], "values": b["values"], "held_out_gap": b["gap"]}
        for name, b in (("own", own_best), ("converged", conv_best))
    }
    verb = "reproduces" if take else "does not reproduce"
    reason = (
        f"{forms}, the best effect under a converged solve ({conv_best['effect']}, gap {conv_best['gap']:.4g}) "
        f"{verb} the data materially better than under the sim env's own solver ({own_best['effect']}, gap "
        f"{own_best['gap']:.4g}; needs {MATERIAL:.0%} lower at p<{SIGNIFICANCE:.2g}, p={p:.2g})"
    )
    check = {"checked": True, "taken": "converged" if take else "own", "reason": reason, "p_value": p, **summary}
    if take:
        return SolverChoice(other, check, conv_memo)
    return SolverChoice(resim, check, own_memo, (other, conv_memo))


def _converged_better(own_best: dict, conv_best: dict, held: Windows, config: FitConfig) -> tuple[bool, float]:
    """Whether the best candidate under the converged solve leaves a held-out gap `MATERIAL` below the best under
    the sim env's own at p < `SIGNIFICANCE`, and that p."""
    p = paired_p_value(own_best["per_window"], conv_best["per_window"], held, config.block_rows, SIGNIFICANCE)
    return bool(conv_best["gap"] <= (1.0 - MATERIAL) * own_best["gap"] and p < SIGNIFICANCE), p


def recheck_with_named(
    choice: SolverChoice,
    named: list[Candidate],
    train: Windows,
    held: Windows,
    base: PhysicsParams,
    gap_after: np.ndarray,
    config: FitConfig,
) -> SolverChoice:
    """After a selection under the sim env's own solver: the `named` effects refitted together under the converged
    solve (from their values under the own), scored on the held-out windows against their gap under the own
    (`gap_after`, (W, horizons)). The converged choice, to select again with, where that is `MATERIAL` lower at
    p < `SIGNIFICANCE`; else `choice` as it was. Either way its check records the test ("named_set").

    A named `contact_solver` with more iterations already says the own solver is too coarse for the data: the other
    named effects are refitted under the converged solve, which is taken where it leaves no more than the named set.
    A `contact_solver` of no-slip iterations or the cone alone is no change a converged solve makes: no check."""
    if choice.converged is None or not named:
        return choice
    finer = next(((e, f) for e, f in named if e.name == "contact_solver"), None)
    effects = [(e, f) for e, f in named if e.name != "contact_solver"]
    if finer is not None and round(finer[1].values[0]) <= finer[0].parameters[0].nominal:
        return choice
    other, memo = choice.converged
    own = gap_after.mean(1)
    start = np.concatenate([fit.values for _, fit in effects]) if effects else np.zeros(0)
    values, conv, reason = _refit_under(other, effects, start, train, held, base, config)
    p, take = float("nan"), False
    if conv is not None:
        p, take, reason = _named_set_test(own, conv, effects, finer is not None, held, config)
    named_set = {
        "effects": [e.name for e, _ in named],
        "refitted": [e.name for e, _ in effects],
        "values_own": [float(v) for v in start],
        "values_converged": [float(v) for v in values],
        "held_out_gap_own": float(own.mean()),
        "held_out_gap_converged": float(conv.mean()) if conv is not None else None,
        "p_value": p,
        "taken": "converged" if take else "own",
        "reason": reason,
    }
    check = {**choice.check, "named_set": named_set}
    if not take:
        return replace(choice, check=check)
    check.update(taken="converged", reason=f"{check['reason']}; but {reason}")
    return SolverChoice(other, check, memo)


def _refit_under(
    other: Resimulator,
    effects: list[Candidate],
    start: np.ndarray,
    train: Windows,
    held: Windows,
    base: PhysicsParams,
    config: FitConfig,
) -> tuple[np.ndarray, np.ndarray | None, str]:
    """The `effects` refitted together under `other`'s solver from their values `start`: the values, the held-out
    gap per window under `other` (None where the refit failed or the rollout blew up) and why it is None."""
    values, params = start, base
    if effects:
        combined = combine(effects)
        fit = fit_effect(combined, other, train, base, config, start, None, max_evaluations=2 * config.max_evaluations)
        values, params = fit.values, combined.physics(fit.values, base)
        if fit.status != "ok":
            return values, None, f"the named effects' refit under the converged solve failed ({fit.status})"
    try:
        return values, gap_per_window(other.spec, other.rollout(held, params), held).mean(1), ""
    except SimulationDiverged as err:
        return values, None, f"the named effects blow up under the converged solve ({err.reason})"


def _named_set_test(
    own: np.ndarray, conv: np.ndarray, effects: list[Candidate], finer: bool, held: Windows, config: FitConfig
) -> tuple[float, bool, str]:
    """The test of the named set: p that the converged solve's gap per window `conv` is below the own's `own`,
    whether the converged solve is taken (`MATERIAL` lower at p < `SIGNIFICANCE`; with a `finer` contact solver
    named, no higher), and why."""
    p = paired_p_value(own, conv, held, config.block_rows, SIGNIFICANCE)
    names = ", ".join(e.name for e, _ in effects) or "none"
    if not finer:
        take = conv.mean() <= (1.0 - MATERIAL) * own.mean() and p < SIGNIFICANCE
        than = f"materially better than under the sim env's own solver (gap {own.mean():.4g}; needs {MATERIAL:.0%}"
        than += f" lower at p<{SIGNIFICANCE:.2g}, p={p:.2g})"
    else:
        take = conv.mean() <= own.mean()
        than = f"as well as with the finer contact solver named (gap {own.mean():.4g})"
    verb = "reproduce" if take else "do not reproduce"
    reason = f"refitted together under a converged solve, the named effects ({names}; gap {conv.mean():.4g}) "
    reason += f"{verb} the data {than}"
    return p, bool(take), reason


def lost_in_reselection(check: dict, gap_after: np.ndarray) -> dict:
    """After `recheck_with_named` took the converged solve and the selection ran again under it: `check` with the
    sim env's own solver kept where that selection's held-out gap (`gap_after`) is `MATERIAL` above what the named
    effects refitted under the converged solve left (it lost them: an effect in some joints whose global form
    explains nothing is not scoped where another effect can be named), else as it was. Either way it records the
    test ("reselection")."""
    named = check["named_set"]["held_out_gap_converged"]
    again = float(gap_after.mean())
    lost = (1.0 - MATERIAL) * again > named
    verb = "leaves materially more than" if lost else "leaves no materially more than"
    reason = (
        f"selected again under the converged solve, the effects named there (gap {again:.4g}) {verb} the named "
        f"effects refitted under it (gap {named:.4g})"
    )
    record = {"held_out_gap": again, "kept": "own" if lost else "converged", "reason": reason}
    if not lost:
        return {**check, "reselection": record}
    reason = f"{check['reason']}; {reason}, so it is not taken"
    return {**check, "reselection": record, "taken": "own", "reason": reason}


def named_only_under_converged(
    check: dict,
    own_gap: np.ndarray,
    named: list[Candidate],
    converged_gap: np.ndarray,
    held: Windows,
    config: FitConfig,
) -> dict:
    """After a selection under the sim env's own solver that named nothing though its gap lies above the floor
    (`own_gap`, (W, horizons)), and a selection under the converged solve that named `named` and left `converged_gap`:
    `check` with the converged solve taken where it named something and leaves `MATERIAL` less at p <
    `SIGNIFICANCE`, and the test recorded either way ("unexplained_under_own"). On a slippery floor the own solver's
    few iterations let a walking robot's feet slide wherever friction is lowered, so no fit lowers it there, while a
    converged solve follows the slide (delay, payload and ground friction on a converged robot's walking data)."""
    own, conv = own_gap.mean(1), converged_gap.mean(1)
    p = paired_p_value(own, conv, held, config.block_rows, SIGNIFICANCE)
    take = bool(named) and conv.mean() <= (1.0 - MATERIAL) * own.mean() and p < SIGNIFICANCE
    names = ", ".join(e.name for e, _ in named) or "nothing"
    verb = "and leaves" if take else "and does not leave"
    reason = (
        f"the sim env's own solver names nothing; selected under a converged solve, {names} is named {verb} the data "
        f"materially closer (gap {conv.mean():.4g} against {own.mean():.4g}; needs {MATERIAL:.0%} lower at "
        f"p<{SIGNIFICANCE:.2g}, p={p:.2g})"
    )
    record = {
        "named": [e.name for e, _ in named],
        "held_out_gap_converged": float(conv.mean()),
        "held_out_gap_own": float(own.mean()),
        "p_value": p,
        "taken": "converged" if take else "own",
        "reason": reason,
    }
    out = {**check, "unexplained_under_own": record}
    if take:
        out.update(taken="converged", reason=f"{check['reason']}; but {reason}")
    return out


def solver_settings(resim: Resimulator) -> dict:
    """The solver `resim` runs with, as its compiled nominal model holds it."""
    opt = resim.model(PhysicsParams()).opt
    cone = next(name for name, value in CONES.items() if value == opt.cone)
    return {
        "iterations": int(opt.iterations),
        "ls_iterations": int(opt.ls_iterations),
        "noslip_iterations": int(opt.noslip_iterations),
        "cone": cone,
    }


def corrected_solver(resim: Resimulator, check: dict) -> SolverSettings | None:
    """The solver settings the corrected robot carries (`PhysicsParams.solver`) for the re-simulator the check
    returned: the converged ones where it took them, else None (the sim env's own)."""
    return resim.solver if check["taken"] == "converged" else None

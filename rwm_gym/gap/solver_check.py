"""Which solver the gap workflow re-simulates with: the sim env's own, or a converged solve.

The workflow judges the simulator as the user runs it, so it re-simulates with the sim env's own solver settings
(ANYmal D: 4 warm-started iterations, fast for PPO). Data from that same fast physics are reproduced exactly only so.
A real robot's physics is no unfinished solve, though, and on its data the fast solver does harm beyond its own small
gap: each step's solve stops after a few iterations, so a re-simulated window is a rough function of the parameters
(least squares stalls in a narrow valley, which `fit.first_along_bracket` searches first) and of the noisy start
state (the noise floor rises). So the first selection step is fitted under both solvers (`fit.fit_all` and the
scoped forms of the best joint effects, the same windows), and the converged solve is taken where the best candidate
under it leaves a held-out gap `MATERIAL` below the best under the sim's own, at p < `SIGNIFICANCE`
(`fit.paired_p_value` on block means). The report says which was taken and why; the corrected robot then carries the
converged settings (`PhysicsParams.solver`). The fits under the solver taken are handed on (`fit.FitMemo`):
selection's first step takes them rather than fitting them again, so the check costs one first step, under the
other solver.

The scoped forms are part of the check because an effect held by a few joints is misfit in its global form under
either solver, so the global forms alone cannot tell the solvers apart; per group, the fast solve's rough cost leaks
the effect into the other groups (friction of 6 N·m in one leg: 1.3-1.9 N·m fitted in the others, and the per-leg
form then loses to the global one), where the converged solve fits it (5.8, the others below 0.5).
"""

from __future__ import annotations

from rwm_gym.gap.effects import vocabulary
from rwm_gym.gap.fit import FitConfig, FitInputs, FitMemo, fit_all, gap_per_window, paired_p_value
from rwm_gym.gap.resim import Resimulator, SimulationDiverged, Windows
from rwm_gym.gap.scope import scope_candidates
from rwm_gym.physics.params import CONES, CONVERGED_SOLVER, PhysicsParams, SolverSettings

MATERIAL = 0.2
"""The converged solve is taken where its best held-out gap is at least this fraction below the sim's own best."""

SIGNIFICANCE = 0.05
"""p-value under which the converged solve's lower held-out gap counts (`fit.paired_p_value` on block means). Looser
than naming an effect (`FitConfig.significance`): the check chooses between two simulators of the same parameters,
not whether something is there, and with two held-out episodes a per-leg friction fitted to within 3 % under the
converged solve (gap 63 % lower) reached p = 0.014 only."""


def converged(solver: SolverSettings) -> SolverSettings:
    """`solver` with each step solved to convergence (`CONVERGED_SOLVER`'s iteration counts; cone and no-slip kept)."""
    return solver.then(CONVERGED_SOLVER)


def is_converged(resim: Resimulator) -> bool:
    """Whether the compiled nominal model already solves each step to convergence."""
    opt = resim.model(PhysicsParams()).opt
    return opt.iterations >= CONVERGED_SOLVER.iterations and opt.ls_iterations >= CONVERGED_SOLVER.ls_iterations


def best_candidate(
    resim: Resimulator, train: Windows, held: Windows, base: PhysicsParams, config: FitConfig, progress: bool
) -> tuple[dict, FitMemo]:
    """Step 1 under `resim`'s solver: every effect but `contact_solver` fitted and scored, and the scoped forms of
    the best joint effects (`scope.scope_candidates`); the best held-out gap {"effect", "scope", "values", "gap",
    "per_window" (W,)} (the nominal simulator's where no effect lowers it), and the fits, which the selection's first
    step under this solver takes rather than fitting them again (`fit.FitMemo`)."""
    effects = {n: e for n, e in vocabulary(resim.spec, resim.xml_file, resim.solver).items() if n != "contact_solver"}
    before = gap_per_window(resim.spec, resim.rollout(held, base), held)
    best = {"effect": "none", "scope": None, "values": [], "gap": float(before.mean()), "per_window": before.mean(1)}
    inputs = FitInputs(resim, train, held, base, before, config)
    memo = FitMemo(inputs)
    fits = fit_all(effects, inputs, progress, memo=memo)
    scoped = scope_candidates(fits, effects, inputs, memo)
    chosen = None
    for effect, fit in [(effects[f.effect], f) for f in fits] + scoped:
        if fit.status == "ok" and fit.gap_mean < best["gap"]:
            best = {"effect": fit.effect, "scope": fit.scope, "values": fit.values, "gap": fit.gap_mean}
            chosen = effect
    if chosen is not None:
        params = chosen.physics(best["values"], base)
        best["per_window"] = gap_per_window(resim.spec, resim.rollout(held, params), held).mean(1)
    return best, memo


def choose_solver(
    resim: Resimulator,
    train: Windows,
    held: Windows,
    base: PhysicsParams,
    config: FitConfig,
    progress: bool = True,
) -> tuple[Resimulator, dict, FitMemo | None]:
    """The re-simulator to run the workflow with (`resim`, the sim env's own solver, or a converged one), the
    report's account of the check (see the module docstring) and the first step's fits under it (`fit.FitMemo`, for
    `select.select_effects`; None where the check did not run)."""
    if is_converged(resim):
        return resim, {"checked": False, "taken": "own", "reason": "the sim env's own solver is converged"}, None
    other = Resimulator(resim.spec, resim.xml_file, resim.nthread, converged(resim.solver or SolverSettings()))
    own_best, own_memo = best_candidate(resim, train, held, base, config, progress)
    try:
        conv_best, conv_memo = best_candidate(other, train, held, base, config, progress)
    except SimulationDiverged as err:
        reason = f"the converged solve blows up ({err.reason})"
        return resim, {"checked": True, "taken": "own", "reason": reason}, own_memo
    p = paired_p_value(own_best["per_window"], conv_best["per_window"], held, config.block_rows, SIGNIFICANCE)
    take = conv_best["gap"] <= (1.0 - MATERIAL) * own_best["gap"] and p < SIGNIFICANCE
    summary = {
        name: {"best_effect": b["effect"], "scope": b["scope"], "values": b["values"], "held_out_gap": b["gap"]}
        for name, b in (("own", own_best), ("converged", conv_best))
    }
    verb = "reproduces" if take else "does not reproduce"
    reason = (
        f"fitted alone, the best effect under a converged solve ({conv_best['effect']}, gap {conv_best['gap']:.4g}) "
        f"{verb} the data materially better than under the sim env's own solver ({own_best['effect']}, gap "
        f"{own_best['gap']:.4g}; needs {MATERIAL:.0%} lower at p<{SIGNIFICANCE:.2g}, p={p:.2g})"
    )
    check = {"checked": True, "taken": "converged" if take else "own", "reason": reason, "p_value": p, **summary}
    return (other, check, conv_memo) if take else (resim, check, own_memo)


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

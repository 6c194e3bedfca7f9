"""Fit each candidate effect to measured windows, score it on held-out episodes, and name the one that explains the gap.

Fitting (training episodes): the residual vector is the normalised state error of re-simulated windows over the first
`fit_horizon` steps. Every effect is screened on a coarse grid of its first parameter; the `refine_top` best are
refined: one-parameter effects by a bounded Brent search (`scipy.optimize.minimize_scalar`), discrete ones (delay, the
solver's iteration counts and cone) on their steps, other multi-parameter ones by a Brent search of the first parameter
within its screening bracket and then `scipy.optimize.least_squares`, from that point and from the screened one if the
search moved it (the cheaper end is kept: on a cost with two valleys either start can land in the worse). A sensor
bias that shifts every window alike (`Effect.fit_on_mean`) is fitted by least squares on the windows' mean residual.
Uncertainty: 1-sigma from the Jacobian at the optimum (`mujoco.sysid.calculate_intervals`).

Scoring (held-out episodes, never fitted): the gap is the mean over `GAP_HORIZONS` of the normalised state MSE at that
step; the explained fraction is 1 - gap_after / gap_before; the score charges `penalty_per_parameter` per extra
parameter: score = 1 - (gap_after / gap_before) x (1 + penalty x extra parameters). Significance: one-sided Wilcoxon
signed-rank test on per-block (`block_rows` rows of an episode) mean error reductions, or where there are too few blocks
for it, a t-test on the blocks' log error ratios (`paired_p_value`).

Blow-ups: parameters at which MuJoCo's integration diverges (`resim.SimulationDiverged`) are rejected, never silently:
the grid point or search step costs infinity, and the candidate's `rejected` lists each rejected point with MuJoCo's
reason; a candidate whose fitted values blow up on held-out windows is itself rejected (score -inf).

Which candidates are named, and in which order, is `rwm_gym.gap.select`'s call.
"""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Callable, Hashable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from mujoco import sysid
from scipy import optimize
from tqdm import tqdm

from rwm_gym.gap.effects import Effect
from rwm_gym.gap.resim import Resimulator, SimulationDiverged, Windows, normalised_residual
from rwm_gym.gap.significance import paired_p_value
from rwm_gym.options import check_ranges, option
from rwm_gym.physics.params import PhysicsParams

GAP_HORIZONS: tuple[int, ...] = (1, 5, 25)
"""Steps ahead (policy steps) at which the gap is measured."""


def gap_horizons(horizon: int) -> tuple[int, ...]:
    """The steps at which windows of `horizon` steps are scored: `GAP_HORIZONS`, cut at the windows' horizon where
    the episodes are too short for the last (a robot that falls within a second), with the horizon itself last."""
    if horizon >= GAP_HORIZONS[-1]:
        return GAP_HORIZONS
    return (*tuple(h for h in GAP_HORIZONS if h < horizon), horizon)


@dataclass(frozen=True)
class FitConfig:
    """How candidates are fitted and judged."""

    fit_horizon: int = option(5, ge=1)
    """Steps of each training window in the fit objective."""
    grid_fractions: tuple[float, ...] = (0.12, 0.35, 1.0)
    """Screening grid of the first parameter: these fractions of the way from nominal to each bound."""
    screen_stride: int = option(1, ge=1)
    """The coarse grid is screened on every this-many-th fitting window (1: all). It ranks the effects and brackets
    their refinement, which runs on every window. At 2 (10 % faster on 16 x 250 steps), friction and a payload on a
    converged robot's excitation data came out with a third, false effect named beside them (PD gains)."""
    max_evaluations: int = option(12, ge=1)
    """Cap on re-simulations of the local search."""
    penalty_per_parameter: float = option(0.1, ge=0)
    """Each parameter beyond the first inflates the remaining gap by this fraction in the score."""
    significance: float = option(0.01, gt=0, lt=1)
    """p-value under which a reduction of the held-out gap is significant."""
    ambiguity_ratio: float = option(0.25, ge=0)
    """A different effect whose penalised remaining gap above the noise floor is within this factor of the best's makes
    it `unexplained`."""
    rival_excess_explained: float = option(0.15, ge=0, le=1)
    """... if that effect itself explains at least this share of the gap above the floor: one that explains nothing is
    no rival, even where the penalty for the best's parameters leaves the two penalised gaps alike."""
    block_rows: int = option(25, ge=1)
    """Rows of an episode pooled into one sample of the significance test."""
    refine_top: int = option(3, ge=0)
    """Effects (best on the coarse grid) whose parameters are refined; the rest keep their best grid point."""
    max_effects: int = option(3, ge=1)
    """Forward selection names at most this many effects."""
    min_excess_explained: float = option(0.3, ge=0, le=1)
    """Share of the gap still above the noise floor that an effect must explain to be named."""
    scopes: tuple[str, ...] = ("leg", "joint_type", "joint")
    """Joint-group scopes tried for the best joint effects of each selection step (`gap.scope`): leg, joint_type
    and/or joint, each kept only if held-out data pays (none: the global forms only; on the command line,
    comma-separated)."""
    group_sweeps: int = option(2, ge=1)
    """Sweeps of the coordinate-wise fit of a per-leg or per-joint-type form. One costs half as much, but the groups
    fitted first soak up part of an effect held by a later group (knee friction), which a second sweep gives back."""
    scoped_effects: int = option(2, ge=0)
    """How many joint effects (best global fit first) are also fitted in their scopes: an effect held by a few
    joints may explain little in its global form and rank below another joint effect that mimics it there."""
    every_scope: bool = True
    """Where step 1 would call the gap `unexplained`, first fit every joint effect in its scopes, also those whose
    global form explains nothing (`scope.every_scope`): an effect in one joint type alone can look like that."""
    refine_every_effect: bool = True
    """Where step 1 would call the gap `unexplained`, first refine every effect, not only the `refine_top` best
    screened: a second effect can rank low on the coarse grid only because no grid point is near its value."""
    refit_single_effect: bool = True
    """Refit a lone named effect of several parameters (a scoped form, the payload) by least squares from its values,
    kept if the held-out gap does not grow, as a set of named effects is: the coordinate-wise fit of a per-group form
    can
    leave part of the effect in the wrong groups."""
    near_the_floor_after_naming: bool = True
    """A step after the first whose gap is not significantly above its floor on the held-out episodes tests it again
    on every episode; where it is above the floor there, the step fits the candidates and tests each one's own
    reduction, as step 1 does near the floor (Bonferroni, the best cross-fitted on every episode): the held-out third
    has few blocks, and a third effect of a triple in 9 walking episodes left 3x its floor at p = 0.017. Off: such a
    step stops selection without fitting."""
    joint_candidates: int = option(2, ge=0)
    """At selection steps after the first, the best candidates of the step (this many) and of the step before are
    also fitted together with the effects named before them: a first effect fitted alone may soak up part of a second
    (armature can absorb an action delay on walking data), and on top of it, frozen, the second then
    explains nothing. 0: off."""
    pair_candidates: int = option(3, ge=0)
    """Where a step with its gap above the noise floor names nothing, the best this many unrelated effects are fitted
    together in pairs, and a pair whose every effect adds to the other is named (`gap.pairs`; 0: off)."""
    stepwise_sets: bool = True
    """Where such a step names no pair either, build a set step by step (the best effect on top of the set at each)
    and name it where every effect adds to the others (`gap.sets`; off: the step names nothing)."""
    drop_idle: bool = True
    """Of several named effects, drop one that adds nothing at the final values (`select.drop_idle`)."""
    look_ahead: bool = True
    """Where a step's best candidate and an unrelated rival explain the gap alike and neither holds the other, name
    each in turn, follow selection to its end, and take the branch that leaves clearly less (`search._look_ahead`).
    Off: such a step names nothing (`unexplained` at step 1)."""
    spread_check: bool = True
    """Where step 1 would call a gap above the floor `unexplained`, ask each effect at which value its simulator's
    own noise spread covers the data, and name one that does on held-out data and removes the nominal simulator's
    systematic misfit (`gap.spread`): a slippery floor under a coarse contact solver turns start noise into another
    slide, and least squares never moves towards it."""
    spread_points: int = option(9, ge=2)
    """Values of each effect's first parameter across its range in that search."""
    spread_bisections: int = option(4, ge=0)
    """Bisections between the covering value of least spread and its neighbour that does not cover."""

    def __post_init__(self) -> None:
        check_ranges(self)


@dataclass
class CandidateFit:
    """One fitted effect and how it does on held-out data."""

    effect: str
    names: list[str]
    units: list[str]
    values: list[float]
    uncertainty: list[float]
    """1-sigma, same units."""
    train_cost: float
    gap: dict[int, float] = field(default_factory=dict)
    """Held-out normalised MSE at each horizon."""
    gap_mean: float = float("nan")
    explained_fraction: float = float("nan")
    excess_explained: float = float("nan")
    """Share of the gap above the noise floor that this candidate removes (set by `select`)."""
    score: float = float("nan")
    p_value: float = 1.0
    cross_fitted_p_value: float = float("nan")
    """Near the noise floor only: the test of the reduction on every measured episode, each scored by a fit that did
    not see it (`cross_fit.cross_fitted_p_value`); when set, it decides instead of `p_value`."""
    scope: str = "global"
    """"global" (one value for all joints), "leg", "joint_type" or "joint" (`rwm_gym.gap.scope`)."""
    rejected: list[str] = field(default_factory=list)
    """Parameter points rejected because the simulation blew up there, each with MuJoCo's reason."""
    status: str = "ok"
    """"ok", or "rejected: <reason>" when the fitted values blow up on held-out windows."""
    named_refit: list[list[float]] | None = None
    """A joint candidate's values for each effect named before it, fitted together with it
    (`FitConfig.joint_candidates`)."""
    spread: dict | None = None
    """Where the effect was named because its own noise spread covers the data (`gap.spread`), that check's record:
    the values are then no least-squares fit, and no refit changes them."""


def gap_per_window(spec, simulated: np.ndarray, windows: Windows) -> np.ndarray:
    """(W, len(gap_horizons(windows.horizon))) normalised MSE over channels at each horizon step, each window's at
    most `windows.gap_ceiling`."""
    res = normalised_residual(spec, simulated, windows.target)
    gap = np.stack([(res[:, h - 1] ** 2).mean(-1) for h in gap_horizons(res.shape[1])], axis=1)
    return gap if windows.gap_ceiling is None else np.minimum(gap, windows.gap_ceiling)


def gap_ceiling(resim: Resimulator, windows: Windows, params: PhysicsParams) -> Windows:
    """`windows` on which no window's gap counts for more than the worst window of the simulator `params` (the
    nominal one) at each horizon. A simulator that misses a window by more than that has lost it (a fall, a contact
    the solver resolves otherwise), and by how much more says nothing of an effect: under the sim env's own solver,
    viscous joint damping at its true 1.5 N·m·s/rad left 89 of 90 walking windows at a median gap of 0.005, and one,
    at a fall, at 54 (the nominal simulator: 1.0 there, 3.6 at most anywhere); that window outweighed the other 89,
    and Coulomb friction (median 0.12, no window above 3) was named in its place."""
    free = dataclasses.replace(windows, gap_ceiling=None)
    nominal = gap_per_window(resim.spec, resim.rollout(free, params), free)
    return dataclasses.replace(windows, gap_ceiling=nominal.max(0))


BLOW_UP_RESIDUAL = 1e3
"""Normalised residual given to every sample at parameters where the simulation blew up (cost 1e6 >> any real one)."""


def _objective(
    effect: Effect, resim: Resimulator, train: Windows, base: PhysicsParams, horizon: int, rejected: list[str]
):
    """Residual vector of `effect` at values; at a blow-up, a huge constant and a line in `rejected`."""
    size = len(train) * horizon * resim.spec.state_dim

    def residual(values: np.ndarray) -> np.ndarray:
        try:
            sim = resim.rollout(train, effect.physics(values, base), horizon=horizon)
        except SimulationDiverged as err:
            point = ", ".join(f"{p.name}={v:.4g}" for p, v in zip(effect.parameters, values))
            rejected.append(f"{point}: {err.reason}")
            return np.full(size, BLOW_UP_RESIDUAL)
        return normalised_residual(resim.spec, sim, train.target[:, :horizon]).ravel()

    return residual


def screen_grid(effect: Effect, fractions: tuple[float, ...]) -> np.ndarray:
    """Sorted grid of the first parameter: the nominal value and `fractions` of the way to each bound."""
    p = effect.parameters[0]
    grid = [p.nominal] + [p.nominal + f * (bound - p.nominal) for bound in (p.low, p.high) for f in fractions]
    grid = np.asarray(grid)
    if p.step > 0:
        grid = np.round(grid / p.step) * p.step
    return np.unique(np.round(grid, 12))


def screen_effect(
    effect: Effect,
    resim: Resimulator,
    train: Windows,
    base: PhysicsParams,
    config: FitConfig,
    nominal_cost: float,
    rejected: list[str],
) -> tuple[np.ndarray, float, tuple[float, float]]:
    """Coarse grid over the effect's first parameter (the others nominal, `nominal_cost` at the nominal point).

    Returns the best values, their training cost and the bracket (the best point's neighbours on the grid); blown-up
    points are appended to `rejected`.
    """
    residual = _objective(effect, resim, train, base, config.fit_horizon, rejected)
    first = effect.parameters[0]
    grid = screen_grid(effect, config.grid_fractions)
    costs = np.array(
        [
            nominal_cost
            if np.isclose(g, first.nominal)
            else float(np.mean(residual(effect.values_from_magnitude(g)) ** 2))
            for g in grid
        ]
    )
    best = int(np.argmin(costs))
    bracket = (float(grid[max(best - 1, 0)]), float(grid[min(best + 1, len(grid) - 1)]))
    return effect.values_from_magnitude(grid[best]), float(costs[best]), bracket


def fit_effect(
    effect: Effect,
    resim: Resimulator,
    train: Windows,
    base: PhysicsParams,
    config: FitConfig,
    start: np.ndarray,
    bracket: tuple[float, float] | None,
    rejected: list[str] | None = None,
    max_evaluations: int | None = None,
) -> CandidateFit:
    """Refine `effect`'s parameters (on top of `base`) from `start`, the first within `bracket` (None: its whole
    range), on training windows."""
    rejected = [] if rejected is None else rejected
    residual = _objective(effect, resim, train, base, config.fit_horizon, rejected)
    budget = max_evaluations or config.max_evaluations

    def cost(values: np.ndarray) -> float:
        return float(np.mean(residual(values) ** 2))

    first = effect.parameters[0]
    lo, hi = (first.low, first.high) if bracket is None else bracket
    values = start.copy()
    lows = np.array([p.low for p in effect.parameters])
    highs = np.array([p.high for p in effect.parameters])
    if effect.fit_on_mean and not any(p.step > 0 for p in effect.parameters):
        values = cheapest_least_squares(
            window_mean(residual, len(train)), [np.clip(start, lows, highs)], lows, highs, budget
        )
    elif first.step > 0 and len(effect.parameters) == 1:
        steps = np.arange(lo, hi + first.step / 2, first.step)
        values = effect.values_from_magnitude(steps[int(np.argmin([cost(np.array([x])) for x in steps]))])
    elif all(p.step > 0 for p in effect.parameters):
        values = discrete_search(effect, cost, start, (lo, hi))
    elif len(effect.parameters) == 1:
        found = optimize.minimize_scalar(
            lambda x: cost(np.array([x])),
            bounds=(lo, hi),
            method="bounded",
            options={"xatol": 5e-3 * min(hi - lo, 0.2 * (first.high - first.low)), "maxiter": budget},
        )
        values = np.array([found.x])
    else:
        screened = np.clip(start, lows, highs)
        along = first_along_bracket(effect, cost, screened, bracket, SCALAR_FIRST_EVALUATIONS)
        starts = [along] if np.array_equal(along, screened) else [along, screened]
        values = cheapest_least_squares(residual, starts, lows, highs, max(budget // 2, 1))
    r_star = residual(values)
    return CandidateFit(
        effect.name,
        [p.name for p in effect.parameters],
        [p.unit for p in effect.parameters],
        [float(v) for v in values],
        _uncertainty(effect, residual, values, r_star),
        float(np.mean(r_star**2)),
        scope=effect.scope,
        rejected=rejected,
    )


def window_mean(residual, windows: int):
    """`residual` (values -> the windows' residuals, flattened) averaged over the `windows` windows: what is common to
    all of them (`Effect.fit_on_mean`)."""

    def mean(values: np.ndarray) -> np.ndarray:
        return residual(values).reshape(windows, -1).mean(0)

    return mean


SCALAR_FIRST_EVALUATIONS = 12
"""Re-simulations of the first parameter's search within its bracket before a multi-parameter least-squares fit."""


def first_along_bracket(
    effect: Effect, cost, start: np.ndarray, bracket: tuple[float, float] | None, evaluations: int
) -> np.ndarray:
    """`start` with its first parameter moved to a bounded Brent minimum within `bracket` (the others held), if that
    costs less. The screened point is only the best of a coarse grid; least squares from it can stall on a rough cost
    whose valley in the first parameter is narrow (a torque-speed limit's slope: 5.3 for a true 7.5, at 13x the true
    point's cost), and a scalar search crosses such a valley where a finite-difference step does not. No bracket (a
    joint refit from fitted values): `start` as it is."""
    if bracket is None or bracket[1] <= bracket[0]:
        return start
    lo, hi = bracket

    def along(x: float) -> float:
        return cost(np.concatenate([[x], start[1:]]))

    first = effect.parameters[0]
    found = optimize.minimize_scalar(
        along,
        bounds=(lo, hi),
        method="bounded",
        options={"xatol": 5e-3 * (first.high - first.low), "maxiter": evaluations},
    )
    return np.concatenate([[found.x], start[1:]]) if found.fun < cost(start) else start


def cheapest_least_squares(
    residual, starts: list[np.ndarray], lows: np.ndarray, highs: np.ndarray, evaluations: int
) -> np.ndarray:
    """The cheapest end of `scipy.optimize.least_squares` run from each of `starts` within the bounds. On a cost with
    two valleys either start can land in the worse one (a base-velocity bias at 1x on walking data: 0.130 m/s from the
    bracket's best point, training cost 0.00219; 0.105 from the screened point, 0.00214; the truth 0.1)."""
    ends = [
        optimize.least_squares(
            residual, x0, bounds=(lows, highs), x_scale=highs - lows, diff_step=1e-2, max_nfev=evaluations
        )
        for x0 in starts
    ]
    return min(ends, key=lambda found: found.cost).x


def discrete_search(effect: Effect, cost, start: np.ndarray, bracket: tuple[float, float]) -> np.ndarray:
    """One sweep over the steps of an effect whose every parameter is discrete (the solver's iteration counts and
    cone): the first within `bracket`, each other over its range, one at a time, the others held at the best so far.
    Least squares would see no slope there."""
    values = np.asarray(start, float).copy()
    for i, p in enumerate(effect.parameters):
        lo, hi = bracket if i == 0 else (p.low, p.high)
        steps = np.unique(np.append(np.arange(lo, hi + p.step / 2, p.step), values[i]))
        trials = [np.concatenate([values[:i], [x], values[i + 1 :]]) for x in steps]
        values = trials[int(np.argmin([cost(t) for t in trials]))]
    return values


def fit_coordinatewise(
    effect: Effect,
    resim: Resimulator,
    train: Windows,
    base: PhysicsParams,
    config: FitConfig,
    start: np.ndarray,
    brackets: list[tuple[float, float]],
    evaluations: int,
    sweeps: int = 2,
) -> CandidateFit:
    """`sweeps` sweeps of bounded Brent searches, one parameter at a time (the others held), each within its bracket
    and `evaluations` re-simulations: robust where least squares stalls on a non-smooth cost (Coulomb friction, dead
    band) with one parameter per joint group."""
    rejected: list[str] = []
    residual = _objective(effect, resim, train, base, config.fit_horizon, rejected)
    values = np.asarray(start, float).copy()
    for i, (lo, hi) in [(i, b) for _ in range(sweeps) for i, b in enumerate(brackets)]:

        def cost(x: float, i: int = i) -> float:
            trial = values.copy()
            trial[i] = x
            return float(np.mean(residual(trial) ** 2))

        p = effect.parameters[i]
        found = optimize.minimize_scalar(
            cost, bounds=(lo, hi), method="bounded", options={"xatol": 5e-3 * (p.high - p.low), "maxiter": evaluations}
        )
        values[i] = found.x
    r_star = residual(values)
    return CandidateFit(
        effect.name,
        [p.name for p in effect.parameters],
        [p.unit for p in effect.parameters],
        [float(v) for v in values],
        _uncertainty(effect, residual, values, r_star),
        float(np.mean(r_star**2)),
        scope=effect.scope,
        rejected=rejected,
    )


def _uncertainty(effect: Effect, residual, values: np.ndarray, r_star: np.ndarray) -> list[float]:
    """1-sigma per parameter from a forward-difference Jacobian at the optimum (discrete: half a step)."""
    jac = np.zeros((len(r_star), len(values)))
    for i, p in enumerate(effect.parameters):
        if p.step > 0:
            continue
        dx = 1e-2 * (p.high - p.low)
        x = values.copy()
        x[i] = x[i] + dx if x[i] + dx <= p.high else x[i] - dx
        jac[:, i] = (residual(x) - r_star) / (x[i] - values[i])
    with np.errstate(invalid="ignore", divide="ignore"):  # an unidentifiable parameter has a zero Jacobian
        sigma, _ = sysid.calculate_intervals([r_star], jac)
    out = np.sqrt(np.abs(np.diag(sigma))) if sigma.size else np.zeros(len(values))
    return [float(p.step / 2) if p.step > 0 else float(s) for p, s in zip(effect.parameters, out)]


def score_fit(
    fit: CandidateFit,
    effect: Effect,
    resim: Resimulator,
    heldout: Windows,
    base: PhysicsParams,
    before: np.ndarray,
    config: FitConfig,
) -> np.ndarray:
    """Fill the held-out gap, explained fraction (of the gap `before` (W, 3)), score and p-value of `fit`; return its
    per-window gap (W, 3), or `before` for a candidate rejected because its values blow up."""
    try:
        after = gap_per_window(resim.spec, resim.rollout(heldout, effect.physics(fit.values, base)), heldout)
    except SimulationDiverged as err:
        fit.status = f"rejected: the simulation blows up on held-out windows at the fitted values ({err.reason})"
        fit.gap, fit.gap_mean, fit.explained_fraction, fit.score, fit.p_value = (
            {},
            float("nan"),
            float("nan"),
            -float("inf"),
            1.0,
        )
        return before
    fit.gap = {h: float(v) for h, v in zip(gap_horizons(heldout.horizon), after.mean(0))}
    fit.gap_mean = float(after.mean())
    fit.explained_fraction = 1.0 - fit.gap_mean / float(before.mean())
    remaining = (fit.gap_mean / float(before.mean())) * (1.0 + config.penalty_per_parameter * (len(fit.values) - 1))
    fit.score = 1.0 - remaining
    fit.p_value = paired_p_value(before.mean(1), after.mean(1), heldout, config.block_rows, config.significance)
    return after


@dataclass(frozen=True)
class FitInputs:
    """What fitting effects on top of one simulator reads: the re-simulator, the windows fitted on (`train`) and scored
    on (`heldout`), the simulator fitted on top of (`base`), its held-out gap per window (`before`, (W,
    len(gap_horizons(heldout.horizon)))) and the fit settings. A fit is deterministic given these."""

    resim: Resimulator
    train: Windows
    heldout: Windows
    base: PhysicsParams
    before: np.ndarray
    config: FitConfig

    @property
    def spec(self):
        return self.resim.spec

    def same_as(self, other: FitInputs) -> bool:
        """Whether fits on `other` are fits on these (the same re-simulator and windows, equal base, gap and config)."""
        return (
            other.resim is self.resim
            and other.train is self.train
            and other.heldout is self.heldout
            and other.base == self.base
            and other.config == self.config
            and np.array_equal(other.before, self.before)
        )


class FitMemo:
    """Fits on top of one simulator, computed once and handed on.

    The solver check (`gap.solver_check`) fits the first selection step under the solver the workflow then runs with,
    on the same windows from the same nominal simulator; `select` takes those fits from here rather than fitting them
    again. Every fit is deterministic given its `FitInputs`, so a memo answers only calls on exactly those (`covers`)
    and a hit is what fitting again would give. Results are stored and handed out as copies: callers change the fits
    they get (shares, scope charges)."""

    def __init__(self, inputs: FitInputs):
        self.inputs = dataclasses.replace(inputs, before=np.array(inputs.before))
        self._store: dict[Hashable, Any] = {}

    def covers(self, inputs: FitInputs) -> bool:
        """Whether fits on these inputs are the memo's."""
        return self.inputs.same_as(inputs)

    def get(self, key: Hashable, compute: Callable[[], Any]) -> Any:
        """A copy of the result stored under `key`, computed (and stored) on the first call."""
        if key not in self._store:
            self._store[key] = copy.deepcopy(compute())
        return copy.deepcopy(self._store[key])


def memo_for(memo: FitMemo | None, inputs: FitInputs) -> FitMemo | None:
    """`memo` where it covers these inputs, else None (fit afresh)."""
    return memo if memo is not None and memo.covers(inputs) else None


def remembered(memo: FitMemo | None, key: Hashable, compute: Callable[[], Any]) -> Any:
    """`compute()`, through `memo` where there is one."""
    return compute() if memo is None else memo.get(key, compute)


def fit_all(
    effects: dict[str, Effect],
    inputs: FitInputs,
    progress: bool = True,
    refine_top: int | None = None,
    memo: FitMemo | None = None,
) -> list[CandidateFit]:
    """Screen every effect (on top of `inputs.base`) on a coarse grid, refine the `refine_top` best (default: the
    config's), score all on the held-out windows against the gap `inputs.before`. `memo`: each effect's screening and
    fit are taken from it where it has them (and stored there), where it covers these inputs (`FitMemo`).

    Returns the fits; unrefined ones sit at their best grid point with uncertainty NaN, their training cost that of
    the screening windows (`FitConfig.screen_stride`).
    """
    resim, train, heldout, base = inputs.resim, inputs.train, inputs.heldout, inputs.base
    before, config = inputs.before, inputs.config
    refine_top = config.refine_top if refine_top is None else refine_top
    memo = memo_for(memo, inputs)
    bar = tqdm(total=2 * len(effects) + refine_top, desc="fit effects", unit="step", disable=not progress)
    h = config.fit_horizon
    screening = train.every(config.screen_stride)
    nominal_cost = remembered(
        memo,
        ("screening nominal cost",),
        lambda: float(
            np.mean(
                normalised_residual(resim.spec, resim.rollout(screening, base, horizon=h), screening.target[:, :h]) ** 2
            )
        ),
    )

    def screen(effect: Effect) -> tuple[np.ndarray, float, tuple[float, float], list[str]]:
        rejected: list[str] = []
        return *screen_effect(effect, resim, screening, base, config, nominal_cost, rejected), rejected

    def finish(effect: Effect, refine: bool) -> CandidateFit:
        start, cost, bracket, rejected = screened[effect.name]
        rejected = list(rejected)
        if refine:
            fit = fit_effect(effect, resim, train, base, config, start, bracket, rejected)
        else:
            fit = CandidateFit(
                effect.name,
                [p.name for p in effect.parameters],
                [p.unit for p in effect.parameters],
                [float(v) for v in start],
                [float("nan")] * len(start),
                cost,
                rejected=rejected,
            )
        score_fit(fit, effect, resim, heldout, base, before, config)
        return fit

    screened = {}
    for name, effect in effects.items():
        screened[name] = remembered(memo, ("screen", name), lambda effect=effect: screen(effect))
        bar.update(1)
    order = sorted(screened, key=lambda n: screened[n][1])
    fits = []
    for name in order:
        refine = len(fits) < refine_top and screened[name][1] < nominal_cost
        fits.append(remembered(memo, ("fit", name, refine), lambda name=name, r=refine: finish(effects[name], r)))
        bar.update(2 if len(fits) <= refine_top else 1)
    bar.close()
    return fits

"""Name the effects behind a gap: forward selection over the vocabulary and its scopes, then a joint refit.

Step k starts from the simulator with the k-1 effects named so far, and tests its held-out gap against that
simulator's own sensor-noise floor (`noise_floor`: a damped joint carries start noise less far than the nominal robot;
the nominal robot started from offset encoder readings carries it further). That test of the whole gap is weak where
an effect shows in a few windows only (a 0.5x torque limit, a small backlash), or where the held-out third holds few
blocks (a triple's third effect in 9 walking episodes: 3x the floor at p = 0.017). So step 1, where its gap is not
significantly above its floor, fits the candidates anyway and asks each one's own held-out reduction, at
`FitConfig.significance` divided by the number of candidates (Bonferroni). The best candidate, if it fails only that
test, is fitted again on the held-out episodes and scored on the fitting ones (2-fold cross-fitting); the test then runs
on every measured episode, each scored by a fit that did not see it. If none passes, the verdict is `none`.

A later step whose gap is not significantly above its floor tests it again on every episode (the fitting ones too,
where the named effects were fitted: a conservative test) and stops where it is not above the floor there either
(at once where `FitConfig.near_the_floor_after_naming` is off); otherwise it judges its candidates as step 1 does near
the floor. Its pick must also leave `min_excess_explained` less above its own simulator's floor than the step's gap
lies above the step's floor: near the floor, a candidate that changes how far sensor noise carries (another contact
solver) lowers the gap by lowering the floor.

At each step every effect not yet named is fitted and scored on top of the named ones (`fit.fit_all`), the best joint
effects also in their scopes (`scope.scope_candidates`), and the best-scoring candidate is named when

- its held-out reduction is significant (`FitConfig.significance`, Wilcoxon on block means),
- it explains `min_excess_explained` of the gap above the step's floor (the floor itself no effect can remove;
  measured against the whole gap, an effect near the floor could never reach it),
- no unrelated candidate (not the same effect in another scope, not nesting it) that itself explains
  `rival_excess_explained` of the gap above the floor leaves a penalised remaining gap within `ambiguity_ratio` of
  the best's.

A rival that stays alike after `resolve_rivals` (neither holds the other) is followed with the best: each is named in
turn and selection runs to its end, and the branch that leaves clearly less is taken (`_look_ahead`,
`FitConfig.look_ahead`); else the step names nothing.

Before step 1 calls a gap above the floor `unexplained`, every effect is refined (not only the best screened,
`FitConfig.refine_every_effect`) and every joint effect is fitted in its scopes too (`scope.every_scope`), also those
whose global form explained nothing; a best candidate that then explains enough but fails only its held-out test is
tested again cross-fitted on every episode (a torque limit 2x on walking data explained 89 % of a gap 300x the floor
at p = 0.034 on the held-out third).

At later steps some candidates are also fitted together with the effects named so far (`joint_candidates`: the best
of this step and of the step before); one that scores better so is judged (and named) with those refitted values.
A significant gap that no candidate explains at step 1 is `unexplained`. From two named effects on, all their
parameters are refitted together after each naming (least squares from the sequential values, kept if the held-out
gap does not grow), so the next step starts from the best simulator with them: fitted one after the other, two effects
that trade off (armature and an action delay) leave a misfit that a third, spurious one would take up. A lone named
effect of several parameters (`FitConfig.refit_single_effect`) is refitted so at the end.
Each named effect's share of the explained gap is its held-out gap reduction when the effects are added in order at
their final values.
"""

from __future__ import annotations

import copy
import itertools
from collections.abc import Callable
from dataclasses import asdict, dataclass, field

import numpy as np

from rwm_gym.gap.effects import Effect
from rwm_gym.gap.fit import (
    CandidateFit,
    FitConfig,
    FitInputs,
    FitMemo,
    fit_all,
    fit_effect,
    gap_per_window,
    paired_p_value,
    score_fit,
)
from rwm_gym.gap.noise_floor import FloorConfig, compare_with_floor
from rwm_gym.gap.resim import Resimulator, SimulationDiverged, Windows, normalised_residual
from rwm_gym.gap.scope import every_scope, scope_candidates
from rwm_gym.gap.spread import SpreadInputs, name_by_spread
from rwm_gym.physics.params import PhysicsParams
from rwm_gym.spec import TaskSpec

Candidate = tuple[Effect, CandidateFit]


@dataclass
class Selection:
    """What forward selection found."""

    verdict: str
    """The first named effect, `unexplained` or `none`."""
    reason: str
    named: list[Candidate]
    """Named effects in order, at their final (jointly refitted) values."""
    params: PhysicsParams
    """The corrected simulator: every named effect on top of the nominal one."""
    gap_after: np.ndarray
    """(W, len(gap_horizons(held.horizon))) held-out gap of `params`."""
    shares: list[float] = field(default_factory=list)
    """Share of the explained gap per named effect."""
    steps: list[dict] = field(default_factory=list)
    """Per step: the floor test of the gap it started from, its candidates and what it decided."""
    joint_refit: dict | None = None
    simpler_forms: list[dict] = field(default_factory=list)
    """Each named effect's test against a simpler one it holds (`prefer_simpler`)."""
    idle_effects: list[dict] = field(default_factory=list)
    """Each named effect's test that it still adds something at the final values (`drop_idle`)."""


def combine(named: list[Candidate]) -> Effect:
    """One effect whose parameters are all of `named`'s, in order (for the joint refit)."""
    sizes = [len(e.parameters) for e, _ in named]
    cuts = np.cumsum([0, *sizes])

    def apply(values: np.ndarray) -> dict[str, object]:
        out: dict[str, object] = {}
        for (effect, _), lo, hi in zip(named, cuts[:-1], cuts[1:]):
            out.update(effect.apply(values[lo:hi]))
        return out

    parameters = tuple(p for e, _ in named for p in e.parameters)
    fit_on_mean = all(e.fit_on_mean for e, _ in named)  # a dynamic effect's residual averages out over windows
    return Effect(
        "+".join(e.name for e, _ in named), "jointly refitted named effects", parameters, apply, fit_on_mean=fit_on_mean
    )


def _related(a: Effect, b: Effect) -> bool:
    return a.name == b.name or a.name in b.nested_in or b.name in a.nested_in


def name_step(
    candidates: list[Candidate], config: FitConfig, significance: float, gap: float, floor: float
) -> tuple[Candidate | None, str, Candidate | None]:
    """The candidate this step names, or None, why, and an unrelated rival that explains the gap alike (then the
    pick is None); `gap` and `floor` are the means of the step's gap and of its noise floor. Alike: the rival explains
    `rival_excess_explained` of the gap above the floor and its
    penalised remaining gap above the floor is within `ambiguity_ratio` of the best's (measured from zero, an effect
    that explains a third of a gap twice the floor had every candidate that explains nothing as its rival)."""
    ranked = sorted((c for c in candidates if c[1].status == "ok"), key=lambda c: c[1].score, reverse=True)
    if not ranked:
        return None, "every candidate blew up the simulation", None
    effect, best = ranked[0]
    share, needed = best.excess_explained, config.min_excess_explained
    crossed = not np.isnan(best.cross_fitted_p_value)
    p_value, test = (best.cross_fitted_p_value, "cross-fitted p") if crossed else (best.p_value, "p")
    if p_value >= significance or not share >= needed:  # NaN share: the gap is not above the floor
        return (
            None,
            (
                f"best candidate {best.effect} ({best.scope}) explains {share:.0%} of the gap above the noise "
                f"floor ({test}={p_value:.2g}; needs {needed:.0%} and p<{significance:.2g})"
            ),
            None,
        )

    def left_above_floor(fit: CandidateFit) -> float:
        return (1.0 - fit.score) * gap - floor

    for other_effect, other in ranked[1:]:
        alike = left_above_floor(other) < left_above_floor(best) * (1.0 + config.ambiguity_ratio)
        explains = other.excess_explained >= config.rival_excess_explained
        if not _related(effect, other_effect) and alike and explains:
            return (
                None,
                (
                    f"ambiguous: {best.effect} ({best.explained_fraction:.0%}) and {other.effect} "
                    f"({other.explained_fraction:.0%}) explain the gap alike"
                ),
                (other_effect, other),
            )
    return ranked[0], f"explains {share:.0%} of the gap above the noise floor ({test}={p_value:.2g})", None


def judge(
    candidates: list[Candidate], gap: float, floor: float, config: FitConfig, significance: float
) -> tuple[Candidate | None, str, Candidate | None]:
    """`name_step` after setting each candidate's share of the gap above the floor (`gap`, `floor`: the means)."""
    excess = gap - floor
    for _, fit in candidates:
        fit.excess_explained = (gap - fit.gap_mean) / excess if excess > 0 else float("nan")
    return name_step(candidates, config, significance, gap, floor)


@dataclass(frozen=True)
class CrossFit:
    """The two roles swapped: windows to fit on from the held-out episodes, and windows to score on (at the held-out
    horizon and stride) from the fitting episodes."""

    fit: Windows
    score: Windows


def cross_fitted_p_value(
    candidate: Candidate,
    resim: Resimulator,
    held: Windows,
    cross: CrossFit,
    params: PhysicsParams,
    before: np.ndarray,
    config: FitConfig,
    significance: float,
    under: PhysicsParams | None = None,
) -> float:
    """One-sided p that `candidate` lowers the gap (`before` (W, 3): held-out, of `params`) on every measured episode:
    the held-out windows at its values, the fitting episodes' windows at its values fitted again on the held-out
    episodes. 2-fold cross-fitting: no window is scored by a fit that saw it, and the test has about three times the
    blocks of the held-out third alone. `under`: the simulator the candidate is added to, where it is not `params`
    (a joint candidate's, with the named effects at the values refitted with it)."""
    effect, fit = candidate
    under = params if under is None else under
    first = effect.parameters[0]
    refit = fit_effect(effect, resim, cross.fit, under, config, np.asarray(fit.values), (first.low, first.high))
    try:
        after = gap_per_window(resim.spec, resim.rollout(held, effect.physics(fit.values, under)), held)
        nominal = gap_per_window(resim.spec, resim.rollout(cross.score, params), cross.score)
        swapped = gap_per_window(
            resim.spec, resim.rollout(cross.score, effect.physics(refit.values, under)), cross.score
        )
    except SimulationDiverged:
        return 1.0
    return paired_p_value(
        np.concatenate([before.mean(1), nominal.mean(1)]),
        np.concatenate([after.mean(1), swapped.mean(1)]),
        held.join(cross.score),
        config.block_rows,
        significance,
    )


def resolve_rivals(
    best: Candidate,
    rival: Candidate,
    resim: Resimulator,
    train: Windows,
    held: Windows,
    params: PhysicsParams,
    current: np.ndarray,
    floor: np.ndarray,
    config: FitConfig,
    cross: Callable[[], CrossFit] | None = None,
) -> tuple[Candidate, str] | None:
    """Two unrelated effects explain the gap alike: both present (a pair), one standing in for part of the other, or
    confusable? Fit the rival on top of the best; if it still explains `min_excess_explained` of the gap above the
    floor, significantly, the best is named (the rival is fitted again at the next step). Else fit the best on top of
    the rival: if the best still explains that much and the rival nothing more on top of it, the best holds all the
    rival explains and more, and it is named. Else None (confusable: `unexplained`). What is left on top of another
    effect is small, so where the held-out third alone is not significant, the test runs again on every episode
    (`cross`: the swapped windows, `cross_fitted_p_value`)."""
    rival_on_best = _explains_on_top(rival, best, resim, train, held, params, floor, config, cross)
    if rival_on_best is not None:
        return best, (
            f"{best[1].effect} and {rival[1].effect} explain the gap alike, and {rival[1].effect} still explains "
            f"{rival_on_best:.0%} of the rest above the floor on top of {best[1].effect}: both are present"
        )
    best_on_rival = _explains_on_top(best, rival, resim, train, held, params, floor, config, cross)
    if best_on_rival is not None:
        return best, (
            f"{best[1].effect} and {rival[1].effect} explain the gap alike, but on top of {rival[1].effect}, "
            f"{best[1].effect} still explains {best_on_rival:.0%} of the rest above the floor, and "
            f"{rival[1].effect} on top of {best[1].effect} too little: {best[1].effect} is named"
        )
    return None


def _explains_on_top(
    candidate: Candidate,
    under: Candidate,
    resim: Resimulator,
    train: Windows,
    held: Windows,
    params: PhysicsParams,
    floor: np.ndarray,
    config: FitConfig,
    cross: Callable[[], CrossFit] | None = None,
) -> float | None:
    """The share of the gap above the floor that `candidate`, refitted on top of `params` with `under` at its values,
    still explains, where it is significant (on the held-out windows, or else cross-fitted on every episode where
    `cross` gives the swapped windows) and at least `min_excess_explained`; else None."""
    effect, fit = candidate
    on_top = under[0].physics(under[1].values, params)
    after = gap_per_window(resim.spec, resim.rollout(held, on_top), held)
    p = effect.parameters[0]
    refit = fit_effect(effect, resim, train, on_top, config, np.asarray(fit.values), (p.low, p.high))
    score_fit(refit, effect, resim, held, on_top, after, config)
    excess = float(after.mean() - np.nanmean(floor))
    share = (float(after.mean()) - refit.gap_mean) / excess if excess > 0 else 0.0
    if refit.status != "ok" or share < config.min_excess_explained:
        return None
    significant = refit.p_value < config.significance or (
        cross is not None
        and cross_fitted_p_value((effect, refit), resim, held, cross(), on_top, after, config, config.significance)
        < config.significance
    )
    return share if significant else None


@dataclass(frozen=True)
class _Search:
    """What every step of the forward selection reads; none of it changes from step to step."""

    effects: dict[str, Effect]
    spec: TaskSpec
    resim: Resimulator
    train: Windows
    held: Windows
    base: PhysicsParams
    floor: np.ndarray
    """The nominal simulator's noise floor (W, 3): step 1's."""
    config: FitConfig
    progress: bool
    cross: Callable[[], CrossFit] | None
    memo: FitMemo | None = None
    """Fits of step 1 already made (by the solver check), taken rather than fitted again."""
    floor_of: Callable[..., np.ndarray] | None = None
    """The noise floor of a simulator on the held-out windows, or on the windows given (None: the nominal floor at
    every step)."""
    floor_config: FloorConfig = FloorConfig()

    def floor_at(self, k: int, params: PhysicsParams) -> np.ndarray:
        """The floor step `k` tests against: that of `params`, the simulator with the effects named so far."""
        return self.floor if k == 0 or self.floor_of is None else self.floor_of(params)

    def on_top_of(self, params: PhysicsParams, current: np.ndarray) -> FitInputs:
        """What a fit on top of the simulator `params` (held-out gap `current`) reads."""
        return FitInputs(self.resim, self.train, self.held, params, current, self.config)

    def first_step(self, k: int) -> dict:
        """`memo=` for the fitting calls of step `k` (k = 0 only, where there is a memo), else nothing."""
        return {"memo": self.memo} if k == 0 and self.memo is not None else {}


@dataclass
class _Step:
    """One step's judged candidates: the pick (or None), why, an unrelated rival that explains the gap alike, and the
    Bonferroni-corrected significance over the `tested` candidates."""

    candidates: list[Candidate]
    fits: list[CandidateFit]
    """The fits of the effects' global forms behind `candidates`."""
    pick: Candidate | None
    decision: str
    rival: Candidate | None
    significance: float
    tested: int
    floor: np.ndarray
    """The noise floor the step judges against (`_Search.floor_at`)."""
    spread: list[dict] | None = None
    """Step 1 about to call its gap `unexplained`: each effect's check of its own noise spread (`gap.spread`)."""


def select_effects(
    effects: dict[str, Effect],
    spec: TaskSpec,
    resim: Resimulator,
    train: Windows,
    held: Windows,
    base: PhysicsParams,
    before: np.ndarray,
    floor: np.ndarray,
    config: FitConfig,
    floor_config: FloorConfig = FloorConfig(),
    progress: bool = True,
    cross: Callable[[], CrossFit] | None = None,
    memo: FitMemo | None = None,
    floor_of: Callable[..., np.ndarray] | None = None,
) -> Selection:
    """Forward selection of effects on top of `base` (see the module docstring); `before` and `floor` (W, 3) are the
    nominal held-out gap and its noise floor per window; `cross`: builds the swapped windows for a gap near the floor,
    called once if step 1's best candidate needs them (None: the held-out test alone); `memo`: step 1's fits where
    they were made already (`fit.FitMemo`; the solver check's under the solver it took); `floor_of`: the noise floor
    of a simulator, for the steps after the first (None: the nominal `floor` at every step)."""
    search = _Search(
        effects, spec, resim, train, held, base, floor, config, progress, cross, memo, floor_of, floor_config
    )
    path = _forward(search, _Path([], base, before, []), config.look_ahead)
    return _selection(search, path.named, path.steps, path.reason, before, path.params, path.current, path.refit)


@dataclass
class _Path:
    """Where a forward selection stands: the named effects, the simulator with them and its held-out gap, the steps
    so far, the last step's candidates (ranked), the last joint refit, and why the last step decided as it did."""

    named: list[Candidate]
    params: PhysicsParams
    current: np.ndarray
    steps: list[dict]
    earlier: list[Candidate] = field(default_factory=list)
    refit: dict | None = None
    reason: str = ""

    def fork(self) -> _Path:
        """A copy that naming and refitting on it leave this one as it is (they change the named fits' values)."""
        named = [(effect, copy.deepcopy(fit)) for effect, fit in self.named]
        steps = [dict(step) for step in self.steps]
        return _Path(named, self.params, self.current, steps, list(self.earlier), self.refit, self.reason)


def _forward(search: _Search, path: _Path, look_ahead: bool) -> _Path:
    """Name effects from `path` on, one per step, until a step names none or `max_effects` are named; where a step's
    best candidate and an unrelated rival stay alike (`resolve_rivals`) and `look_ahead`, follow both
    (`_look_ahead`)."""
    config = search.config
    while len(path.named) < config.max_effects:
        k = len(path.named)
        step_floor = search.floor_at(k, path.params)
        test = compare_with_floor(path.current, step_floor, search.held, config.block_rows, search.floor_config)
        step: dict = {"gap": float(path.current.mean()), "floor_test": test, "candidates": [], "named": None}
        path.steps.append(step)
        below = not test["above_floor"]
        if below:
            path.reason = _below_floor(test, search.floor_config)
            if k > 0:
                wide = _floor_test_on_every_episode(search, path.params, path.current, step_floor)
                step["floor_test_every_episode"] = wide
                if wide is None or not wide["above_floor"]:
                    path.reason += (
                        "" if wide is None else f"; on every episode: {_below_floor(wide, search.floor_config, 'gap')}"
                    )
                    break
        judged = _judge_step(search, k, below, path.named, path.earlier, path.params, path.current, step_floor)
        path.earlier = _ranked(judged.candidates)
        step["candidates"] = [asdict(f) for _, f in sorted(judged.candidates, key=lambda c: c[1].score, reverse=True)]
        pick, path.reason = _decide(search, judged, below, path.reason, path.named, path.params, path.current)
        step["decision"] = path.reason
        if judged.spread is not None:
            step["spread"] = judged.spread
        if pick is None and judged.rival is not None and not below and look_ahead:
            return _look_ahead(search, path, judged)
        if pick is None:
            break
        _take(search, path, pick)
        if pick[1].spread is not None:
            path.reason = "its gap lies at its own noise floor, which no further effect can lower"
            break
    return path


def _take(search: _Search, path: _Path, pick: Candidate) -> None:
    """Name `pick` at `path`'s last step; from two named effects on, refit them together (`joint_refit`)."""
    path.steps[-1]["named"] = f"{pick[0].name} ({pick[0].scope})"
    path.params, path.current = _name(search, pick, path.named, path.params)
    if len(path.named) > 1:
        path.named, path.params, path.current, path.refit = joint_refit(
            path.named, search.resim, search.train, search.held, search.base, path.current, search.config
        )


def _look_ahead(search: _Search, path: _Path, step: _Step) -> _Path:
    """The step's best candidate and an unrelated rival explain the gap alike, and neither holds the other
    (`resolve_rivals`): name each in turn and follow selection to its end (without looking ahead again). The branch
    that leaves less of the gap above the step's floor is taken where the other leaves `ambiguity_ratio` more above
    it, on windows that are significantly worse (`paired_p_value`); else the step names nothing, as before. With
    several effects present, the one that mimics the first may explain as much alone, yet leave a misfit that none
    of the others takes up: armature, joint damping and a compliant floor on excitation data, where joint friction
    explained the gap as well as the damping at step 1 and on top of it the damping explained too little to hold it."""
    config, floor = search.config, float(np.nanmean(step.floor))
    best = _best(step.candidates)
    assert best is not None and step.rival is not None
    branches = []
    for first in (best, step.rival):
        branch = path.fork()
        _take(search, branch, (first[0], copy.deepcopy(first[1])))
        branches.append(_forward(search, branch, look_ahead=False))
    above = [float(b.current.mean()) - floor for b in branches]
    lower = int(np.argmin(above))
    higher = 1 - lower
    p_value = paired_p_value(
        branches[higher].current.mean(1),
        branches[lower].current.mean(1),
        search.held,
        config.block_rows,
        config.significance,
    )
    clear = above[higher] > above[lower] * (1.0 + config.ambiguity_ratio) and p_value < config.significance
    k = len(path.named)
    record = {
        "branches": [
            {"named": [f"{e.name} ({e.scope})" for e, _ in b.named[k:]], "gap": float(b.current.mean()), "above": a}
            for b, a in zip(branches, above)
        ],
        "p_value": p_value,
        "taken": lower if clear else None,
    }
    followed = ", ".join(
        f"naming {b.named[k][0].name} leads to {' + '.join(e.name for e, _ in b.named[k:])}, {a:.3g} above the floor"
        for b, a in zip(branches, above)
    )
    verdict = f"{branches[lower].named[k][0].name} is named" if clear else "still alike"
    decision = f"{path.steps[-1]['decision']}; looking ahead: {followed} (p={p_value:.2g}): {verdict}"
    taken = branches[lower] if clear else path
    taken.steps[len(path.steps) - 1].update(look_ahead=record, decision=decision)
    if not clear:
        path.reason = decision
    return taken


def _floor_test_on_every_episode(
    search: _Search, params: PhysicsParams, current: np.ndarray, floor: np.ndarray
) -> dict | None:
    """A later step's floor test again on every measured episode: the held-out windows (gap `current`, floor
    `floor`) and the fitting episodes' at the held-out horizon (`CrossFit.score`). The named effects were fitted on
    the latter, so their gap there is if anything smaller, and the test conservative. None where it is not made
    (`FitConfig.near_the_floor_after_naming` off, no swapped windows or no floor to ask) or the simulation diverged."""
    if not search.config.near_the_floor_after_naming or search.cross is None or search.floor_of is None:
        return None
    score = search.cross().score
    try:
        gap = gap_per_window(search.spec, search.resim.rollout(score, params), score)
    except SimulationDiverged:
        return None
    return compare_with_floor(
        np.concatenate([current, gap]),
        np.concatenate([floor, search.floor_of(params, score)]),
        search.held.join(score),
        search.config.block_rows,
        search.floor_config,
    )


def _below_floor(test: dict, config: FloorConfig, gap: str = "held-out gap") -> str:
    """Why a gap is not above the noise floor, from `compare_with_floor`'s test: the parts of it that failed."""
    failed = [f"ratio {test['ratio']:.2f} < {config.min_ratio}"] if not test["ratio"] >= config.min_ratio else []
    if not test["p_value"] < config.significance:
        failed.append(f"p={test['p_value']:.2g} >= {config.significance}")
    return f"{gap} {test['gap']:.4g} is not above the sensor-noise floor {test['floor']:.4g} ({'; '.join(failed)})"


def _ranked(candidates: list[Candidate]) -> list[Candidate]:
    """The candidates whose fit is ok, best score first."""
    return sorted((c for c in candidates if c[1].status == "ok"), key=lambda c: c[1].score, reverse=True)


def _best(candidates: list[Candidate]) -> Candidate | None:
    """The best-scoring candidate whose fit is ok, or None."""
    return max((c for c in candidates if c[1].status == "ok"), key=lambda c: c[1].score, default=None)


def _judge_step(
    search: _Search,
    k: int,
    below: bool,
    named: list[Candidate],
    earlier: list[Candidate],
    params: PhysicsParams,
    current: np.ndarray,
    floor: np.ndarray,
) -> _Step:
    """Fit every effect not yet named on top of `params` (and in its scopes, and jointly with the named ones), and
    judge the candidates; at step 1 (k = 0), where none is named and no rival found, look harder before giving up."""
    config = search.config
    remaining = {n: e for n, e in search.effects.items() if n not in {e.name for e, _ in named}}
    inputs = search.on_top_of(params, current)
    fits = fit_all(remaining, inputs, search.progress, **search.first_step(k))
    candidates = [(remaining[f.effect], f) for f in fits]
    candidates += scope_candidates(fits, remaining, inputs, **search.first_step(k))
    if named and config.joint_candidates:
        candidates = joint_candidates(
            candidates, named, earlier, search.resim, search.train, search.held, search.base, current, config
        )
    tested = sum(f.status == "ok" for _, f in candidates)
    significance = config.significance / max(tested, 1) if below else config.significance
    step = _Step(
        candidates, fits, *_judge(search, candidates, current, significance, floor), significance, tested, floor
    )
    if below:
        _cross_fit_the_best(search, step, named, params, current)
        if named:
            _against_its_own_floor(search, step, named, params, current)
    elif k == 0:
        _refine_every_effect(search, step, remaining, params, current)
        _fit_every_scope(search, step, remaining, params, current)
        _cross_fit_the_best(search, step, named, params, current)
        _by_spread(search, step, remaining, params, current)
    return step


def _judge(
    search: _Search, candidates: list[Candidate], current: np.ndarray, significance: float, floor: np.ndarray
) -> tuple[Candidate | None, str, Candidate | None]:
    """`judge` on the step's gap `current` and the mean of its noise floor."""
    return judge(candidates, float(current.mean()), float(np.nanmean(floor)), search.config, significance)


def _undecided(step: _Step) -> bool:
    return step.pick is None and step.rival is None


def _cross_fit_the_best(
    search: _Search, step: _Step, named: list[Candidate], params: PhysicsParams, current: np.ndarray
) -> None:
    """Nothing named at this step (a gap near the floor, or step 1 about to call one above it `unexplained`): if the
    best candidate explains enough of the gap, test it again on every measured episode (`cross_fitted_p_value`), and
    judge again."""
    if not _undecided(step) or search.cross is None:
        return
    best = _best(step.candidates)
    if best is not None and best[1].excess_explained >= search.config.min_excess_explained:
        under = named_params(named, best, search.base, params)
        best[1].cross_fitted_p_value = cross_fitted_p_value(
            best, search.resim, search.held, search.cross(), params, current, search.config, step.significance, under
        )
        step.pick, step.decision, step.rival = _judge(search, step.candidates, current, step.significance, step.floor)


def _against_its_own_floor(
    search: _Search, step: _Step, named: list[Candidate], params: PhysicsParams, current: np.ndarray
) -> None:
    """A later step near its floor: the pick must leave `min_excess_explained` less above its own simulator's noise
    floor than the step's gap lies above the step's floor. Near the floor, a candidate that changes how far sensor
    noise carries (another contact solver, more damping) lowers the gap by lowering the floor, not by explaining
    anything: after joint friction and a payload on excitation data, a contact solver took a gap 1.16x its floor to
    half that floor, and was named. No pick, or no floor to ask (`floor_of`): nothing to check."""
    if step.pick is None or search.floor_of is None:
        return
    effect, fit = step.pick
    own = float(
        np.nanmean(search.floor_of(effect.physics(fit.values, named_params(named, step.pick, search.base, params))))
    )
    excess = float(current.mean()) - float(np.nanmean(step.floor))
    share = 1.0 - (fit.gap_mean - own) / excess if excess > 0 else float("nan")
    if not share >= search.config.min_excess_explained:
        step.pick, step.decision = (
            None,
            (
                f"best candidate {fit.effect} ({fit.scope}) leaves {fit.gap_mean:.4g} against its own noise floor "
                f"{own:.4g}: {share:.0%} of the gap above the step's floor explained, measured so (needs "
                f"{search.config.min_excess_explained:.0%}); before that check: {step.decision}"
            ),
        )


def _refine_every_effect(
    search: _Search, step: _Step, remaining: dict[str, Effect], params: PhysicsParams, current: np.ndarray
) -> None:
    """Step 1, gap above the floor, nothing named: refine every effect (not only the best screened), and judge
    again."""
    config = search.config
    if not _undecided(step) or not config.refine_every_effect or len(remaining) <= config.refine_top:
        return
    inputs = search.on_top_of(params, current)
    fits = fit_all(remaining, inputs, search.progress, len(remaining), **search.first_step(0))
    refined = {f.effect: f for f in fits}
    step.candidates = [(e, refined[f.effect]) if f.scope == "global" else (e, f) for e, f in step.candidates]
    step.fits = fits
    step.pick, step.decision, step.rival = _judge(search, step.candidates, current, step.significance, step.floor)


def _fit_every_scope(
    search: _Search, step: _Step, remaining: dict[str, Effect], params: PhysicsParams, current: np.ndarray
) -> None:
    """Step 1, gap above the floor, still nothing named: fit every joint effect in its scopes too (also those whose
    global form explained nothing), and judge again."""
    if not _undecided(step) or not search.config.every_scope:
        return
    scoped = {f.effect for _, f in step.candidates if f.scope != "global"}
    more = every_scope(step.fits, scoped, remaining, search.on_top_of(params, current), **search.first_step(0))
    if more:
        step.candidates += more
        step.pick, step.decision, step.rival = _judge(search, step.candidates, current, step.significance, step.floor)


def _by_spread(
    search: _Search, step: _Step, remaining: dict[str, Effect], params: PhysicsParams, current: np.ndarray
) -> None:
    """Step 1, gap above the floor, still nothing named: name an effect whose own noise spread covers the data
    (`spread.name_by_spread`), if one does."""
    if not _undecided(step) or not search.config.spread_check or search.floor_of is None:
        return
    inputs = SpreadInputs(
        search.resim,
        search.train,
        search.held,
        params,
        current,
        step.floor,
        search.floor_of,
        search.config,
        search.floor_config,
    )
    pick, step.spread = name_by_spread(remaining, inputs)
    if pick is not None:
        record = pick[1].spread
        step.pick = pick
        step.decision = (
            f"{step.decision}; but the data lie within {pick[0].name}'s own noise spread (held-out gap "
            f"{record['own_floor_test']['ratio']:.2f}x its own floor, p={record['own_floor_test']['p_value']:.2g}), "
            f"it removes {record['systematic_misfit']['explained']:.0%} of the nominal simulator's systematic "
            f"misfit, and the data are more likely under its spread (p={record['likelihood']['p_value']:.2g}): "
            "named by its spread"
        )


def _decide(
    search: _Search,
    step: _Step,
    below: bool,
    reason: str,
    named: list[Candidate],
    params: PhysicsParams,
    current: np.ndarray,
) -> tuple[Candidate | None, str]:
    """The step's pick (or None) and why; a rival is resolved (`resolve_rivals`) where the gap is above the floor;
    below it, `reason` says so and the decision tells the corrected significance."""
    pick, decision = step.pick, step.decision
    if below:
        decision = (
            f"{reason}; each candidate's own reduction tested at p < {step.significance:.2g} "
            f"({search.config.significance} over {step.tested} candidates, Bonferroni): {decision}"
        )
    if step.rival is not None and not below:
        best = _best(step.candidates)
        resolved = resolve_rivals(
            best,
            step.rival,
            search.resim,
            search.train,
            search.held,
            named_params(named, best, search.base, params),
            current,
            step.floor,
            search.config,
            search.cross,
        )
        if resolved is not None:
            return resolved
    return pick, decision


def _name(
    search: _Search, pick: Candidate, named: list[Candidate], params: PhysicsParams
) -> tuple[PhysicsParams, np.ndarray]:
    """Append `pick` to `named` (a joint candidate sets the named effects to the values refitted with it); returns
    the simulator with every named effect and its held-out gap."""
    params = named_params(named, pick, search.base, params)
    if pick[1].named_refit is not None:
        for (_, fit), values in zip(named, pick[1].named_refit):
            fit.values = list(values)
    named.append(pick)
    params = pick[0].physics(pick[1].values, params)
    return params, gap_per_window(search.spec, search.resim.rollout(search.held, params), search.held)


def _selection(
    search: _Search,
    named: list[Candidate],
    steps: list[dict],
    reason: str,
    before: np.ndarray,
    params: PhysicsParams,
    current: np.ndarray,
    refit: dict | None,
) -> Selection:
    """The verdict: `none` or `unexplained` if nothing was named; else the named effects (several: refitted jointly
    after the last naming, `refit`; a lone one of several parameters: refitted here), with their shares of the
    explained gap."""
    config, base = search.config, search.base
    if not named:
        verdict = "none" if not steps[0]["floor_test"]["above_floor"] else "unexplained"
        return Selection(verdict, reason, [], base, before, steps=steps)
    if named[0][1].spread is not None:  # no least-squares fit: nothing to refit, no simpler form to ask
        why = f"{steps[0]['decision']}; then: {reason}"
        return Selection(named[0][0].name, why, named, params, current, [1.0], steps)
    if len(named) == 1 and config.refit_single_effect and len(named[0][0].parameters) > 1:
        named, params, current, refit = joint_refit(
            named, search.resim, search.train, search.held, base, current, config
        )
    named, params, current, simpler = prefer_simpler(named, search, params, current)
    why = _why(named, steps, reason)
    named, params, current, idle = drop_idle(named, search, params, current)
    dropped = [f"{c['effect']} ({c['scope']})" for c in idle if c["dropped"]]
    if dropped:
        why += f"; dropped, adding nothing at the final values: {', '.join(dropped)}"
    shares = effect_shares(named, search.resim, search.held, base, before)
    return Selection(
        named[0][0].name,
        why,
        named,
        params,
        current,
        shares,
        steps,
        refit,
        simpler,
        idle,
    )


def drop_idle(
    named: list[Candidate], search: _Search, params: PhysicsParams, current: np.ndarray
) -> tuple[list[Candidate], PhysicsParams, np.ndarray, list[dict]]:
    """Of several named effects, one that adds nothing at the final values is dropped: set back to nominal (the others
    as they are, not refitted), the held-out gap rises neither significantly (`FitConfig.significance`) nor by
    `min_excess_explained` of what then lies above the corrected simulator's noise floor. A later step's candidate
    fitted together with the named effects (`joint_candidates`) is credited with what the refit of those does:
    armature per joint type on the fast robot's walking data, stopped at (0.013, 0.112, 0.006) kg·m² by its solver's
    rough cost (true: 0.1 in the hip flexion joints only), moved to (0.002, 0.102, 0.003) with joint damping beside
    it, and damping, named for that, ended at 1e-7 N·m·s/rad. Checked from the last named effect to the first."""
    if len(named) < 2 or not search.config.drop_idle:
        return named, params, current, []
    config, checks = search.config, []
    floor = float(np.nanmean(search.floor_at(len(named), params)))
    for candidate in reversed(list(named)):
        if len(named) < 2:
            break
        others = [c for c in named if c is not candidate]
        without = search.base
        for effect, fit in others:
            without = effect.physics(fit.values, without)
        try:
            gap = gap_per_window(search.spec, search.resim.rollout(search.held, without), search.held)
        except SimulationDiverged:
            continue
        excess = float(gap.mean()) - floor
        share = (float(gap.mean()) - float(current.mean())) / excess if excess > 0 else float("nan")
        p_value = paired_p_value(gap.mean(1), current.mean(1), search.held, config.block_rows, config.significance)
        idle = p_value >= config.significance and not share >= config.min_excess_explained
        checks.append(
            {
                "effect": candidate[0].name,
                "scope": candidate[0].scope,
                "gap": float(current.mean()),
                "gap_without": float(gap.mean()),
                "floor": floor,
                "share_above_floor": share,
                "p_value": p_value,
                "dropped": idle,
            }
        )
        if idle:
            named, params, current = others, without, gap
    return named, params, current, checks


def prefer_simpler(
    named: list[Candidate], search: _Search, params: PhysicsParams, current: np.ndarray
) -> tuple[list[Candidate], PhysicsParams, np.ndarray, list[dict]]:
    """A named effect that holds a simpler one of the vocabulary as a special case (`Effect.nested_in`: a weak motor
    is both PD gains scaled alike) gives way to it where the simpler one, fitted in its place and refitted with the
    other named effects, leaves a held-out gap not significantly larger (`FitConfig.significance`): alike there, the
    simpler one is named. Each check also records both simulators' training costs. Beside other effects, the extra
    parameter absorbs part of them, which the step's charge per parameter does not see; where it also lowers the
    held-out gap significantly, PD gains stay named (strength 0.8 with joint friction and encoder offsets on
    excitation data: kp 0.77, kd 1.00, friction 1.35 for 2.0; held-out gap 0.0038 against 0.0052 with motor strength
    at p = 2e-4, training cost 0.00327 against 0.00342, as close as for PD gains of kp 0.7 alone: 0.0030 against
    0.0054, p = 4e-4, and 0.00381 against 0.00399)."""
    config, checks = search.config, []
    for i, (effect, _) in enumerate(list(named)):
        for simpler in (e for e in search.effects.values() if effect.name in e.nested_in and effect.scope == "global"):
            swapped = _in_place_of(search, named, i, simpler)
            if swapped is None:
                continue
            p_value = paired_p_value(
                swapped[2].mean(1), current.mean(1), search.held, config.block_rows, config.significance
            )
            cost, cost_simpler = (training_cost(search, physics) for physics in (params, swapped[1]))
            alike = p_value >= config.significance
            checks.append(
                {
                    "effect": effect.name,
                    "simpler": simpler.name,
                    "gap": float(current.mean()),
                    "gap_simpler": float(swapped[2].mean()),
                    "p_value": p_value,
                    "training_cost": cost,
                    "training_cost_simpler": cost_simpler,
                    "named": simpler.name if alike else effect.name,
                }
            )
            if alike:
                named, params, current = swapped
                break
    return named, params, current, checks


def training_cost(search: _Search, params: PhysicsParams) -> float:
    """Mean squared normalised residual of the simulator `params` on the training windows over the fit horizon (what
    the fits minimise); infinite where it blows up."""
    horizon = search.config.fit_horizon
    try:
        sim = search.resim.rollout(search.train, params, horizon=horizon)
    except SimulationDiverged:
        return float("inf")
    return float(np.mean(normalised_residual(search.spec, sim, search.train.target[:, :horizon]) ** 2))


def _in_place_of(
    search: _Search, named: list[Candidate], i: int, simpler: Effect
) -> tuple[list[Candidate], PhysicsParams, np.ndarray] | None:
    """`simpler` fitted on top of the named effects but the i-th, then every parameter refitted together
    (`joint_refit`): the named effects, the simulator and its held-out gap; None if its fit is rejected."""
    spec, resim, held, base = search.spec, search.resim, search.held, search.base
    others = [*named[:i], *named[i + 1 :]]
    under = combine(others).physics(np.concatenate([f.values for _, f in others]), base) if others else base
    [fit] = fit_all(
        {simpler.name: simpler},
        search.on_top_of(under, gap_per_window(spec, resim.rollout(held, under), held)),
        progress=False,
    )
    if fit.status != "ok":
        return None
    swapped = [*named[:i], (simpler, fit), *named[i + 1 :]]
    start = combine(swapped).physics(np.concatenate([f.values for _, f in swapped]), base)
    sequential = gap_per_window(spec, resim.rollout(held, start), held)
    refitted, params, gap, _ = joint_refit(swapped, resim, search.train, held, base, sequential, search.config)
    return refitted, params, gap


def _why(named: list[Candidate], steps: list[dict], stop: str) -> str:
    """The verdict's reason: the named effects (or the one's own reason) and why selection stopped there."""
    if len(named) > 1:
        return f"named in order: {', '.join(f'{e.name} ({e.scope})' for e, _ in named)}; {stop}"
    return f"{steps[0]['decision']}; then: {stop}" if len(steps) > 1 else steps[0]["decision"]


def named_params(
    named: list[Candidate], candidate: Candidate, base: PhysicsParams, params: PhysicsParams
) -> PhysicsParams:
    """The simulator `candidate` is added to: `params` (the named effects), or for a joint candidate the named
    effects at the values refitted with it."""
    if candidate[1].named_refit is None:
        return params
    return combine(named).physics(np.concatenate(candidate[1].named_refit), base)


def joint_candidates(
    candidates: list[Candidate],
    named: list[Candidate],
    earlier: list[Candidate],
    resim: Resimulator,
    train: Windows,
    held: Windows,
    base: PhysicsParams,
    current: np.ndarray,
    config: FitConfig,
) -> list[Candidate]:
    """Fit some candidates again together with the effects named so far, on top of `base`: the best
    `config.joint_candidates` of this step, then (up to twice that many in all) the best of the step before
    (`earlier`, ranked; started from their values there), which a named effect may have soaked up. Each is replaced
    where the joint fit scores better on held-out windows than its fit on top of the named effects: scored against
    the same gap `current`, charged for its own parameters only (the named effects' are already charged)."""
    ok = {(e.name, f.scope): (e, f) for e, f in candidates if f.status == "ok"}
    ranked = sorted(ok, key=lambda key: ok[key][1].score, reverse=True)[: config.joint_candidates]
    starts = {key: ok[key][1].values for key in ranked}
    for effect, fit in earlier:
        key = (effect.name, fit.scope)
        if key in ok and key not in starts and len(starts) < 2 * config.joint_candidates:
            starts[key] = fit.values
    better: dict[int, Candidate] = {}
    for key, values in starts.items():
        effect, fit = ok[key]
        combined = combine([*named, (effect, fit)])
        start = np.concatenate([*(f.values for _, f in named), values])
        joint = fit_effect(
            combined, resim, train, base, config, start, (0.0, 0.0), max_evaluations=2 * config.max_evaluations
        )
        score_fit(joint, combined, resim, held, base, current, config)
        if joint.status != "ok":
            continue
        own = len(fit.values)
        score = 1.0 - (joint.gap_mean / float(current.mean())) * (1.0 + config.penalty_per_parameter * (own - 1))
        if score <= fit.score:
            continue
        cuts = np.cumsum([0] + [len(f.values) for _, f in named])
        values = [float(v) for v in joint.values]
        better[id(fit)] = (
            effect,
            CandidateFit(
                fit.effect,
                fit.names,
                fit.units,
                values[-own:],
                list(joint.uncertainty[-own:]),
                joint.train_cost,
                joint.gap,
                joint.gap_mean,
                joint.explained_fraction,
                score=score,
                p_value=joint.p_value,
                scope=fit.scope,
                rejected=joint.rejected,
                named_refit=[values[a:b] for a, b in itertools.pairwise(cuts)],
            ),
        )
    return [better.get(id(fit), (effect, fit)) for effect, fit in candidates]


def joint_refit(
    named: list[Candidate],
    resim: Resimulator,
    train: Windows,
    held: Windows,
    base: PhysicsParams,
    sequential_gap: np.ndarray,
    config: FitConfig,
) -> tuple[list[Candidate], PhysicsParams, np.ndarray, dict]:
    """Refit every parameter of `named` together; keep the result if the held-out gap does not grow."""
    combined = combine(named)
    start = np.concatenate([fit.values for _, fit in named])
    fit = fit_effect(
        combined, resim, train, base, config, start, (0.0, 0.0), max_evaluations=2 * config.max_evaluations
    )
    score_fit(fit, combined, resim, held, base, sequential_gap, config)
    kept = fit.status == "ok" and fit.gap_mean <= float(sequential_gap.mean())
    info = {
        "kept": bool(kept),
        "gap_sequential": float(sequential_gap.mean()),
        "gap_joint": fit.gap_mean,
        "rejected_points": fit.rejected,
    }
    if not kept:
        return named, combined.physics(start, base), sequential_gap, info
    out, i = [], 0
    for effect, old in named:
        n = len(effect.parameters)
        old.values, old.uncertainty = fit.values[i : i + n], fit.uncertainty[i : i + n]
        out.append((effect, old))
        i += n
    params = combined.physics(fit.values, base)
    return out, params, gap_per_window(resim.spec, resim.rollout(held, params), held), info


def effect_shares(
    named: list[Candidate], resim: Resimulator, held: Windows, base: PhysicsParams, before: np.ndarray
) -> list[float]:
    """Held-out gap reduction of each named effect, added in order at its final values, over the total reduction."""
    gaps, params = [float(before.mean())], base
    for effect, fit in named:
        params = effect.physics(fit.values, params)
        try:
            gaps.append(float(gap_per_window(resim.spec, resim.rollout(held, params), held).mean()))
        except SimulationDiverged:
            gaps.append(gaps[-1])
    total = gaps[0] - gaps[-1]
    return [float((gaps[i] - gaps[i + 1]) / total) if total > 0 else float("nan") for i in range(len(named))]

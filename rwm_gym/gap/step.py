"""One step of the forward selection: fit every effect not yet named on top of the simulator with the named ones,
judge the candidates (`gap.judge`), and look harder where the step would otherwise name nothing.

At each step every effect not yet named is fitted and scored on top of the named ones (`fit.fit_all`), the best joint
effects also in their scopes (`scope.scope_candidates`), and from the second step on some also together with the named
effects (`refit.joint_candidates`).

Step 1, where its gap is not significantly above its floor, fits the candidates anyway and asks each one's own
held-out reduction, at `FitConfig.significance` divided by the number of candidates (Bonferroni). The best candidate,
if it fails only that test, is tested again on every measured episode (`cross_fit`). A later step near its floor
judges its candidates so too, and its pick must also leave `min_excess_explained` less above its own simulator's floor
than the step's gap lies above the step's floor: near the floor, a candidate that changes how far sensor noise carries
(another contact solver) lowers the gap by lowering the floor.

Before step 1 calls a gap above the floor `unexplained`, every effect is refined (not only the best screened,
`FitConfig.refine_every_effect`) and every joint effect is fitted in its scopes too (`scope.every_scope`), also those
whose global form explained nothing; a best candidate that then explains enough but fails only its held-out test is
tested again cross-fitted on every episode (a torque limit 2x on walking data explained 89 % of a gap 300x the floor
at p = 0.034 on the held-out third); last, an effect whose own noise spread covers the data is named
(`spread.name_by_spread`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from rwm_gym.gap.cross_fit import CrossFit, cross_fitted_p_value
from rwm_gym.gap.effects import Effect
from rwm_gym.gap.fit import CandidateFit, FitConfig, FitInputs, FitMemo, fit_all
from rwm_gym.gap.judge import best_of, judge
from rwm_gym.gap.noise_floor import FloorConfig
from rwm_gym.gap.refit import Candidate, joint_candidates, named_params
from rwm_gym.gap.resim import Resimulator, Windows
from rwm_gym.gap.scope import every_scope, scope_candidates
from rwm_gym.gap.spread import SpreadInputs, name_by_spread
from rwm_gym.physics.params import PhysicsParams
from rwm_gym.spec import TaskSpec


@dataclass(frozen=True)
class Search:
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
class Step:
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
    """The noise floor the step judges against (`Search.floor_at`)."""
    spread: list[dict] | None = None
    """Step 1 about to call its gap `unexplained`: each effect's check of its own noise spread (`gap.spread`)."""


def judge_step(
    search: Search,
    k: int,
    below: bool,
    named: list[Candidate],
    earlier: list[Candidate],
    params: PhysicsParams,
    current: np.ndarray,
    floor: np.ndarray,
) -> Step:
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
    step = Step(
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
    search: Search, candidates: list[Candidate], current: np.ndarray, significance: float, floor: np.ndarray
) -> tuple[Candidate | None, str, Candidate | None]:
    """`judge` on the step's gap `current` and the mean of its noise floor."""
    return judge(candidates, float(current.mean()), float(np.nanmean(floor)), search.config, significance)


def _undecided(step: Step) -> bool:
    return step.pick is None and step.rival is None


def _cross_fit_the_best(
    search: Search, step: Step, named: list[Candidate], params: PhysicsParams, current: np.ndarray
) -> None:
    """Nothing named at this step (a gap near the floor, or step 1 about to call one above it `unexplained`): if the
    best candidate explains enough of the gap, test it again on every measured episode (`cross_fitted_p_value`), and
    judge again."""
    if not _undecided(step) or search.cross is None:
        return
    best = best_of(step.candidates)
    if best is not None and best[1].excess_explained >= search.config.min_excess_explained:
        under = named_params(named, best, search.base, params)
        best[1].cross_fitted_p_value = cross_fitted_p_value(
            best, search.resim, search.held, search.cross(), params, current, search.config, step.significance, under
        )
        step.pick, step.decision, step.rival = _judge(search, step.candidates, current, step.significance, step.floor)


def _against_its_own_floor(
    search: Search, step: Step, named: list[Candidate], params: PhysicsParams, current: np.ndarray
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
    search: Search, step: Step, remaining: dict[str, Effect], params: PhysicsParams, current: np.ndarray
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
    search: Search, step: Step, remaining: dict[str, Effect], params: PhysicsParams, current: np.ndarray
) -> None:
    """Step 1, gap above the floor, still nothing named: fit every joint effect in its scopes too (also those whose
    global form explained nothing), and judge again."""
    if not _undecided(step) or not search.config.every_scope:
        return
    # effects already fitted per group; a single-joint form (one value) does not stand for its effect's groups
    scoped = {f.effect for _, f in step.candidates if f.scope != "global" and len(f.values) > 1}
    inputs = search.on_top_of(params, current)
    more = every_scope(step.fits, scoped, remaining, inputs, **search.first_step(0))
    if more:
        step.candidates += more
        step.pick, step.decision, step.rival = _judge(search, step.candidates, current, step.significance, step.floor)


def _by_spread(
    search: Search, step: Step, remaining: dict[str, Effect], params: PhysicsParams, current: np.ndarray
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

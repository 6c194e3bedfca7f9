"""Judge one step's candidates: which one it names, or why none, and what to make of a rival that explains the gap
alike.

The best-scoring candidate is named when

- its held-out reduction is significant (`FitConfig.significance`, Wilcoxon on block means),
- it explains `min_excess_explained` of the gap above the step's floor (the floor itself no effect can remove;
  measured against the whole gap, an effect near the floor could never reach it),
- no unrelated candidate (not the same effect in another scope, not nesting it) that itself explains
  `rival_excess_explained` of the gap above the floor leaves a penalised remaining gap within `ambiguity_ratio` of
  the best's.

Two unrelated candidates that explain the gap alike are then told apart, where they can be, by fitting each on top
of the other (`resolve_rivals`).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from rwm_gym.gap.cross_fit import CrossFit, cross_fitted_p_value
from rwm_gym.gap.effects import Effect
from rwm_gym.gap.fit import CandidateFit, FitConfig, fit_effect, gap_per_window, score_fit
from rwm_gym.gap.refit import Candidate
from rwm_gym.gap.resim import Resimulator, Windows
from rwm_gym.physics.params import PhysicsParams


def ranked(candidates: list[Candidate]) -> list[Candidate]:
    """The candidates whose fit is ok, best score first."""
    return sorted((c for c in candidates if c[1].status == "ok"), key=lambda c: c[1].score, reverse=True)


def best_of(candidates: list[Candidate]) -> Candidate | None:
    """The best-scoring candidate whose fit is ok, or None."""
    return max((c for c in candidates if c[1].status == "ok"), key=lambda c: c[1].score, default=None)


def related(a: Effect, b: Effect) -> bool:
    """The same effect, or one nests the other."""
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
        if not related(effect, other_effect) and alike and explains:
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

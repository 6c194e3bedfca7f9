"""Test a candidate on every measured episode: 2-fold cross-fitting.

The held-out third alone holds few blocks (a triple's third effect in 9 walking episodes: 3x the floor at p = 0.017).
The candidate is fitted again on the held-out episodes and scored on the fitting ones; the test then runs on every
measured episode, each scored by a fit that did not see it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rwm_gym.gap.fit import FitConfig, fit_effect, gap_per_window
from rwm_gym.gap.refit import Candidate
from rwm_gym.gap.resim import Resimulator, SimulationDiverged, Windows
from rwm_gym.gap.significance import paired_p_value
from rwm_gym.physics.params import PhysicsParams


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

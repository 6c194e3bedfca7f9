"""How much each fitted value would move with other measured episodes: a bootstrap over the fitting episodes.

The Jacobian's 1-sigma (`fit._uncertainty`) assumes independent residuals and a cost that is smooth near the optimum;
neither holds for a contact-rich trajectory, and where the cost is flat it says nothing. The bootstrap asks the data
instead: the fitting episodes are drawn with replacement `resamples` times (a fixed seed per draw, so the report is
the same on every run), and every named effect is refitted jointly on each draw's windows from the selection's values
(`fit.fit_effect` with `FitConfig`'s budget; a one-parameter effect searched within a quarter of its range either side
of its value). The spread of the refitted values is the report's `bootstrap` entry beside each value: the standard
deviation and the 2.5 and 97.5 percentiles. Windows, not rows, are the unit drawn: a drawn episode brings all its
fitting windows, so the correlation inside an episode stays in each draw. An effect named by its noise spread
(`gap.spread`) is searched again so on each draw (a draw where no value covers the data counts as NaN, said in the
entry).
"""

from __future__ import annotations

import numpy as np

from rwm_gym.gap.fit import FitConfig, fit_effect
from rwm_gym.gap.refit import Candidate, combine
from rwm_gym.gap.resim import Resimulator, Windows
from rwm_gym.gap.spread import FloorOf, spread_search
from rwm_gym.physics.params import PhysicsParams

SEARCH_REACH = 0.25
"""Half-width, as a share of a parameter's range, of the interval a one-parameter effect is refitted in."""


def resample(train: Windows, rng: np.random.Generator) -> Windows:
    """The windows of as many fitting episodes as `train` has, drawn with replacement (an episode drawn twice brings its
    windows twice)."""
    episodes = np.unique(train.episode)
    drawn = rng.choice(episodes, size=len(episodes), replace=True)
    parts = [train.subset(train.episode == e) for e in drawn]
    out = parts[0]
    for part in parts[1:]:
        out = out.join(part)
    return out


def bootstrap(
    named: list[Candidate],
    resim: Resimulator,
    train: Windows,
    base: PhysicsParams,
    config: FitConfig,
    resamples: int,
    seed: int = 0,
    floor_of: FloorOf | None = None,
) -> dict:
    """{"resamples", "method", "parameters": {name: {"std", "interval"}}} for every parameter of the `named` effects
    (empty where none is named or `resamples` is 0); `floor_of` (`spread.FloorOf`): for an effect named by its
    spread."""
    if resamples < 0:
        raise ValueError(f"bootstrap resamples must be >= 0, got {resamples}")
    if not named or resamples == 0:
        return {"resamples": resamples, "parameters": {}}
    effect = combine(named)
    start = np.concatenate([np.asarray(f.values, float) for _, f in named])
    names = [n for _, f in named for n in f.names]
    first = effect.parameters[0]
    reach = SEARCH_REACH * (first.high - first.low)
    bracket = (max(first.low, start[0] - reach), min(first.high, start[0] + reach))
    by_spread = named[0][1].spread is not None and floor_of is not None
    draws = np.full((resamples, len(start)), np.nan)
    for b in range(resamples):
        windows = resample(train, np.random.default_rng([seed, 17, b]))
        if by_spread:
            point = spread_search(named[0][0], resim, windows, base, floor_of, config)
            draws[b] = np.nan if point is None else point.values
        else:
            draws[b] = fit_effect(effect, resim, windows, base, config, start.copy(), bracket).values
    method = "fitting episodes drawn with replacement, every named effect refitted jointly from its value"
    if by_spread:
        covered = int(np.isfinite(draws[:, 0]).sum())
        method = (
            f"fitting episodes drawn with replacement, the value of least spread that covers them searched again "
            f"(found on {covered} of {resamples} draws)"
        )
        draws = draws[np.isfinite(draws[:, 0])]
    if len(draws) == 0:
        return {"resamples": resamples, "method": method, "parameters": {}}
    return {
        "resamples": resamples,
        "method": method,
        "parameters": {
            name: {
                "std": float(draws[:, i].std(ddof=1)) if len(draws) > 1 else float("nan"),
                "interval": [float(np.percentile(draws[:, i], 2.5)), float(np.percentile(draws[:, i], 97.5))],
            }
            for i, name in enumerate(names)
        },
    }

"""Effects that spread sensor noise: a simulator judged by whether its own noise spread covers the data.

The gap of a simulator that is exactly right is its noise floor (`noise_floor`). Where that floor is small, least
squares finds the right simulator, whose gap is the smallest. A simulator that carries the start state's sensor noise
into a different motion each time (a slippery floor under the package's fast contact solver: four iterations turn a
millimetre off at the start into another slide) has a large floor, and its data too: re-simulated from noisy
measured states, the right simulator slides elsewhere and leaves a larger gap than a wrong one that does not slide. No
least-squares fit moves towards it, and step 1 calls the gap `unexplained`.

Before it does (`FitConfig.spread_check`), each effect is asked another question: at which value does its simulator's
own spread cover the data? Its first parameter (the rest nominal) is searched along its range on the fitting windows,
each point re-simulated and its own floor computed there. A point covers the data where its gap is below its floor
(or, where no point does, below 1.2x it: `COVERING_RATIOS`); of the points that cover, the one with the least spread is
kept, and the range between it and its neighbour that does not cover is bisected (`spread_search`): the most precise
simulator that still explains the data as noise. On the held-out windows it is named (`judge_spread`) where

- its gap is not above its own floor (`compare_with_floor`): the data look as its simulator with sensor noise;
- it removes `FitConfig.min_excess_explained` of the nominal simulator's systematic misfit (`systematic_misfit`: the
  residual's mean over windows, which noise averages out of): a simulator whose spread is only wide enough to cover
  a misfit (a slippery floor beside a knee spring on walking data: 0.63x its own floor) leaves the misfit's mean
  where it was, or larger;
- the data are significantly more likely under its spread than under the nominal simulator's (`paired_p_value` on
  each window's negative log-likelihood: per horizon, the gap over the floor plus the floor's log, a Gaussian whose
  variance is the floor).

Such a fit is no least-squares fit: it is not refitted with other effects, and selection stops after it (its gap lies
at its own floor). Its gap may be larger than the nominal one; what it explains is said against its own floor.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from rwm_gym.gap.effects import Effect
from rwm_gym.gap.fit import CandidateFit, FitConfig, gap_horizons, gap_per_window
from rwm_gym.gap.noise_floor import FloorConfig, compare_with_floor
from rwm_gym.gap.resim import Resimulator, SimulationDiverged, Windows, normalised_residual
from rwm_gym.gap.significance import paired_p_value
from rwm_gym.physics.params import PhysicsParams

COVERING_RATIOS = (1.0, 1.2)
"""A value covers the fitting windows where its gap is below the first of these multiples of its own floor at which
any value does. The floor is the gap a right simulator leaves on average, so 1 aims at the right value; the held-out
test's margin (`FloorConfig.min_ratio`, 1.2) alone stops the search short of it, at a value of less spread: ground
friction 0.74 for 0.65 on the fast robot's excitation data (0.70 at 1), 0.32 for 0.3 on its walking data (0.29). On a
short log no value may reach 1 (6 episodes of 150 steps at ground friction 0.3); the margin is taken there.
"""

FloorOf = Callable[..., np.ndarray]
"""`floor_of(params)`: the noise floor (W, horizons) of a simulator on the held-out windows; `floor_of(params,
windows)`: on `windows`."""


@dataclass(frozen=True)
class SpreadPoint:
    """One value of an effect's first parameter: its gap and its own noise floor per horizon (means over windows)."""

    values: np.ndarray
    gap: np.ndarray
    floor: np.ndarray

    def covers(self, ratio: float) -> bool:
        """The gap lies below `ratio` times the floor, both averaged over horizons as `compare_with_floor` averages
        them. A test per horizon fails the right floor on a few windows' slides: ground friction 0.3 on the fast
        robot's excitation data, 25-step fitting windows, leaves 0.61x its floor at 1 step and 1.45x at 5."""
        return bool(self.gap.mean() < ratio * self.floor.mean())

    @property
    def spread(self) -> float:
        return float(self.floor.mean())


def _point(
    effect: Effect, value: float, resim: Resimulator, windows: Windows, base: PhysicsParams, floor_of: FloorOf
) -> SpreadPoint | None:
    """The effect at `value` (first parameter; the rest nominal) on `windows`; None where the simulation blows up."""
    values = effect.nominal.copy()
    values[0] = value
    params = effect.physics(values, base)
    try:
        gap = gap_per_window(resim.spec, resim.rollout(windows, params), windows)
        floor = floor_of(params, windows)
    except SimulationDiverged:
        return None
    if not np.isfinite(floor).any():
        return None
    return SpreadPoint(values, gap.mean(0), np.nanmean(floor, 0))


def _grid(effect: Effect, points: int) -> np.ndarray:
    """`points` values of the first parameter across its range, on its step where it has one."""
    first = effect.parameters[0]
    grid = np.linspace(first.low, first.high, points)
    return np.unique(np.round(grid / first.step) * first.step) if first.step else grid


def spread_search(
    effect: Effect,
    resim: Resimulator,
    windows: Windows,
    base: PhysicsParams,
    floor_of: FloorOf,
    config: FitConfig,
    ratios: tuple[float, ...] = COVERING_RATIOS,
) -> SpreadPoint | None:
    """The value of `effect`'s first parameter with the least spread whose simulator still covers the data on
    `windows` at the first of `ratios` at which any value does (see the module docstring); None where none does."""
    first = effect.parameters[0]
    points = {
        float(v): _point(effect, float(v), resim, windows, base, floor_of) for v in _grid(effect, config.spread_points)
    }
    for ratio in ratios:
        covering = [v for v, p in points.items() if p is not None and p.covers(ratio)]
        if covering:
            break
    else:
        return None
    best = min(covering, key=lambda v: points[v].spread)
    values = sorted(points)
    i = values.index(best)
    neighbours = [values[j] for j in (i - 1, i + 1) if 0 <= j < len(values) and values[j] not in covering]
    if not neighbours:
        return points[best]
    inside = best
    outside = min(neighbours, key=lambda v: points[v].spread if points[v] is not None else np.inf)
    for _ in range(config.spread_bisections):
        middle = 0.5 * (inside + outside)
        if first.step:
            middle = round(middle / first.step) * first.step
            if middle in (inside, outside):
                break
        point = _point(effect, middle, resim, windows, base, floor_of)
        if point is not None and point.covers(ratio):
            inside, points[middle] = middle, point
        else:
            outside = middle
    return points[inside]


def negative_log_likelihood(gap: np.ndarray, floor: np.ndarray) -> np.ndarray:
    """(W,) per window: over horizons, the gap over the floor's mean there plus the log of that mean (a Gaussian
    error whose variance is the simulator's own floor; constants dropped)."""
    spread = np.nanmean(floor, 0)
    return (gap / spread + np.log(spread)).sum(1)


@dataclass(frozen=True)
class SpreadInputs:
    """What the spread check reads: the simulator (`base` under `resim`'s solver), the fitting and held-out windows,
    the nominal held-out gap and noise floor (W, horizons), every simulator's floor, and the fit's and floor's
    settings."""

    resim: Resimulator
    train: Windows
    held: Windows
    base: PhysicsParams
    before: np.ndarray
    floor: np.ndarray
    floor_of: FloorOf
    config: FitConfig
    floor_config: FloorConfig


def systematic_misfit(spec, simulated: np.ndarray, windows: Windows) -> float:
    """The part of a simulator's gap on `windows` that it leaves on average: over the gap's horizons and the state
    channels, the squared mean of the normalised residual over windows, less that mean's sampling noise (variance over
    the number of windows). Noise, however far a simulator spreads it, averages out of it; a missing spring does not."""
    res = normalised_residual(spec, simulated, windows.target)
    steps = res[:, [h - 1 for h in gap_horizons(res.shape[1])]]
    return float((steps.mean(0) ** 2 - steps.var(0, ddof=1) / len(steps)).sum())


def judge_spread(
    effect: Effect, point: SpreadPoint, inputs: SpreadInputs, nominal_misfit: float
) -> tuple[CandidateFit | None, dict]:
    """`point` on the held-out windows: the candidate fit (None where it fails) and the record of the three tests.
    `nominal_misfit`: the nominal simulator's `systematic_misfit` there."""
    resim, held, before, floor, config = inputs.resim, inputs.held, inputs.before, inputs.floor, inputs.config
    record: dict = {"effect": effect.name, "values": [float(v) for v in point.values], "spread": point.spread}
    params = effect.physics(point.values, inputs.base)
    try:
        simulated = resim.rollout(held, params)
        own = inputs.floor_of(params)
    except SimulationDiverged as err:
        record["reason"] = f"the simulation blows up on held-out windows ({err.reason})"
        return None, record
    gap = gap_per_window(resim.spec, simulated, held)
    test = compare_with_floor(gap, own, held, config.block_rows, inputs.floor_config)
    misfit = systematic_misfit(resim.spec, simulated, held)
    share = 1.0 - misfit / nominal_misfit if nominal_misfit > 0 else float("nan")
    nll, nll_nominal = negative_log_likelihood(gap, own), negative_log_likelihood(before, floor)
    p_value = paired_p_value(nll_nominal, nll, held, config.block_rows, config.significance)
    record.update(
        own_floor_test=test,
        systematic_misfit={"misfit": misfit, "nominal": nominal_misfit, "explained": share},
        likelihood={"nll": float(nll.mean()), "nll_nominal": float(nll_nominal.mean()), "p_value": p_value},
    )
    reason = ""
    if test["above_floor"]:
        reason = f"its held-out gap is above its own floor ({test['ratio']:.2f}x, p={test['p_value']:.2g})"
    elif not share >= config.min_excess_explained:
        reason = (
            f"it removes {share:.0%} of the nominal simulator's systematic misfit (needs "
            f"{config.min_excess_explained:.0%})"
        )
    elif not p_value < config.significance:
        reason = f"the data are not significantly more likely under its spread (p={p_value:.2g})"
    record.update(named=not reason, **({"reason": reason} if reason else {}))
    if reason:
        return None, record
    horizons = gap_horizons(held.horizon)
    fit = CandidateFit(
        effect.name,
        [p.name for p in effect.parameters],
        [p.unit for p in effect.parameters],
        [float(v) for v in point.values],
        [float("nan")] * len(effect.parameters),
        float("nan"),
        {h: float(v) for h, v in zip(horizons, gap.mean(0))},
        float(gap.mean()),
        float(1.0 - gap.mean() / before.mean()),
        excess_explained=share,
        score=share,
        p_value=p_value,
        spread=record,
    )
    return fit, record


def name_by_spread(
    effects: dict[str, Effect], inputs: SpreadInputs
) -> tuple[tuple[Effect, CandidateFit] | None, list[dict]]:
    """Search every effect (`spread_search`) on the fitting windows `train`; judge those that cover them on `held`,
    least spread first (`judge_spread`); the first that passes, and every effect's record. Nothing to search where
    the nominal simulator covers the fitting windows itself."""
    resim, train, base, floor_of = inputs.resim, inputs.train, inputs.base, inputs.floor_of
    gap = gap_per_window(resim.spec, resim.rollout(train, base), train)
    nominal = SpreadPoint(np.zeros(0), gap.mean(0), np.nanmean(floor_of(base, train), 0))
    if nominal.covers(inputs.floor_config.min_ratio):
        return None, [{"reason": "the nominal simulator's own spread covers the fitting windows"}]
    found = []
    for effect in effects.values():
        point = spread_search(effect, resim, train, base, floor_of, inputs.config)
        if point is not None:
            found.append((effect, point))
    nominal_misfit = systematic_misfit(resim.spec, resim.rollout(inputs.held, base), inputs.held)
    records = []
    for effect, point in sorted(found, key=lambda item: item[1].spread):
        fit, record = judge_spread(effect, point, inputs, nominal_misfit)
        records.append(record)
        if fit is not None:
            return (effect, fit), records
    return None, records

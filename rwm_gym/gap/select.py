"""Name the effects behind a gap: forward selection over the vocabulary and its scopes, then the final choice and its
reason.

`select_effects` runs the forward search (`gap.search`; each step fits and judges its candidates, `gap.step` and
`gap.judge`) and turns where it ended into a `Selection`. A significant gap that no candidate explains at step 1 is
`unexplained`; a gap not above its noise floor where none passes is `none`. Where effects were named: a lone named
effect of several parameters (`FitConfig.refit_single_effect`) is refitted (`refit.joint_refit`); a named effect gives
way to a simpler one it holds where that fits alike (`prefer_simpler`); of several, one that adds nothing at the final
values is dropped (`drop_idle`). Each named effect's share of the explained gap is its held-out gap reduction when the
effects are added in order at their final values.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from rwm_gym.gap.cross_fit import CrossFit
from rwm_gym.gap.effects import Effect
from rwm_gym.gap.fit import FitConfig, FitMemo, fit_all, gap_per_window
from rwm_gym.gap.noise_floor import FloorConfig
from rwm_gym.gap.refit import Candidate, combine, effect_shares, joint_refit
from rwm_gym.gap.resim import Resimulator, SimulationDiverged, Windows, normalised_residual
from rwm_gym.gap.search import forward
from rwm_gym.gap.significance import paired_p_value
from rwm_gym.gap.step import Search
from rwm_gym.physics.params import PhysicsParams
from rwm_gym.spec import TaskSpec


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
    """Forward selection of effects on top of `base` (this module's docstring and `gap.search`'s); `before` and
    `floor` (W, 3) are the nominal held-out gap and its noise floor per window; `cross`: builds the swapped windows for
    a gap near the floor, called once if step 1's best candidate needs them (None: the held-out test alone); `memo`:
    step 1's fits where they were made already (`fit.FitMemo`; the solver check's under the solver it took);
    `floor_of`: the noise floor of a simulator, for the steps after the first (None: the nominal `floor` at every
    step)."""
    search = Search(
        effects, spec, resim, train, held, base, floor, config, progress, cross, memo, floor_of, floor_config
    )
    path = forward(search, base, before)
    return _selection(search, path.named, path.steps, path.reason, before, path.params, path.current, path.refit)


def _selection(
    search: Search,
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
    named: list[Candidate], search: Search, params: PhysicsParams, current: np.ndarray
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
    named: list[Candidate], search: Search, params: PhysicsParams, current: np.ndarray
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


def training_cost(search: Search, params: PhysicsParams) -> float:
    """Mean squared normalised residual of the simulator `params` on the training windows over the fit horizon (what
    the fits minimise); infinite where it blows up."""
    horizon = search.config.fit_horizon
    try:
        sim = search.resim.rollout(search.train, params, horizon=horizon)
    except SimulationDiverged:
        return float("inf")
    return float(np.mean(normalised_residual(search.spec, sim, search.train.target[:, :horizon]) ** 2))


def _in_place_of(
    search: Search, named: list[Candidate], i: int, simpler: Effect
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

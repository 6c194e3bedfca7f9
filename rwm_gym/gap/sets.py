"""Several effects named together where no single effect and no pair passes: a set built step by step.

Three effects can hide one another. Action delay + payload + ground friction on a converged robot's walking data,
re-simulated with a converged solve: the delay explains 29 % of the gap above the floor alone (a step needs 30 %), the
payload 7 % and ground friction 5 %, so no pair of the effects that explain 15 % alone can hold them; on top of the
delay, ground friction explains 20 %, and on top of both the payload 44 %. Fitted together the three leave 0.024 of a
nominal gap of 0.156 (floor 0.005).

So where a step with its gap above the noise floor names nothing and no pair passes, a set is built: the step's best
global candidate that lowers the held-out gap at p < `FitConfig.significance`, then, on top of the set, the best
unrelated effect (global forms, `fit.fit_all`) that lowers it further at that p, until no effect does or the set fills
the room left under `max_effects`. Each effect of the set is fitted again on top of the others, and then all together
(`refit.joint_refit`): fitted on top of the delay alone, ground friction stopped at 0.40 and the payload at 4.9 kg;
fitted again on top of the others, 0.31 and 9.1 kg (the truth 0.30 and 8 kg). The set is named, every effect of it,
where it explains `min_excess_explained` of the gap above the floor at that p and each of its effects still explains
`rival_excess_explained` of it on top of the others (they at their values in the set) at that p: the rule of a pair
(`gap.pairs`), for a set of any size.
"""

from __future__ import annotations

import copy

import numpy as np

from rwm_gym.gap.effects import Effect
from rwm_gym.gap.fit import FitConfig, FitInputs, fit_all, fit_effect, gap_per_window
from rwm_gym.gap.judge import ranked, related
from rwm_gym.gap.pairs import each_on_top_of_the_others, passes_together
from rwm_gym.gap.refit import Candidate, combine, joint_refit
from rwm_gym.gap.resim import Resimulator, SimulationDiverged, Windows
from rwm_gym.gap.significance import paired_p_value
from rwm_gym.physics.params import PhysicsParams


def best_set(
    candidates: list[Candidate],
    effects: dict[str, Effect],
    resim: Resimulator,
    train: Windows,
    held: Windows,
    params: PhysicsParams,
    current: np.ndarray,
    floor: float,
    room: int,
    config: FitConfig,
) -> tuple[list[Candidate] | None, dict]:
    """The set to name on top of `params` (held-out gap `current` (W, 3), floor mean `floor`), of at most `room`
    effects, starting from the step's `candidates`, or None; and the record of how it was built and tested (see the
    module docstring)."""
    excess = float(current.mean()) - floor
    significance = config.significance
    first = next((c for c in ranked(candidates) if _lowers(c, current, significance)), None)
    record: dict = {"significance": significance, "built": []}
    if first is None or excess <= 0 or room < 2:
        return None, record
    members = [(first[0], copy.deepcopy(first[1]))]
    set_params = first[0].physics(first[1].values, params)
    set_gap = gap_per_window(resim.spec, resim.rollout(held, set_params), held)
    record["built"].append({"effect": first[0].name, "values": list(first[1].values), "gap": float(set_gap.mean())})
    while len(members) < room:
        remaining = {n: e for n, e in effects.items() if not any(related(e, m) for m, _ in members)}
        fits = fit_all(remaining, FitInputs(resim, train, held, set_params, set_gap, config), False)
        step = [(remaining[f.effect], f) for f in fits]
        pick = next((c for c in ranked(step) if _lowers(c, set_gap, significance)), None)
        if pick is None:
            break
        members.append(pick)
        set_params = pick[0].physics(pick[1].values, set_params)
        set_gap = gap_per_window(resim.spec, resim.rollout(held, set_params), held)
        record["built"].append({"effect": pick[0].name, "values": list(pick[1].values), "gap": float(set_gap.mean())})
    if len(members) < 2:
        return None, record
    backfitted = _backfit(members, resim, train, params, config)
    values = np.concatenate([f.values for _, f in backfitted])
    try:
        gap = gap_per_window(resim.spec, resim.rollout(held, combine(backfitted).physics(values, params)), held)
    except SimulationDiverged:
        gap = None
    if gap is not None and gap.mean() <= set_gap.mean():  # kept where the held-out gap does not grow
        members, set_gap = backfitted, gap
    members, set_params, after, refit = joint_refit(members, resim, train, held, params, set_gap, config)
    share = (float(current.mean()) - float(after.mean())) / excess
    p_value = paired_p_value(current.mean(1), after.mean(1), held, config.block_rows, significance)
    record.update(
        effects=[e.name for e, _ in members],
        values=[list(f.values) for _, f in members],
        refit=refit,
        gap=float(after.mean()),
        excess_explained=share,
        p_value=p_value,
    )
    at_values = [(effect, fit.values) for effect, fit in members]
    added = each_on_top_of_the_others(at_values, resim, held, params, after, excess, significance, config)
    record["on_top_of_the_others"] = added
    passes = added is not None and passes_together(p_value, share, added, significance, config)
    record["passes"] = passes
    if not passes:
        return None, record
    for _, fit in members:
        fit.gap_mean, fit.excess_explained, fit.p_value = float(after.mean()), share, p_value
        fit.explained_fraction = 1.0 - float(after.mean()) / float(current.mean())
    return members, record


def _backfit(
    members: list[Candidate], resim: Resimulator, train: Windows, params: PhysicsParams, config: FitConfig
) -> list[Candidate]:
    """Each member fitted again on top of the others (its first parameter searched over its whole range), in the order
    they joined. An effect that joined early was fitted without the later ones, which hid part of it; a refit of all
    parameters together (least squares from these values) stalls on a threshold-like cost such as ground friction's."""
    members = [(effect, copy.deepcopy(fit)) for effect, fit in members]
    for i, (effect, fit) in enumerate(members):
        others = members[:i] + members[i + 1 :]
        under = combine(others).physics(np.concatenate([f.values for _, f in others]), params)
        first = effect.parameters[0]  # searched over its whole range first, also where the effect has more
        refit = fit_effect(effect, resim, train, under, config, np.asarray(fit.values, float), (first.low, first.high))
        if refit.status == "ok":
            fit.values, fit.uncertainty = refit.values, refit.uncertainty
    return members


def _lowers(candidate: Candidate, current: np.ndarray, significance: float) -> bool:
    """A global candidate (not refitted with the named effects) whose held-out gap is below `current`'s, at
    p < `significance`."""
    fit = candidate[1]
    alone = fit.scope == "global" and fit.named_refit is None
    return alone and fit.gap_mean < float(current.mean()) and fit.p_value < significance

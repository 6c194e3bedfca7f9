"""Two effects named together where no single one passes.

With three effects present each explains about a third of the gap alone, and the one that explains most may fall
just short of what a step needs: action delay + payload + ground friction on a converged robot's walking data, where
the delay, fitted at its true 15 ms, explained 28 % of the gap above the floor at p = 6e-8 (a step needs 30 %).
Fitted together, two of them explain what neither does alone.

So where a step with its gap above the noise floor names nothing, the best `FitConfig.pair_candidates` unrelated
effects (global forms, each explaining `rival_excess_explained` of the gap above the floor alone) are fitted in pairs,
on top of the effects named so far, from their values at the step. A pair is named, both of its effects, where it
explains `min_excess_explained` of the gap above the floor at p < `FitConfig.significance` over the pairs tried
(Bonferroni), and each of its effects still explains `rival_excess_explained` of it on top of the other (the other at
its value in the pair) at that p: a pair of which one effect adds nothing is that effect alone, which did not pass.
"""

from __future__ import annotations

import itertools

import numpy as np

from rwm_gym.gap.effects import Effect
from rwm_gym.gap.fit import CandidateFit, FitConfig, fit_effect, gap_per_window, score_fit
from rwm_gym.gap.judge import ranked, related
from rwm_gym.gap.refit import Candidate, combine
from rwm_gym.gap.resim import Resimulator, SimulationDiverged, Windows
from rwm_gym.gap.significance import paired_p_value
from rwm_gym.physics.params import PhysicsParams


def candidates_to_pair(candidates: list[Candidate], share: float, count: int) -> list[Candidate]:
    """The best `count` global candidates (by score) of unrelated effects that each explain `share` of the gap above
    the floor alone."""
    out: list[Candidate] = []
    for effect, fit in ranked(candidates):
        if len(out) == count:
            break
        alone = fit.excess_explained >= share
        if fit.scope == "global" and alone and not any(related(effect, other) for other, _ in out):
            out.append((effect, fit))
    return out


def best_pair(
    candidates: list[Candidate],
    resim: Resimulator,
    train: Windows,
    held: Windows,
    params: PhysicsParams,
    current: np.ndarray,
    floor: float,
    config: FitConfig,
) -> tuple[list[Candidate] | None, dict]:
    """The pair to name on top of `params` (held-out gap `current` (W, 3), floor mean `floor`) among the step's
    `candidates`, best single effect first, or None; and the record of every pair tried (see the module docstring)."""
    excess = float(current.mean()) - floor
    top = candidates_to_pair(candidates, config.rival_excess_explained, config.pair_candidates)
    pairs = list(itertools.combinations(top, 2)) if excess > 0 else []
    significance = config.significance / max(len(pairs), 1)
    tried, passed = [], []
    for first, second in pairs:
        record, members = _fit_pair(first, second, resim, train, held, params, current, excess, significance, config)
        tried.append(record)
        if members is not None:
            passed.append((record["score"], members))
    record = {"significance": significance, "pairs": tried}
    if not passed:
        return None, record
    members = max(passed, key=lambda sm: sm[0])[1]
    record["named"] = [e.name for e, _ in members]
    return members, record


def _fit_pair(
    first: Candidate,
    second: Candidate,
    resim: Resimulator,
    train: Windows,
    held: Windows,
    params: PhysicsParams,
    current: np.ndarray,
    excess: float,
    significance: float,
    config: FitConfig,
) -> tuple[dict, list[Candidate] | None]:
    """`first` and `second` fitted together on top of `params` and tested against the gap above the floor `excess`
    (> 0): the record, and the two as named candidates at their values in the pair where it passes, else None."""
    combined = combine([first, second])
    start = np.concatenate([first[1].values, second[1].values])
    fit = fit_effect(combined, resim, train, params, config, start, None, max_evaluations=2 * config.max_evaluations)
    after = score_fit(fit, combined, resim, held, params, current, config)
    record = {"effects": [first[0].name, second[0].name], "values": fit.values, "status": fit.status}
    if fit.status != "ok":
        return record, None
    share = (float(current.mean()) - fit.gap_mean) / excess
    record.update(gap=fit.gap_mean, score=fit.score, excess_explained=share, p_value=fit.p_value)
    cut = len(first[1].values)
    values = (fit.values[:cut], fit.values[cut:])
    added = each_on_top_of_the_others(
        [(first[0], values[0]), (second[0], values[1])], resim, held, params, after, excess, significance, config
    )
    if added is None:
        return record, None
    record["on_top_of_the_other"] = added
    passes = passes_together(fit.p_value, share, added, significance, config)
    record["passes"] = passes
    if not passes:
        return record, None
    members = []
    for (effect, single), member_values, uncertainty in zip(
        (first, second), values, (fit.uncertainty[:cut], fit.uncertainty[cut:])
    ):
        named = CandidateFit(
            single.effect,
            single.names,
            single.units,
            [float(v) for v in member_values],
            list(uncertainty),
            fit.train_cost,
            gap=fit.gap,
            gap_mean=fit.gap_mean,
            explained_fraction=1.0 - fit.gap_mean / float(current.mean()),
            excess_explained=share,
            score=fit.score,
            p_value=fit.p_value,
            scope=single.scope,
            rejected=fit.rejected,
        )
        members.append((effect, named))
    return record, members


def each_on_top_of_the_others(
    members: list[tuple[Effect, list[float]]],
    resim: Resimulator,
    held: Windows,
    params: PhysicsParams,
    after: np.ndarray,
    excess: float,
    significance: float,
    config: FitConfig,
) -> list[dict] | None:
    """What each of `members` (effect, its values together with the others) adds on top of the others at their values,
    the simulator with all of them leaving the held-out gap `after`: its share of the gap above the floor `excess` and
    the p-value of that reduction; None where a simulation without one of them blows up."""
    added = []
    for i, (effect, _) in enumerate(members):
        others = members[:i] + members[i + 1 :]
        without_it = params
        for other, values in others:
            without_it = other.physics(values, without_it)
        try:
            without = gap_per_window(resim.spec, resim.rollout(held, without_it), held)
        except SimulationDiverged:
            return None
        p = paired_p_value(without.mean(1), after.mean(1), held, config.block_rows, significance)
        share = (float(without.mean()) - float(after.mean())) / excess
        added.append({"effect": effect.name, "excess_explained": share, "p_value": p})
    return added


def passes_together(p_value: float, share: float, added: list[dict], significance: float, config: FitConfig) -> bool:
    """The rule of effects named together: they explain `min_excess_explained` of the gap above the floor (`share`) at
    p < `significance`, and each still explains `rival_excess_explained` on top of the others at that p (`added`)."""
    return bool(
        p_value < significance
        and share >= config.min_excess_explained
        and all(a["excess_explained"] >= config.rival_excess_explained and a["p_value"] < significance for a in added)
    )

"""Fit named effects together: the joint candidates of a later step, the joint refit after each naming, and each
named effect's share of the explained gap.

At later steps some candidates are also fitted together with the effects named so far (`joint_candidates`: the best
of this step and of the step before); one that scores better so is judged (and named) with those refitted values.
From two named effects on, all their parameters are refitted together after each naming (`joint_refit`: least squares
from the sequential values, kept if the held-out gap does not grow), so the next step starts from the best simulator
with them: fitted one after the other, two effects that trade off (armature and an action delay) leave a misfit that a
third, spurious one would take up. Each named effect's share of the explained gap is its held-out gap reduction when
the effects are added in order at their final values (`effect_shares`).
"""

from __future__ import annotations

import itertools

import numpy as np

from rwm_gym.gap.effects import Effect
from rwm_gym.gap.fit import CandidateFit, FitConfig, fit_effect, gap_per_window, score_fit
from rwm_gym.gap.resim import Resimulator, SimulationDiverged, Windows
from rwm_gym.physics.params import PhysicsParams

Candidate = tuple[Effect, CandidateFit]


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
            combined, resim, train, base, config, start, None, max_evaluations=2 * config.max_evaluations
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
    fit = fit_effect(combined, resim, train, base, config, start, None, max_evaluations=2 * config.max_evaluations)
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

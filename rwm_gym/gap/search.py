"""The forward search: name effects one step at a time, each on top of the ones named before, until a step names
none.

Step k starts from the simulator with the k-1 effects named so far, and tests its held-out gap against that
simulator's own sensor-noise floor (`noise_floor`: a damped joint carries start noise less far than the nominal robot;
the nominal robot started from offset encoder readings carries it further). That test of the whole gap is weak where
an effect shows in a few windows only (a 0.5x torque limit, a small backlash), or where the held-out third holds few
blocks; so a step whose gap is not significantly above its floor still judges its candidates (`gap.step`). At step 1,
if none passes, the verdict is `none`. A later step whose gap is not significantly above its floor tests it again on
every episode (the fitting ones too, where the named effects were fitted: a conservative test) and stops where it is
not above the floor there either (at once where `FitConfig.near_the_floor_after_naming` is off).

A rival that stays alike after `judge.resolve_rivals` (neither holds the other) is followed with the best: each is
named in turn and selection runs to its end, and the branch that leaves clearly less is taken (`_look_ahead`,
`FitConfig.look_ahead`); else the step names nothing.

From two named effects on, all their parameters are refitted together after each naming (`refit.joint_refit`), so the
next step starts from the best simulator with them.
"""

from __future__ import annotations

import copy
from dataclasses import asdict, dataclass, field

import numpy as np

from rwm_gym.gap.fit import gap_per_window
from rwm_gym.gap.judge import best_of, ranked, resolve_rivals
from rwm_gym.gap.noise_floor import FloorConfig, compare_with_floor
from rwm_gym.gap.pairs import best_pair
from rwm_gym.gap.refit import Candidate, joint_refit, named_params
from rwm_gym.gap.resim import SimulationDiverged
from rwm_gym.gap.sets import best_set
from rwm_gym.gap.significance import paired_p_value
from rwm_gym.gap.step import Search, Step, judge_step
from rwm_gym.physics.params import PhysicsParams


@dataclass
class Path:
    """Where a forward selection stands: the named effects, the simulator with them and its held-out gap, the steps
    so far, the last step's candidates (ranked), the last joint refit, and why the last step decided as it did."""

    named: list[Candidate]
    params: PhysicsParams
    current: np.ndarray
    steps: list[dict]
    earlier: list[Candidate] = field(default_factory=list)
    refit: dict | None = None
    reason: str = ""

    def fork(self) -> Path:
        """A copy that naming and refitting on it leave this one as it is (they change the named fits' values)."""
        named = [(effect, copy.deepcopy(fit)) for effect, fit in self.named]
        steps = [dict(step) for step in self.steps]
        return Path(named, self.params, self.current, steps, list(self.earlier), self.refit, self.reason)


def forward(search: Search, base: PhysicsParams, before: np.ndarray) -> Path:
    """Forward selection from the simulator `base` (held-out gap `before`, (W, 3)) to its end, looking ahead where
    `FitConfig.look_ahead`."""
    return _forward(search, Path([], base, before, []), search.config.look_ahead)


def _forward(search: Search, path: Path, look_ahead: bool) -> Path:
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
        judged = judge_step(search, k, below, path.named, path.earlier, path.params, path.current, step_floor)
        path.earlier = ranked(judged.candidates)
        step["candidates"] = [asdict(f) for _, f in sorted(judged.candidates, key=lambda c: c[1].score, reverse=True)]
        pick, path.reason = _decide(search, judged, below, path.reason, path.named, path.params, path.current)
        step["decision"] = path.reason
        if judged.spread is not None:
            step["spread"] = judged.spread
        if pick is None and judged.rival is not None and not below and look_ahead:
            taken = _look_ahead(search, path, judged)
            if taken is not path:
                return taken
        if pick is None and not below and (_name_a_pair(search, path, judged) or _name_a_set(search, path, judged)):
            continue
        if pick is None:
            break
        _take(search, path, pick)
        if pick[1].spread is not None:
            path.reason = "its gap lies at its own noise floor, which no further effect can lower"
            break
    return path


def _take(search: Search, path: Path, pick: Candidate) -> None:
    """Name `pick` at `path`'s last step; from two named effects on, refit them together (`joint_refit`)."""
    path.steps[-1]["named"] = f"{pick[0].name} ({pick[0].scope})"
    path.params, path.current = _name(search, pick, path.named, path.params)
    if len(path.named) > 1:
        path.named, path.params, path.current, path.refit = joint_refit(
            path.named, search.resim, search.train, search.held, search.base, path.current, search.config
        )


def _name_a_set(search: Search, path: Path, step: Step) -> bool:
    """The step names nothing, its gap above the floor, and no pair passes: name a set built step by step that passes
    (`sets.best_set`), where there is room for two more; whether it did. The set's record joins the step's."""
    config = search.config
    room = config.max_effects - len(path.named)
    if not config.stepwise_sets or room < 2:
        return False
    remaining = {n: e for n, e in search.effects.items() if n not in {e.name for e, _ in path.named}}
    members, record = best_set(
        step.candidates,
        remaining,
        search.resim,
        search.train,
        search.held,
        path.params,
        path.current,
        float(np.nanmean(step.floor)),
        room,
        config,
    )
    path.steps[-1]["set"] = record
    if members is None:
        return False
    names = " + ".join(e.name for e, _ in members)
    path.reason = (
        f"{path.reason}; built step by step and fitted together, {names} explain {record['excess_explained']:.0%} of "
        f"the gap above the floor (p={record['p_value']:.2g}), and each on top of the others "
        + " and ".join(f"{a['excess_explained']:.0%}" for a in record["on_top_of_the_others"])
        + ": all are named"
    )
    path.steps[-1].update(decision=path.reason, named=" + ".join(f"{e.name} ({e.scope})" for e, _ in members))
    for member in members:
        path.params, path.current = _name(search, member, path.named, path.params)
    if len(path.named) > len(members):
        path.named, path.params, path.current, path.refit = joint_refit(
            path.named, search.resim, search.train, search.held, search.base, path.current, search.config
        )
    return True


def _name_a_pair(search: Search, path: Path, step: Step) -> bool:
    """The step names nothing, its gap above the floor: name two effects that pass together (`pairs.best_pair`), where
    there is room for two more; whether it did. The pair's record joins the step's."""
    config = search.config
    if not config.pair_candidates or len(path.named) + 2 > config.max_effects:
        return False
    floor = float(np.nanmean(step.floor))
    members, record = best_pair(
        step.candidates, search.resim, search.train, search.held, path.params, path.current, floor, config
    )
    path.steps[-1]["pairs"] = record
    if members is None:
        return False
    (first, fit), (second, _) = members
    tried = next(p for p in record["pairs"] if p["effects"] == [first.name, second.name])
    path.reason = (
        f"{path.reason}; fitted together, {first.name} and {second.name} explain {fit.excess_explained:.0%} of the "
        f"gap above the floor (p={fit.p_value:.2g}), and each on top of the other "
        + " and ".join(f"{a['excess_explained']:.0%}" for a in tried["on_top_of_the_other"])
        + ": both are named"
    )
    path.steps[-1].update(decision=path.reason, named=f"{first.name} ({first.scope}) + {second.name} ({second.scope})")
    for member in members:
        path.params, path.current = _name(search, member, path.named, path.params)
    if len(path.named) > 2:
        path.named, path.params, path.current, path.refit = joint_refit(
            path.named, search.resim, search.train, search.held, search.base, path.current, search.config
        )
    return True


def _look_ahead(search: Search, path: Path, step: Step) -> Path:
    """The step's best candidate and an unrelated rival explain the gap alike, and neither holds the other
    (`resolve_rivals`): name each in turn and follow selection to its end (without looking ahead again). The branch
    that leaves less of the gap above the step's floor is taken where the other leaves `ambiguity_ratio` more above
    it, on windows that are significantly worse (`paired_p_value`); else the step names nothing, as before. With
    several effects present, the one that mimics the first may explain as much alone, yet leave a misfit that none
    of the others takes up: armature, joint damping and a compliant floor on excitation data, where joint friction
    explained the gap as well as the damping at step 1 and on top of it the damping explained too little to hold it."""
    config, floor = search.config, float(np.nanmean(step.floor))
    best = best_of(step.candidates)
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
    search: Search, params: PhysicsParams, current: np.ndarray, floor: np.ndarray
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


def _decide(
    search: Search,
    step: Step,
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
        best = best_of(step.candidates)
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
    search: Search, pick: Candidate, named: list[Candidate], params: PhysicsParams
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

"""Per-leg scope: a joint effect with one value per leg, one more candidate for the decision.

A worn gearbox or a stiff seal sits in one leg, not in all twelve joints; fitted globally, such an effect may explain
too little to be named. So the best-scoring one-parameter joint effect (friction, damping, armature, motor strength,
torque limit, backlash) is also fitted with one value per leg (least squares from its global value, `fit.fit_effect`)
and scored on the same held-out windows with the same rule: every parameter beyond the first inflates the remaining gap
by `FitConfig.penalty_per_parameter`. `fit.decide` names the per-leg form only when its penalised score beats every
other candidate's, its own global form included, so a global effect stays global.

Legs are read from the actuated joints' names in the task spec: the prefix before the first "_" (ANYmal D: LF, RF, LH,
RH, three joints each). A spec without such a grouping (fewer than two groups, or a group of one joint) has no per-leg
scope.
"""

from __future__ import annotations

import numpy as np

from rwm_gym.gap.effects import Effect, Parameter
from rwm_gym.gap.fit import CandidateFit, FitConfig, fit_effect, score_fit
from rwm_gym.gap.resim import Resimulator, Windows
from rwm_gym.physics.params import PhysicsParams
from rwm_gym.spec import TaskSpec

JOINT_EFFECTS: tuple[str, ...] = ("joint_friction", "joint_damping", "armature", "motor_strength", "torque_limit",
                                  "backlash")
"""Effects of one number applied to every actuated joint (a per-joint `PhysicsParams` field)."""


def leg_groups(spec: TaskSpec) -> dict[str, list[int]]:
    """Leg name -> indices of its actuated joints (spec order); {} when the joint names do not group into legs."""
    groups: dict[str, list[int]] = {}
    for i, joint in enumerate(spec.actuator.joints):
        if "_" not in joint:
            return {}
        groups.setdefault(joint.split("_", 1)[0], []).append(i)
    if len(groups) < 2 or min(len(g) for g in groups.values()) < 2:
        return {}
    return groups


def per_leg(effect: Effect, spec: TaskSpec) -> Effect | None:
    """`effect` with one parameter per leg (named `<parameter>_<leg>`), or None if it has no per-leg form."""
    groups = leg_groups(spec)
    if effect.name not in JOINT_EFFECTS or len(effect.parameters) != 1 or not groups:
        return None
    p = effect.parameters[0]
    (field,) = effect.apply(np.array([p.default])).keys()
    joints = len(spec.actuator.joints)

    def apply(values: np.ndarray) -> dict[str, object]:
        per_joint = np.empty(joints)
        for value, ids in zip(values, groups.values()):
            per_joint[ids] = value
        return {field: tuple(float(v) for v in per_joint)}

    parameters = tuple(Parameter(f"{p.name}_{leg}", p.unit, p.nominal, p.low, p.high, p.default, p.step)
                       for leg in groups)
    return Effect(effect.name, f"{effect.description} (one value per leg)", parameters, apply, scope="leg",
                  nested_in=effect.nested_in)


def per_leg_candidate(fits: list[CandidateFit], effects: dict[str, Effect], spec: TaskSpec, resim: Resimulator,
                      train: Windows, heldout: Windows, base: PhysicsParams, before: np.ndarray,
                      config: FitConfig) -> tuple[Effect, CandidateFit] | None:
    """The per-leg form of the best-scoring global joint effect among `fits`, fitted from its global value on every
    leg and scored on the held-out windows; None if no candidate has a per-leg form or none reduces the gap.

    Whether it is named is `fit.decide`'s call, with the penalty for its extra parameters."""
    ranked = sorted((f for f in fits if f.scope == "global" and f.explained_fraction > 0), key=lambda f: -f.score)
    for fit in ranked:
        leg_effect = per_leg(effects[fit.effect], spec)
        if leg_effect is None:
            continue
        p = effects[fit.effect].parameters[0]
        start = np.full(len(leg_effect.parameters), fit.values[0])
        leg_fit = fit_effect(leg_effect, resim, train, base, config, start, (p.low, p.high))
        score_fit(leg_fit, leg_effect, resim, heldout, base, before, config)
        return leg_effect, leg_fit
    return None

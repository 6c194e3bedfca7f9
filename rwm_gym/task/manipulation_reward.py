"""The rewards and success of `dm_control.manipulation` tasks as pure functions of the world-model state.

A manipulation spec's `[manipulation]` table names the goal and its numbers (dm_control's own figures, written there by
`rwm-gym spec --from-dmc manipulation-TASK`):

- `goal = "reach"` (reach_site_features): d = |pinch site - target site|; reward = dm_control's
  `rewards.tolerance(d, bounds=(0, target_radius), margin=target_radius)` (its default Gaussian: 1 within
  `target_radius` of the target, 0.1 at twice that). Exact: both sites are in the state.
- `goal = "lift"` (lift_brick_features): h = height of the brick's lowest corner (its vertex sites, placed by the
  brick's predicted position and rotation); reward = `rewards.tolerance(h, bounds=(rest_height + lift_distance,
  inf), margin=lift_distance, value_at_margin=0, sigmoid="linear")`: 0 at rest, 1 from `lift_distance` above.
  dm_control takes the rest height of each episode's settled brick; the state has no memory of the episode's start,
  so the spec's `rest_height` (the settled brick's, measured) stands in for it.

Success is the reward at its maximum, `GOAL_REWARD`: both rewards are exactly 1 when the goal is met and below 1
otherwise, so the physics env (dm_control's reward) and the imagined env (this module's) judge it alike.
`tests/test_manipulation.py` measures these rewards against dm_control's in physics.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from rwm_gym.spec import TaskSpec

GOAL_REWARD = 1.0
"""The reward of a step at which the goal is met (dm_control's manipulation rewards are at most 1)."""


@dataclass(frozen=True)
class ReachGoal:
    """Bring a hand site within `target_radius` of a target site (spec `[manipulation] goal = "reach"`)."""

    hand_site: str
    target_site: str
    target_radius: float
    """m, dm_control's target radius (the tolerance's bounds and margin)."""


@dataclass(frozen=True)
class LiftGoal:
    """Lift a free body's lowest vertex `lift_distance` above its rest (spec `[manipulation] goal = "lift"`)."""

    prop_body: str
    vertex_sites: tuple[str, ...]
    """The body's corner sites; their offsets in the body frame come from dm_control's model."""
    lift_distance: float
    """m, the height above rest at which the reward reaches 1."""
    rest_height: float
    """m, the lowest vertex's height of the brick resting on the table after dm_control settles it."""


_FIELDS = {"reach": ReachGoal, "lift": LiftGoal}


def manipulation_goal(spec: TaskSpec) -> ReachGoal | LiftGoal:
    """The spec's `[manipulation]` table as a goal; a one-line ValueError if it is missing or malformed."""
    table = spec.extra.get("manipulation")
    if not isinstance(table, dict):
        raise ValueError(f"task spec {spec.name}: a dm_control.manipulation task needs a [manipulation] table (goal)")
    goal = table.get("goal")
    if goal not in _FIELDS:
        raise ValueError(f"task spec {spec.name}: [manipulation] goal {goal!r} unknown (choose from reach, lift)")
    cls = _FIELDS[goal]
    names = set(cls.__dataclass_fields__)
    values = {k: v for k, v in table.items() if k != "goal"}
    if missing := sorted(names - set(values)):
        raise ValueError(f"task spec {spec.name}: [manipulation] field {missing[0]!r} missing for goal {goal!r}")
    if unknown := sorted(set(values) - names):
        raise ValueError(f"task spec {spec.name}: [manipulation] unknown field {unknown[0]!r} for goal {goal!r}")
    if "vertex_sites" in values:
        values["vertex_sites"] = tuple(values["vertex_sites"])
    return cls(**values)


def _columns(spec: TaskSpec, group: str, name: str, components: str | tuple[str, ...]) -> list[int]:
    """State indices of `group/name:c` for each component c; a one-line ValueError naming the first one missing."""
    out = []
    for c in components:
        column = f"{group}/{name}:{c}"
        if column not in spec.state_columns:
            raise ValueError(f"task spec {spec.name}: the [manipulation] goal needs state column {column!r}")
        out.append(spec.state_columns.index(column))
    return out


class ManipulationReward:
    """The goal's reward and success for a batch: `reward(state, foot_height, action) -> (N,)`, `success(state)`.

    state (N, S) SI units after the step; foot_height and action are accepted for the suite rewards' signature and
    not read (the manipulation rewards depend on the state alone).
    """

    success_reward = GOAL_REWARD
    """The reward at which a step counts as a success."""

    held_columns: tuple[int, ...] = ()
    """State columns the goal fixes for a whole episode (a reach's target site): the imagined env holds them at their
    value in the real history an episode starts from, as it holds a legged robot's command, instead of letting the
    model's prediction drift (the arm's dynamics do not depend on them)."""

    def __init__(self, spec: TaskSpec):
        self.spec, self.goal = spec, manipulation_goal(spec)
        if isinstance(self.goal, ReachGoal):
            self._hand = _columns(spec, "site_pos", self.goal.hand_site, "xyz")
            self._target = _columns(spec, "site_pos", self.goal.target_site, "xyz")
            self.held_columns = tuple(self._target)
        else:
            self._height = _columns(spec, "body_pos", self.goal.prop_body, "z")[0]
            self._up = _columns(spec, "body_rot", self.goal.prop_body, ("zx", "zy", "zz"))
            self._vertices = self._vertex_offsets(spec)

    def _vertex_offsets(self, spec: TaskSpec) -> np.ndarray:
        """m, (V, 3) the vertex sites' positions in the prop's frame, read from dm_control's model."""
        from rwm_gym.spec import SuiteTask
        from rwm_gym.task.dmc_environments import load_environment

        params = SuiteTask.from_spec(spec)
        env = load_environment(params.domain, params.task)  # held while its model is read (composer holds weakly)
        model = env.physics.model.ptr
        body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, self.goal.prop_body)
        sites = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, name) for name in self.goal.vertex_sites]
        if body < 0 or min(sites) < 0 or any(model.site_bodyid[s] != body for s in sites):
            raise ValueError(
                f"task spec {spec.name}: [manipulation] vertex_sites must be sites of body {self.goal.prop_body!r}"
            )
        return model.site_pos[sites].copy()

    def __call__(self, state: np.ndarray, foot_height: np.ndarray | None = None, action=None) -> np.ndarray:
        from dm_control.utils import rewards

        state = np.asarray(state, dtype=np.float64)
        if isinstance(self.goal, ReachGoal):
            distance = np.linalg.norm(state[:, self._hand] - state[:, self._target], axis=1)
            radius = self.goal.target_radius
            return np.asarray(rewards.tolerance(distance, bounds=(0.0, radius), margin=radius), dtype=np.float64)
        lowest = self.lowest_vertex_height(state)
        lift = self.goal.lift_distance
        reward = rewards.tolerance(
            lowest,
            bounds=(self.goal.rest_height + lift, np.inf),
            margin=lift,
            value_at_margin=0,
            sigmoid="linear",
        )
        return np.asarray(reward, dtype=np.float64)

    def lowest_vertex_height(self, state: np.ndarray) -> np.ndarray:
        """m, (N,) the height of the prop's lowest vertex: z + min over vertices of (world z in the prop frame) . v."""
        state = np.asarray(state, dtype=np.float64)
        return state[:, self._height] + (state[:, self._up] @ self._vertices.T).min(axis=1)

    def success(self, state: np.ndarray) -> np.ndarray:
        """(N,) bool, the goal met: the reward at `GOAL_REWARD`."""
        return self(state) >= GOAL_REWARD

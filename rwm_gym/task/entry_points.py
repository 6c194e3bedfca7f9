"""Reward and termination given as functions of the predicted transition, for tasks the package has no code for.

A spec names them in an `[imagination]` table, as Gymnasium names env classes (an importable `module:function`):

    [imagination]
    reward = "my_robot.rewards:swingup"          # f(transition) -> (N,) float, the reward of each env's step
    termination = "my_robot.rewards:fell"        # f(transition) -> (N,) bool, which episodes end

or the imagined env takes them as arguments, `ImaginedEnv(checkpoint, reward_fn=f, termination_fn=g)` (mbrl-lib's
`ModelEnv` idea); an argument wins over the spec. Importing a module runs its code, and a spec also travels
inside every dataset and checkpoint, so a file handed over could name any module: the spec's entry points are
imported only when the user opts in (`trust_entry_points=True`, `--trust-entry-points`); otherwise naming one is a
one-line error that says which module it would import. `Transition` is what the functions see, in SI units, with
the columns by name.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from rwm_gym.spec import TaskSpec

TABLE = "imagination"
KEYS = ("reward", "termination")


@dataclass(frozen=True)
class Transition:
    """One imagined step of N envs: state --action--> next_state, with the predicted privileged signals."""

    spec: TaskSpec
    state: np.ndarray
    """(N, S) before the step, SI units, columns `spec.state_columns`."""
    action: np.ndarray
    """(N, A) in [-1, 1]."""
    next_state: np.ndarray
    """(N, S) predicted after the step."""
    contact: np.ndarray
    """(N, C) bool, predicted contact flags after the step (`spec.privileged.contact_bodies`)."""
    foot_height: np.ndarray
    """(N, F) m, predicted foot heights after the step."""
    command: np.ndarray
    """(N, K) the commands in force (K = 0 for tasks without commands)."""
    last_action: np.ndarray
    """(N, A) the action of the step before."""

    def column(self, name: str, *, before: bool = False) -> np.ndarray:
        """(N,) the state column "group/column" (e.g. "joint_cos/shoulder") after the step (before, if asked)."""
        if name not in self.spec.state_columns:
            raise KeyError(
                f"{self.spec.name} has no state column {name!r} (columns: {', '.join(self.spec.state_columns)})"
            )
        index = self.spec.state_columns.index(name)
        return (self.state if before else self.next_state)[:, index]


StepFunction = Callable[[Transition], np.ndarray]


def load_entry_point(target: str, what: str) -> StepFunction:
    """The function that "module:function" names; a ValueError of one line when it cannot be had."""
    module_name, sep, attr = str(target).partition(":")
    if not sep or not module_name or not attr:
        raise ValueError(f"{what} entry point {target!r}: expected 'module:function'")
    try:
        module = importlib.import_module(module_name)
    except ImportError as err:
        raise ValueError(f"{what} entry point {target!r}: cannot import {module_name!r} ({err})") from None
    function = module
    for part in attr.split("."):
        function = getattr(function, part, None)
    if not callable(function):
        raise ValueError(f"{what} entry point {target!r}: {module_name} has no function {attr!r}")
    return function


def spec_entry_points(spec: TaskSpec) -> dict[str, str]:
    """The spec's `[imagination]` entry points ({"reward": ..., "termination": ...}, either may be absent)."""
    table = spec.extra.get(TABLE, {})
    if not isinstance(table, dict):
        raise ValueError(f"task spec {spec.name}: [{TABLE}] must be a table")
    unknown = sorted(set(table) - set(KEYS))
    if unknown:
        raise ValueError(f"task spec {spec.name}: [{TABLE}] unknown field {unknown[0]!r} (known: {', '.join(KEYS)})")
    for key, value in table.items():
        if not isinstance(value, str):
            raise ValueError(f"task spec {spec.name}: [{TABLE}] {key} must be a 'module:function' string")
    return dict(table)


def step_functions(
    spec: TaskSpec,
    reward_fn: StepFunction | None = None,
    termination_fn: StepFunction | None = None,
    *,
    trust: bool = False,
    source: str = "the task spec",
) -> tuple[StepFunction | None, StepFunction | None]:
    """(reward function, termination function): the arguments where given, else the spec's entry points (imported only
    if `trust`; `source` names the file the spec came from in the error), else None."""
    named = spec_entry_points(spec)
    given = {"reward": reward_fn, "termination": termination_fn}
    for what, target in named.items():
        if given[what] is None and not trust:
            module = target.partition(":")[0]
            raise ValueError(
                f"{source} names the {what} entry point {target!r}, which would import and run module "
                f"{module!r}: pass trust_entry_points=True (--trust-entry-points) if you trust it, "
                f"or {what}_fn="
            )
    if reward_fn is None and "reward" in named:
        reward_fn = load_entry_point(named["reward"], "reward")
    if termination_fn is None and "termination" in named:
        termination_fn = load_entry_point(named["termination"], "termination")
    return reward_fn, termination_fn


def call(function: StepFunction, transition: Transition, what: str, dtype: type) -> np.ndarray:
    """function(transition) checked to be one finite value per env, as `dtype`."""
    n = len(transition.next_state)
    out = np.asarray(function(transition))
    if out.shape not in ((n,), (n, 1)):
        raise ValueError(
            f"{what} function {getattr(function, '__name__', function)!r} returned shape {out.shape}, expected ({n},)"
        )
    out = out.reshape(n).astype(dtype)
    if dtype is not bool and not np.all(np.isfinite(out)):
        raise ValueError(f"{what} function {getattr(function, '__name__', function)!r} returned NaN or inf")
    return out

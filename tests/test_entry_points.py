"""Reward and termination as functions of the predicted transition: entry points in a spec, and their errors."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from rwm_gym.cli import main
from rwm_gym.data.collect import collect
from rwm_gym.spec import load_spec, parse_spec
from rwm_gym.task.entry_points import Transition, load_entry_point, step_functions


def _transitions(data) -> Transition:
    spec, starts = data.spec(), np.ones(data.num_steps, dtype=bool)
    starts[data.episode_starts] = False  # rows that follow a transition
    rows = np.flatnonzero(starts)
    return Transition(
        spec,
        data["state"][rows - 1],
        data["action"][rows - 1],
        data["state"][rows],
        data["contact"][rows],
        data["foot_height"][rows],
        data["command"][rows - 1],
        data["action"][rows - 2] * (rows - 2 >= 0)[:, None],
    ), rows


def test_the_acrobot_reward_entry_point_equals_the_suite_reward_on_real_states(tmp_path: Path) -> None:
    from rwm_gym.data.dataset import Dataset

    spec = tmp_path / "acrobot.toml"
    assert main(["spec", "--from-dmc", "acrobot-swingup", "--out", str(spec), "--episodes", "2", "--steps", "20"]) == 0
    data = Dataset.load(collect(str(spec), "random", 2, tmp_path / "a.h5", max_steps=40, progress=False))
    transition, rows = _transitions(data)
    reward = load_entry_point("tests.acrobot_reward:swingup", "reward")(transition)
    np.testing.assert_allclose(reward, data["reward"][rows - 1], atol=1e-5)


def test_entry_points_come_from_the_spec_and_arguments_win() -> None:
    base = load_spec("dmc_finger_spin")
    spec = parse_spec(base.text + '\n[imagination]\nreward = "tests.acrobot_reward:swingup"\n')
    reward, termination = step_functions(spec, trust=True)
    assert reward.__name__ == "swingup" and termination is None

    def mine(t):
        return np.zeros(len(t.next_state))

    assert step_functions(spec, reward_fn=mine)[0] is mine


@pytest.mark.parametrize(
    "table, message",
    [
        ('reward = "no_such_module_xyz:f"', "cannot import 'no_such_module_xyz'"),
        ('reward = "tests.acrobot_reward:nothing"', "has no function 'nothing'"),
        ('reward = "just_a_name"', "expected 'module:function'"),
        ('rewards = "tests.acrobot_reward:swingup"', "unknown field 'rewards'"),
    ],
)
def test_bad_entry_points_fail_in_one_line(table: str, message: str) -> None:
    spec = parse_spec(load_spec("dmc_finger_spin").text + f"\n[imagination]\n{table}\n")
    with pytest.raises(ValueError, match=message) as err:
        step_functions(spec, trust=True)
    assert "\n" not in str(err.value)


def test_transition_columns_by_name() -> None:
    spec = load_spec("dmc_finger_spin")
    state = np.arange(2 * spec.state_dim, dtype=float).reshape(2, -1)
    t = Transition(
        spec,
        state,
        np.zeros((2, 2)),
        state + 100,
        np.zeros((2, 0), bool),
        np.zeros((2, 0)),
        np.zeros((2, 0)),
        np.zeros((2, 2)),
    )
    k = spec.state_columns.index("joint_vel/hinge")
    np.testing.assert_array_equal(t.column("joint_vel/hinge"), state[:, k] + 100)
    np.testing.assert_array_equal(t.column("joint_vel/hinge", before=True), state[:, k])
    with pytest.raises(KeyError, match="no state column"):
        t.column("nope/x")
    assert replace(t, command=np.ones((2, 0))).command.shape == (2, 0)

"""SHAC through the world model: gradients reach the actor through predicted states, the run folder resumes, and the
saved policy is an ordinary SB3 zip that `rwm-gym score` reads."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import torch

from rwm_gym.cli import main as cli
from rwm_gym.imagination.core import ImaginationOptions, ImaginedCore
from rwm_gym.rl.ppo import make_ppo
from rwm_gym.rl.shac import SHAC, DifferentiableImagination, SHACConfig
from rwm_gym.vector.sb3_vec_env import CoreSB3VecEnv


def _learner(num_envs: int = 8, horizon: int = 4, **options) -> SHAC:
    core = ImaginedCore(None, num_envs, options=ImaginationOptions(episode_steps=20, **options))
    imagination = DifferentiableImagination(core)
    imagination.reset(np.arange(num_envs), list(range(num_envs)))
    config = SHACConfig(num_envs=num_envs, horizon=horizon, critic_iterations=2, critic_minibatches=2)
    return SHAC(imagination, make_ppo(CoreSB3VecEnv(core), config.ppo_config(), seed=0).policy, config, seed=0)


def test_the_return_gradient_reaches_the_actions_through_the_model():
    learner = _learner()
    imagination = learner.imagination
    imagination.detach()
    action = torch.zeros((8, 12), requires_grad=True)
    imagination.step(action)  # the reward of step 1 does not see the action's effect on the next state's velocity
    reward, _, _ = imagination.step(torch.zeros((8, 12)))
    reward.sum().backward()
    assert action.grad is not None and action.grad.abs().sum() > 0  # only through the predicted state


def test_an_update_moves_the_actor_and_the_critic_and_reports_its_gradient():
    learner = _learner()
    actor_before = learner.policy.action_net.weight.detach().clone()
    critic_before = learner.policy.value_net.weight.detach().clone()
    stats = learner.update()
    assert stats.timesteps == 8 * 4 and np.isfinite(stats.imagined_return) and stats.actor_grad_norm > 0
    assert not torch.equal(learner.policy.action_net.weight, actor_before)
    assert not torch.equal(learner.policy.value_net.weight, critic_before)


def test_options_shac_cannot_step_are_refused():
    core = ImaginedCore(None, 2, options=ImaginationOptions(uncertainty_penalty=1.0))
    with pytest.raises(ValueError, match="uncertainty penalty and halt"):
        DifferentiableImagination(core)


def test_cli_trains_resumes_and_writes_a_policy_that_score_reads(tmp_path):
    run = tmp_path / "run"
    command = [
        "shac",
        "--num-envs",
        "8",
        "--horizon",
        "4",
        "--critic-iterations",
        "1",
        "--episode-steps",
        "20",
        "--fall-tilt",
        "30",
        "--run-dir",
        str(run),
        "--snapshot-every",
        "2",
        "--save-every",
        "2",
        "--threads",
        "1",
        "--out",
        str(tmp_path / "policy.zip"),
    ]
    assert cli([*command, "--timesteps", "64"]) == 0
    assert json.loads((run / "state.json").read_text())["timesteps"] == 64
    assert cli([*command, "--timesteps", "128"]) == 0  # continues the same run to the larger budget
    rows = list(csv.DictReader((run / "log.csv").open()))
    assert [int(r["timesteps"]) for r in rows] == list(range(32, 129, 32))
    assert sorted(p.name for p in (run / "snapshots").glob("*.zip")) == ["step_0.zip", "step_64.zip"]
    with pytest.raises(SystemExit, match="other settings"):
        cli([*command[:4], "8", *command[5:], "--timesteps", "256"])  # another horizon
    assert (
        cli(
            [
                "score",
                "--policy",
                str(tmp_path / "policy.zip"),
                "--out",
                str(tmp_path / "score"),
                "--seeds",
                "1",
                "--steps",
                "20",
            ]
        )
        == 0
    )
    assert json.loads((tmp_path / "score" / "score.json").read_text())["episodes"] == 18

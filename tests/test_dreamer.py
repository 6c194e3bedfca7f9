"""The Dreamer-style learner: lambda-returns with auto-reset, updates that move the actor and the critic (through the
model, or by REINFORCE without it), the same numbers for the same seed, and a resumable command whose policy
`rwm-gym score` reads."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import torch

from rwm_gym.cli import main as cli
from rwm_gym.imagination.core import ImaginationOptions, ImaginedCore
from rwm_gym.rl.dreamer import Dreamer, DreamerConfig, lambda_returns
from rwm_gym.rl.ppo import make_ppo
from rwm_gym.rl.shac import DifferentiableImagination
from rwm_gym.vector.sb3_vec_env import CoreSB3VecEnv


def _learner(num_envs: int = 8, horizon: int = 4, seed: int = 0, **settings) -> Dreamer:
    core = ImaginedCore(None, num_envs, options=ImaginationOptions(episode_steps=20, fall_tilt=30))
    imagination = DifferentiableImagination(core)
    imagination.reset(np.arange(num_envs), list(range(num_envs)))
    config = DreamerConfig(num_envs=num_envs, horizon=horizon, critic_iterations=2, critic_minibatches=2, **settings)
    policy = make_ppo(CoreSB3VecEnv(core), config.ppo_config(), seed=seed).policy
    return Dreamer(imagination, policy, config, seed=seed)


def test_lambda_returns_stop_at_terminations_and_bootstrap_truncations():
    rewards = torch.tensor([[1.0], [1.0], [1.0]])
    values = torch.tensor([[10.0], [20.0], [30.0]])
    false, true = torch.tensor([False]), torch.tensor([True])
    alive = torch.stack([false, false, false])
    one_step = lambda_returns(rewards, values, alive, alive, gamma=0.5, lam=0.0)
    assert one_step[:, 0].tolist() == [6.0, 11.0, 16.0]  # r + gamma v(next)
    monte_carlo = lambda_returns(rewards, values, alive, alive, gamma=0.5, lam=1.0)
    assert monte_carlo[:, 0].tolist() == [1 + 0.5 * (1 + 0.5 * 16.0), 1 + 0.5 * 16.0, 16.0]
    ends = torch.stack([false, true, false])
    fell = lambda_returns(rewards, values, ends, ends, 0.5, 1.0)
    assert fell[1, 0] == 1.0 and fell[0, 0] == 1.5  # nothing after the fall, nothing from the next episode
    timed_out = lambda_returns(rewards, values, alive, ends, 0.5, 1.0)
    assert timed_out[1, 0] == 11.0 and timed_out[0, 0] == 1 + 0.5 * 11.0  # its own next value, not the next episode


@pytest.mark.parametrize("gradient", ["dynamics", "reinforce"])
def test_an_update_moves_actor_and_critic_and_reports_where_it_stands(gradient):
    learner = _learner(actor_gradient=gradient)
    actor = learner.policy.action_net.weight.detach().clone()
    critic = learner.policy.value_net.weight.detach().clone()
    slow = next(learner.slow_critic.parameters()).detach().clone()
    stats = learner.update()
    assert stats.timesteps == 8 * 4 and np.isfinite(stats.imagined_return) and stats.actor_grad_norm > 0
    assert stats.return_scale > 0 and stats.entropy > 0 and 0 <= stats.fraction_terminated <= 1
    assert not torch.equal(learner.policy.action_net.weight, actor)
    assert not torch.equal(learner.policy.value_net.weight, critic)
    assert not torch.equal(next(learner.slow_critic.parameters()), slow)  # the slow critic follows


def test_the_dynamics_gradient_goes_through_the_model_and_reinforce_does_not():
    dynamics, reinforce = _learner(actor_gradient="dynamics"), _learner(actor_gradient="reinforce")
    assert dynamics._rollout()["reward"].requires_grad
    assert not reinforce._rollout()["reward"].requires_grad


def test_the_same_seed_gives_the_same_updates_and_another_seed_does_not():
    first, second, other = _learner(seed=3), _learner(seed=3), _learner(seed=4)
    runs = [[learner.update() for _ in range(2)] for learner in (first, second, other)]
    assert runs[0] == runs[1]
    assert runs[0][-1].imagined_return != runs[2][-1].imagined_return


def test_bad_settings_are_one_line_errors():
    with pytest.raises(ValueError, match=r"DreamerConfig\.horizon must be >= 1"):
        DreamerConfig(horizon=0)
    with pytest.raises(ValueError, match="actor_gradient"):
        DreamerConfig(actor_gradient="evolution")
    assert cli(["dreamer", "--run-dir", "r", "--timesteps", "64", "--return-lambda", "1.5"]) == 2


def test_cli_trains_resumes_scores_and_writes_a_policy_that_score_reads(tmp_path):
    run, policy = tmp_path / "run", tmp_path / "policy.zip"
    command = ["dreamer", "--num-envs", "8", "--horizon", "4", "--critic-iterations", "1", "--episode-steps", "20"]
    command += ["--fall-tilt", "30", "--run-dir", str(run), "--snapshot-every", "2", "--save-every", "2"]
    command += ["--threads", "1", "--score-seeds", "1", "--score-steps", "10", "--out", str(policy)]
    assert cli([*command, "--timesteps", "64"]) == 0
    assert json.loads((run / "state.json").read_text())["timesteps"] == 64
    assert cli([*command, "--timesteps", "128"]) == 0  # continues the same run to the larger budget
    rows = list(csv.DictReader((run / "log.csv").open()))
    assert [int(r["timesteps"]) for r in rows] == list(range(32, 129, 32))
    assert {"actor_grad_norm", "imagined_return", "return_scale", "entropy"} <= set(rows[0])
    report = json.loads(policy.with_suffix(".json").read_text())
    assert report["imagined_steps"] == 128 and report["physics"]["episodes"] == 18
    assert report["last_update"]["timesteps"] == 128
    with pytest.raises(SystemExit, match="other settings"):
        cli([*command, "--timesteps", "256", "--return-lambda", "0.5"])
    fresh = [str(tmp_path / "fresh") if part == str(run) else part for part in command]
    with pytest.raises(SystemExit, match=r"policy\.zip") as refused:  # a new run may not replace another's policy
        cli([*fresh, "--timesteps", "64"])
    assert refused.value.code == 2
    for written in (run / "latest.zip", run / "latest_dreamer.pt", policy, policy.with_suffix(".json")):
        written.unlink()  # as if killed before its first resume point: the folder is still the run's to start again
    assert cli([*command, "--timesteps", "64"]) == 0 and policy.is_file()
    score = ["score", "--policy", str(policy), "--out", str(tmp_path / "score"), "--seeds", "1", "--steps", "10"]
    assert cli(score) == 0
    assert json.loads((tmp_path / "score" / "score.json").read_text())["episodes"] == 18

"""A robot the package does not ship, from files alone: spec -> collect -> train -> evaluate -> PPO in imagination.

Both paths of `rwm-gym spec` on tiny budgets, through the CLI as a user would: a legged MJCF written here, and a
dm_control domain that does not ship (acrobot-swingup) with its reward as an entry point on the predicted state.
"""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import numpy as np
from stable_baselines3 import PPO

import rwm_gym  # noqa: F401  (registers the envs)
from rwm_gym.cli import main
from tests.legged_mjcf import quadruped_xml

TINY_TRAIN = [
    "--iterations",
    "4",
    "--history",
    "4",
    "--forecast",
    "2",
    "--batch-size",
    "8",
    "--hidden-size",
    "16",
    "--num-layers",
    "1",
    "--head-hidden",
    "16",
    "--val-fraction",
    "0.25",
    "--quiet",
]


def _world_model(spec: Path, folder: Path, capsys) -> Path:
    """collect, train and evaluate through the CLI; returns the checkpoint."""
    data, ckpt = folder / "data.h5", folder / "model.safetensors"
    assert (
        main(
            [
                "collect",
                "--env",
                str(spec),
                "--policy",
                "random",
                "--episodes",
                "4",
                "--num-envs",
                "2",
                "--max-steps",
                "30",
                "--out",
                str(data),
            ]
        )
        == 0
    )
    assert main(["train", "--data", str(data), "--out", str(ckpt), *TINY_TRAIN]) == 0
    assert (
        main(
            [
                "evaluate",
                "--checkpoint",
                str(ckpt),
                "--data",
                str(data),
                "--history",
                "4",
                "--horizons",
                "2",
                "--max-horizon",
                "4",
                "--all-episodes",
                "--quiet",
            ]
        )
        == 0
    )
    assert "rwm on" in capsys.readouterr().out
    return ckpt


def _ppo_in_imagination(ckpt: Path) -> float:
    """A few-thousand-step SB3 PPO in the imagined env; returns the mean imagined reward per step it saw."""
    env = gym.make("rwm_gym:Imagined-v0", checkpoint=str(ckpt), episode_steps=64, trust_entry_points=True)
    model = PPO("MlpPolicy", env, n_steps=256, batch_size=64, n_epochs=2, seed=0, device="cpu")
    model.learn(total_timesteps=2048)
    obs, _ = env.reset(seed=1)
    rewards = []
    for _ in range(20):
        obs, reward, terminated, truncated, _ = env.step(model.predict(obs, deterministic=True)[0])
        rewards.append(reward)
        if terminated or truncated:
            obs, _ = env.reset()
    assert np.all(np.isfinite(rewards))
    return float(np.mean(rewards))


def test_a_legged_mjcf_from_nothing_to_ppo_in_imagination(tmp_path: Path, capsys) -> None:
    (tmp_path / "robot.xml").write_text(quadruped_xml())
    spec = tmp_path / "robot.toml"
    assert (
        main(["spec", "--mjcf", str(tmp_path / "robot.xml"), "--out", str(spec), "--episodes", "2", "--steps", "30"])
        == 0
    )
    ckpt = _world_model(spec, tmp_path, capsys)
    env = gym.make("rwm_gym:Imagined-v0", checkpoint=str(ckpt))
    assert env.unwrapped.task_spec.imagined_env_id == "RWM-TinyQuad-v0"
    assert env.observation_space == gym.make("rwm_gym:Physics-v0", spec=str(spec)).observation_space
    _ppo_in_imagination(ckpt)


def test_a_dm_control_domain_that_does_not_ship_from_nothing_to_ppo_in_imagination(tmp_path: Path, capsys) -> None:
    spec = tmp_path / "acrobot.toml"
    assert main(["spec", "--from-dmc", "acrobot-swingup", "--out", str(spec), "--episodes", "2", "--steps", "30"]) == 0
    assert "[imagination] reward" in capsys.readouterr().out  # it says the reward needs a function
    with spec.open("a") as f:
        f.write('\n[imagination]\nreward = "tests.acrobot_reward:swingup"\n')
    ckpt = _world_model(spec, tmp_path, capsys)
    assert np.isfinite(_ppo_in_imagination(ckpt))


def test_the_imagined_env_takes_reward_and_termination_functions_and_says_when_it_has_none(tmp_path: Path) -> None:
    spec = tmp_path / "acrobot.toml"
    assert main(["spec", "--from-dmc", "acrobot-swingup", "--out", str(spec), "--episodes", "1", "--steps", "10"]) == 0
    data, ckpt = tmp_path / "data.h5", tmp_path / "model.safetensors"
    assert (
        main(
            [
                "collect",
                "--env",
                str(spec),
                "--policy",
                "random",
                "--episodes",
                "2",
                "--max-steps",
                "20",
                "--out",
                str(data),
            ]
        )
        == 0
    )
    assert main(["train", "--data", str(data), "--out", str(ckpt), *TINY_TRAIN]) == 0
    try:
        gym.make("rwm_gym:Imagined-v0", checkpoint=str(ckpt))
        raise AssertionError("an imagined acrobot without a reward function was made")
    except ValueError as err:
        assert "reward_fn=" in str(err) and "\n" not in str(err)

    def upright(t):  # a reward of one's own: the cosine of the shoulder angle
        return t.column("joint_cos/shoulder")

    def after_five(t):
        after_five.calls += 1
        return np.full(len(t.next_state), after_five.calls >= 5)

    after_five.calls = 0
    env = gym.make(
        "rwm_gym:Imagined-v0", checkpoint=str(ckpt), reward_fn=upright, termination_fn=after_five, divergence_bound=1e9
    )  # a 4-iteration model may leave the normal range; score it anyway
    obs, _ = env.reset(seed=0)
    for step in range(1, 6):
        obs, reward, terminated, _, _ = env.step(env.action_space.sample())
        assert np.isclose(reward, obs[0], atol=1e-6)  # joint_cos/shoulder is the observation's first column
        assert terminated == (step == 5)

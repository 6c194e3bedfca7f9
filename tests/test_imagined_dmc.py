"""RWM-<Domain>-v0: the imagined dm_control envs, checked over every id with a tiny model trained here per domain."""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env as gym_check_env
from stable_baselines3.common.env_checker import check_env as sb3_check_env

import rwm_gym  # noqa: F401  (registers the envs)
from rwm_gym.data.collect import collect
from rwm_gym.imagination.env import ImaginedEnv
from rwm_gym.model.config import TrainConfig
from rwm_gym.model.factory import model_config_for
from rwm_gym.model.train import train
from rwm_gym.registration import DMC_SPECS, IMAGINED_ENVS
from rwm_gym.spec import load_spec
from rwm_gym.task.tasks import state_reward
from rwm_gym.vector.sb3_vec_env import ImaginedSB3VecEnv

PHYSICS = {load_spec(spec).imagined_env_id: env_id for env_id, spec in DMC_SPECS.items()}
IDS = sorted(PHYSICS)


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory) -> dict[str, Path]:
    """Per imagined id, a tiny RWM trained 5 iterations on 2 random episodes of 40 steps (its data: the reset data)."""
    folder = tmp_path_factory.mktemp("rwm_dmc")
    out = {}
    for env_id in IDS:
        data = collect(PHYSICS[env_id], "random", 2, folder / f"{env_id}.h5", num_envs=2, max_steps=40, progress=False)
        spec = load_spec(DMC_SPECS[PHYSICS[env_id]])
        config = model_config_for("rwm", spec, hidden_size=16, num_layers=1, head_hidden=16)
        out[env_id] = train(
            data,
            config,
            TrainConfig(
                history=6,
                forecast=3,
                batch_size=8,
                iterations=5,
                val_every=1000,
                checkpoint_every=1000,
                val_fraction=0.0,
            ),
            folder / f"{env_id}.safetensors",
            progress=False,
        ).path
    return out


def test_every_dm_control_spec_has_a_registered_imagined_id() -> None:
    assert set(IDS) <= set(IMAGINED_ENVS) and len(IDS) == 8
    assert all(env_id in gym.registry for env_id in IDS)


@pytest.mark.parametrize("env_id", IDS)
def test_checkers_pass_and_spaces_match_physics(env_id: str, checkpoints) -> None:
    env = gym.make(env_id, checkpoint=checkpoints[env_id])
    gym_check_env(env.unwrapped, skip_render_check=True)
    sb3_check_env(ImaginedEnv(checkpoints[env_id], env_id=env_id), warn=True)
    physics = gym.make(PHYSICS[env_id])
    assert env.observation_space == physics.observation_space and env.action_space == physics.action_space


def _rollout(env: gym.Env, seed: int, steps: int = 12) -> np.ndarray:
    obs, _ = env.reset(seed=seed)
    rng, rows = np.random.default_rng(seed), [obs]
    for _ in range(steps):
        obs, reward, terminated, _, _ = env.step(rng.uniform(-1, 1, env.action_space.shape).astype(np.float32))
        assert not terminated and np.isfinite(reward)
        rows.append(np.append(obs, reward))
    return np.concatenate(rows)


@pytest.mark.parametrize("env_id", IDS)
def test_same_seed_same_rollout_and_the_task_reward_of_the_prediction(env_id: str, checkpoints) -> None:
    def make() -> ImaginedEnv:
        return ImaginedEnv(checkpoints[env_id], env_id=env_id, sample_predictions=True)

    first = _rollout(make(), 3)
    np.testing.assert_array_equal(first, _rollout(make(), 3))
    assert not np.array_equal(first, _rollout(make(), 4))
    env = make()
    env.reset(seed=0)
    action = np.full(env.action_space.shape, 0.5, dtype=np.float32)
    _, reward, *_ = env.step(action)
    core = env.core
    expected = state_reward(core.spec)(core.state, core.foot_height, action[None])[0]
    assert reward == pytest.approx(expected)  # the task's reward of the predicted next state


@pytest.mark.parametrize("env_id", IDS)
def test_batched_env_matches_single_envs(env_id: str, checkpoints) -> None:
    n, steps, seed = 3, 10, 5
    vec = gym.make_vec(env_id, num_envs=n, vectorization_mode="vector_entry_point", checkpoint=checkpoints[env_id])
    actions = np.random.default_rng(0).uniform(-1, 1, (steps, n, vec.single_action_space.shape[0])).astype(np.float32)
    trajectory = [vec.reset(seed=seed)[0]]
    for t in range(steps):
        trajectory.append(vec.step(actions[t])[0])
    for i in range(n):
        env = ImaginedEnv(checkpoints[env_id], env_id=env_id)
        obs, _ = env.reset(seed=seed + i)
        np.testing.assert_allclose(obs, trajectory[0][i], rtol=1e-5, atol=1e-5)
        for t in range(steps):
            obs, *_ = env.step(actions[t, i])
            np.testing.assert_allclose(obs, trajectory[t + 1][i], rtol=1e-4, atol=1e-4)


def test_sb3_vecenv_truncates_at_the_time_limit_and_never_terminates(checkpoints) -> None:
    env_id = "RWM-Cheetah-v0"
    venv = ImaginedSB3VecEnv(checkpoints[env_id], num_envs=2, env_id=env_id, episode_steps=4)
    venv.seed(0)
    assert venv.reset().shape == (2, 30)
    for _t in range(4):
        _, rewards, dones, infos = venv.step(np.zeros((2, 6), dtype=np.float32))
        assert rewards.shape == (2,) and np.all(rewards >= 0)
    assert dones.all() and all(info["TimeLimit.truncated"] for info in infos)


def test_a_missing_or_foreign_checkpoint_is_refused_in_one_line(checkpoints) -> None:
    with pytest.raises(ValueError, match="RWM-Cheetah-v0 needs checkpoint=PATH: rwm-gym ships no trained world model"):
        gym.make("RWM-Cheetah-v0")
    with pytest.raises(
        ValueError,
        match=r"RWM-Cheetah-v0.safetensors: a world model of DMC-Cheetah-Run .* not of "
        r"RWM-Walker-v0",
    ):
        gym.make("RWM-Walker-v0", checkpoint=checkpoints["RWM-Cheetah-v0"])
    with pytest.raises(ValueError, match="push_interval_s needs a base_lin_vel state group"):
        gym.make("RWM-Finger-v0", checkpoint=checkpoints["RWM-Finger-v0"], push_interval_s=1.0)
    with pytest.raises(ValueError, match="fall_tilt needs a projected_gravity state group"):
        gym.make("RWM-Finger-v0", checkpoint=checkpoints["RWM-Finger-v0"], fall_tilt=30.0)
    with pytest.raises(ValueError, match="torque_halt needs a joint_torque state group and a finite effort limit"):
        gym.make("RWM-Cheetah-v0", checkpoint=checkpoints["RWM-Cheetah-v0"], torque_halt=0.9)
    with pytest.raises(ValueError, match="no MJCF model of its own"):
        gym.make("RWM-Hopper-v0", checkpoint=checkpoints["RWM-Hopper-v0"], render_mode="rgb_array")

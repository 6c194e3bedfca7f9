"""The ANYmal D physics env: API conformance, the task's promises, and single/batched agreement."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env as gym_check_env
from stable_baselines3.common.env_checker import check_env as sb3_check_env

import rwm_gym  # noqa: F401  (registers the envs)
from rwm_gym.physics.locomotion import LocomotionEnv
from rwm_gym.spec import load_spec
from rwm_gym.vector.sb3_vec_env import LocomotionSB3VecEnv

ENV_ID = "AnymalD-MuJoCo-v0"


@pytest.fixture(scope="module")
def env():
    env = gym.make(ENV_ID)
    yield env
    env.close()


def test_gymnasium_and_sb3_checkers_pass():
    gym_check_env(gym.make(ENV_ID).unwrapped, skip_render_check=True)
    sb3_check_env(gym.make(ENV_ID).unwrapped, warn=True)


def test_make_with_namespace_prefix_and_spaces(env):
    made = gym.make(f"rwm_gym:{ENV_ID}")
    spec = load_spec("anymal_d")
    assert made.observation_space.shape == (spec.observation_dim,) == (48,)
    assert made.action_space.shape == (12,)
    assert np.all(made.action_space.low == -1) and np.all(made.action_space.high == 1)


def test_state_layout_and_privileged_signals(env):
    env.reset(seed=0)
    record = env.unwrapped.record()
    assert record["state"].shape == (45,)
    assert record["contact"].shape == (8,) and record["foot_height"].shape == (4,)
    gravity = record["state"][6:9]
    assert gravity[2] < -0.95  # upright at reset
    np.testing.assert_allclose(np.linalg.norm(gravity), 1.0, atol=1e-5)


def test_zero_action_stands_without_falling(env):
    env.reset(seed=3)
    for _ in range(250):  # 5 s; the 20 s check is in benchmarks/physics.py
        _, _, terminated, _truncated, _info = env.step(np.zeros(12))
        assert not terminated
    record = env.unwrapped.record()
    assert env.unwrapped.data.qpos[2] > 0.45  # base height, m
    assert record["contact"][4:].all() and not record["contact"][:4].any()  # on its feet, thighs free


def test_same_seed_same_rollout():
    def rollout(seed):
        env = gym.make(ENV_ID)
        obs, _ = env.reset(seed=seed)
        rng = np.random.default_rng(0)
        out = [obs]
        for _ in range(30):
            out.append(env.step(rng.uniform(-1, 1, 12))[0])
        return np.stack(out)

    np.testing.assert_array_equal(rollout(7), rollout(7))
    assert not np.array_equal(rollout(7), rollout(8))


def test_time_limit_truncates():
    env = LocomotionEnv()
    env.reset(seed=0)
    env.unwrapped.core.steps[:] = env.unwrapped.task_spec.episode_steps - 1
    _, _, terminated, truncated, _ = env.step(np.zeros(12))
    assert truncated and not terminated


def test_a_step_the_physics_blows_up_in_ends_that_episode_only():
    """MuJoCo resets a simulation that blows up and carries on; the env ends the episode there instead."""
    single = LocomotionEnv()
    single.reset(seed=0)
    single.unwrapped.data.qvel[6] = 1e12  # past MuJoCo's limit: a bad-velocity warning and a reset
    _, reward, terminated, truncated, info = single.step(np.zeros(12))
    assert terminated and not truncated and reward == 0.0 and info["physics_diverged"]
    vec = gym.make_vec(ENV_ID, num_envs=2, vectorization_mode="vector_entry_point")
    vec.reset(seed=0)
    core = vec.unwrapped.core
    core.sim._bound["qvel"][1, 6] = 1e12
    _, reward, terminated, _, info = core.step(np.zeros((2, 12)))
    assert terminated.tolist() == [False, True] and info["physics_diverged"].tolist() == [False, True]
    assert reward[1] == 0.0 and reward[0] != 0.0
    core.reset(np.array([1]))
    _, _, terminated, _, info = core.step(np.zeros((2, 12)))  # the next step is an ordinary one again
    assert not info["physics_diverged"].any() and not terminated.any()


def test_nan_and_wrong_shape_actions_are_refused(env):
    env.reset(seed=0)
    with pytest.raises(ValueError, match="NaN"):
        env.step(np.full(12, np.nan))
    with pytest.raises(ValueError, match="shape"):
        env.step(np.zeros(5))


def test_physics_overrides_change_the_model():
    nominal = LocomotionEnv()
    heavy = LocomotionEnv(physics={"payload_mass": 10.0, "joint_friction": 1.5})
    assert heavy.model.body_subtreemass[1] == pytest.approx(nominal.model.body_subtreemass[1] + 10.0)
    assert np.all(heavy.model.dof_frictionloss[6:] == 1.5)
    with pytest.raises(ValueError, match="unknown physics parameter"):
        LocomotionEnv(physics={"not_a_param": 1.0})


@pytest.mark.parametrize(
    "physics",
    [{}, {"backlash": 0.02, "torque_speed_slope": 4.0}],
    ids=["nominal", "drive-rewrites"],
)
def test_batched_env_matches_single_envs_step_for_step(physics):
    n, steps, seed = 3, 40, 11
    rng = np.random.default_rng(1)
    actions = rng.uniform(-1, 1, (steps, n, 12))
    vec = gym.make_vec(ENV_ID, num_envs=n, vectorization_mode="vector_entry_point", nthread=2, physics=physics)
    obs_b, _ = vec.reset(seed=seed)
    batched = [obs_b]
    rewards_b = []
    for t in range(steps):
        obs_b, r, _term, _trunc, _ = vec.step(actions[t])
        batched.append(obs_b)
        rewards_b.append(r)
    for i in range(n):
        env = LocomotionEnv(physics=physics)
        obs, _ = env.reset(seed=seed + i)
        np.testing.assert_array_equal(obs, batched[0][i])
        for t in range(steps):
            obs, r, _term, _trunc, _ = env.step(actions[t, i])
            np.testing.assert_array_equal(obs, batched[t + 1][i])
            assert r == rewards_b[t][i]


def test_sb3_vecenv_autoreset_follows_sb3_rules():
    venv = LocomotionSB3VecEnv(num_envs=2, nthread=1)
    venv.seed(0)
    venv.reset()
    venv.core.steps[:] = venv.core.spec.episode_steps - 1
    obs, _rewards, dones, infos = venv.step(np.zeros((2, 12)))
    assert dones.all()
    for i in range(2):
        assert infos[i]["TimeLimit.truncated"] is True
        assert infos[i]["terminal_observation"].shape == (48,)
        assert not np.array_equal(infos[i]["terminal_observation"], obs[i])
    assert (venv.core.steps == 0).all()


def test_render_rgb_array():
    env = LocomotionEnv(render_mode="rgb_array", width=160, height=120)
    env.reset(seed=0)
    try:
        frame = env.render()
    except Exception as err:  # no OpenGL backend on this machine
        pytest.skip(f"offscreen rendering unavailable (set MUJOCO_GL=egl or osmesa): {err}")
    assert frame.shape == (120, 160, 3) and frame.std() > 0

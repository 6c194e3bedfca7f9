"""The dm_control suite rewards computed from the world-model state (rwm_gym.task.suite_reward), against physics."""

from __future__ import annotations

import gymnasium as gym
import mujoco
import numpy as np
import pytest

import rwm_gym  # noqa: F401  (registers the envs)
from rwm_gym.registration import DMC_SPECS
from rwm_gym.spec import load_spec, parse_spec
from rwm_gym.task.suite_reward import SuiteReward

IDS = sorted(i for i, name in DMC_SPECS.items() if load_spec(name).extra["dm_control"]["domain"] != "manipulation")
"""The suite's ids (the manipulation tasks' rewards are checked in tests/test_manipulation.py)."""
EXACT = {"DMC-Finger-Spin-v0", "DMC-Quadruped-Walk-v0"}  # every quantity their rewards read is in the state


def _rollout(env_id: str, steps: int = 150):
    """Correlated random actions in physics: per step the recorded row, the action and the suite's reward."""
    env = gym.make(env_id).unwrapped
    env.reset(seed=0)
    rng, action, rows = np.random.default_rng(0), np.zeros(env.action_space.shape), []
    for _ in range(steps):
        action = np.clip(0.9 * action + 0.5 * rng.standard_normal(action.shape), -1, 1).astype(np.float32)
        _, reward, *_ = env.step(action)
        rows.append((env.record(), action, reward, env.physics.data.ptr))
        yield env, rows[-1]


@pytest.mark.parametrize("env_id", IDS)
def test_reward_from_the_state_matches_the_suite_reward_in_physics(env_id: str) -> None:
    reward = SuiteReward(load_spec(DMC_SPECS[env_id]))
    ours, theirs = [], []
    for _, (record, action, physics_reward, _) in _rollout(env_id):
        ours.append(reward(record["state"][None], record["foot_height"][None], action[None])[0])
        theirs.append(physics_reward)
    ours, theirs = np.array(ours), np.array(theirs)
    if env_id in EXACT:
        np.testing.assert_allclose(ours, theirs, atol=1e-6)
    else:  # centre-of-mass quantities read from the torso frame (see the module docstring)
        assert np.abs(ours - theirs).mean() < 0.05
        assert abs(ours.mean() - theirs.mean()) < 0.03


@pytest.mark.parametrize(
    "env_id", ["DMC-Cheetah-Run-v0", "DMC-Walker-Walk-v0", "DMC-Hopper-Hop-v0", "DMC-Humanoid-Walk-v0"]
)
def test_derived_quantities_are_exact_kinematics(env_id: str) -> None:
    reward = SuiteReward(load_spec(DMC_SPECS[env_id]))
    for env, (record, action, _, data) in _rollout(env_id, steps=40):
        model = env.physics.model.ptr
        torso = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "torso")
        velocity = np.zeros(6)
        mujoco.mj_objectVelocity(model, data, mujoco.mjtObj.mjOBJ_XBODY, torso, velocity, 0)  # world orientation
        q = {
            k: v[0]
            for k, v in reward.quantities(record["state"][None], record["foot_height"][None], action[None]).items()
        }
        assert q["upright"] == pytest.approx(data.xmat[torso, 8], abs=1e-5)
        assert q["height"] == pytest.approx(data.xpos[torso, 2], abs=1e-5)
        assert q["vertical_velocity"] == pytest.approx(velocity[5], abs=1e-4)
        np.testing.assert_allclose(q["ctrl"], data.ctrl, atol=1e-6)
        if env_id == "DMC-Humanoid-Walk-v0":
            head = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "head")
            assert q["head_height"] == pytest.approx(data.xpos[head, 2], abs=1e-5)
            assert q["horizontal_speed"] == pytest.approx(np.linalg.norm(velocity[3:5]), abs=1e-4)
        else:  # planar: world-frame forward velocity from body-frame velocity and projected gravity
            assert q["forward_velocity"] == pytest.approx(velocity[3], abs=1e-4)


def test_a_reward_the_state_cannot_express_is_refused_in_one_line() -> None:
    text = load_spec("dmc_cheetah_run").text.replace('task = "run"', 'task = "flip"')
    with pytest.raises(ValueError, match=r"DMC-Cheetah-Run: the reward of dm_control cheetah-flip cannot be computed"):
        SuiteReward(parse_spec(text))

"""The scripted trot: it walks at 1 m/s, stands at a zero command, is deterministic per seed and vectorised."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from rwm_gym.physics.locomotion import LocomotionCore
from rwm_gym.physics.params import build_model
from rwm_gym.policies.gait import GaitPolicy
from rwm_gym.policies.leg_kinematics import LegKinematics
from rwm_gym.spec import load_spec

SPEC = load_spec("anymal_d")


def run(command: tuple[float, float, float], steps: int, seed: int = 0, **gait) -> tuple[float, bool, GaitPolicy]:
    """One episode with a fixed command: (base x displacement in m, fell, policy)."""
    core = LocomotionCore(SPEC, 1)
    obs = core.reset(np.array([0]), [seed], np.float32([command]))
    policy = GaitPolicy(SPEC, 1, **gait)
    policy.reset(np.array([0]), [np.random.default_rng(seed)])
    start = core.sim.arrays()["qpos"][0, 0]
    fell = False
    for _ in range(steps):
        obs, _, terminated, _, _ = core.step(policy.act(obs))
        fell |= bool(terminated[0])
    return float(core.sim.arrays()["qpos"][0, 0] - start), fell, policy


def test_walks_forward_at_one_metre_per_second():
    distance, fell, _ = run((1.0, 0.0, 0.0), 400)  # 8 s
    assert not fell
    assert distance >= 4.0


def test_stands_still_at_zero_command():
    distance, fell, policy = run((0.0, 0.0, 0.0), 250)
    assert not fell
    assert abs(distance) < 0.15
    assert not policy.in_swing.any()  # the clock holds in the four-foot support


def test_same_seed_same_actions_and_noise_comes_from_the_generators():
    core = LocomotionCore(SPEC, 1)
    obs = core.reset(np.array([0]), [3])
    a, b, c = (GaitPolicy(SPEC, 1, action_noise=0.1) for _ in range(3))
    a.reset(np.array([0]), [np.random.default_rng(7)])
    b.reset(np.array([0]), [np.random.default_rng(7)])
    c.reset(np.array([0]), [np.random.default_rng(8)])
    for _ in range(20):
        act_a, act_b, act_c = a.act(obs), b.act(obs), c.act(obs)
        np.testing.assert_array_equal(act_a, act_b)
        obs, *_ = core.step(act_a)
    assert not np.array_equal(act_a, act_c)


def test_vectorised_envs_match_single_envs():
    n = 3
    core = LocomotionCore(SPEC, n)
    obs = core.reset(np.arange(n), [0, 1, 2])
    batch = GaitPolicy(SPEC, n)
    batch.reset(np.arange(n), [np.random.default_rng(s) for s in range(n)])
    singles = [GaitPolicy(SPEC, 1) for _ in range(n)]
    for s, single in enumerate(singles):
        single.reset(np.array([0]), [np.random.default_rng(s)])
    for _ in range(10):
        actions = batch.act(obs)
        assert actions.shape == (n, SPEC.action_dim) and actions.dtype == np.float32
        assert np.all(np.abs(actions) <= 1.0)
        for i, single in enumerate(singles):
            np.testing.assert_allclose(actions[i], single.act(obs[i : i + 1])[0], atol=1e-6)
        obs, *_ = core.step(actions)


def test_bad_parameters_fail_in_one_line():
    with pytest.raises(ValueError, match="unknown gait parameter"):
        GaitPolicy(SPEC, 1, swing_hieght=0.1)
    with pytest.raises(ValueError, match="duty"):
        GaitPolicy(SPEC, 1, duty=0.3)


def test_leg_kinematics_match_mujoco_and_invert():
    model = build_model(SPEC)
    kin = LegKinematics.from_model(model, SPEC)
    data = mujoco.MjData(model)
    q = kin.default_pose + np.random.default_rng(0).uniform(-0.4, 0.4, (4, 3))
    data.qpos[:7] = [0, 0, 0, 1, 0, 0, 0]
    data.qpos[7:] = q.ravel()
    mujoco.mj_kinematics(model, data)
    feet = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, name) for name in SPEC.privileged.feet]
    np.testing.assert_allclose(kin.forward(q), data.site_xpos[feet], atol=1e-9)
    np.testing.assert_allclose(kin.inverse(kin.forward(q)), q, atol=1e-9)
    jac = kin.jacobian(q)
    dq = np.zeros((4, 3))
    dq[:, 1] = 1e-4
    np.testing.assert_allclose(kin.forward(q + dq) - kin.forward(q), jac[..., 1] * 1e-4, atol=1e-7)

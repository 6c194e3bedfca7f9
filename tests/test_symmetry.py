"""Left-right mirror symmetry: the spec's table, the mirror arrays checked against MuJoCo, the augmented PPO buffer."""

from __future__ import annotations

import argparse
import zipfile
from types import SimpleNamespace

import gymnasium as gym
import mujoco
import numpy as np
import pytest
import torch
from stable_baselines3 import PPO

from rwm_gym.spec import load_spec, parse_spec
from rwm_gym.task.observation import observation_slices
from rwm_gym.task.symmetry import (
    Mirror,
    action_mirror,
    contact_mirror,
    foot_mirror,
    name_mirror,
    observation_mirror,
    side_tokens,
    state_mirror,
    symmetry_table,
)

SPEC = load_spec("anymal_d")
WITHOUT_TABLE = SPEC.text.split("\n[symmetry]")[0]  # as stored in checkpoints and datasets written before the table


def test_mirror_is_an_involution_with_the_anymal_conventions():
    rng = np.random.default_rng(0)
    for mirror, dim in ((observation_mirror(SPEC), 48), (action_mirror(SPEC), 12), (state_mirror(SPEC), 45)):
        x = rng.normal(size=(5, dim)).astype(np.float32)
        assert mirror.index.shape == (dim,) and not np.array_equal(mirror(x), x)
        np.testing.assert_array_equal(mirror(mirror(x)), x)
    obs = np.arange(1, 49, dtype=np.float32)
    image, at = observation_mirror(SPEC)(obs), observation_slices(SPEC)
    for group, signs in (
        ("base_lin_vel", [1, -1, 1]),
        ("base_ang_vel", [-1, 1, -1]),
        ("projected_gravity", [1, -1, 1]),
        ("command", [1, -1, -1]),
    ):
        np.testing.assert_array_equal(image[at[group]], obs[at[group]] * signs)
    for group in ("joint_pos", "joint_vel", "last_action"):  # LF <-> RF, LH <-> RH; HAA flips, HFE and KFE keep
        legs = obs[at[group]].reshape(4, 3)[[1, 0, 3, 2]] * [-1, 1, 1]
        np.testing.assert_array_equal(image[at[group]], legs.ravel())


def test_specs_without_a_table_and_bad_tables():
    assert load_spec("dmc_cheetah_run").symmetry is None
    with pytest.raises(ValueError, match="no \\[symmetry\\] table"):
        observation_mirror(load_spec("dmc_cheetah_run"))
    older = parse_spec(WITHOUT_TABLE)  # the same robot and layout: the shipped table applies
    assert older.symmetry is None and symmetry_table(older) == SPEC.symmetry
    with pytest.raises(ValueError, match="no \\[symmetry\\] table"):  # another layout: no borrowing
        symmetry_table(parse_spec(WITHOUT_TABLE.replace('"last_action"]', "]")))
    with pytest.raises(ValueError, match="'RF_HAX' is not an actuated joint"):
        parse_spec(SPEC.text.replace('joints = ["RF_HAA"', 'joints = ["RF_HAX"'))
    with pytest.raises(ValueError, match="signs must be 1 or -1"):
        parse_spec(SPEC.text.replace("base_lin_vel = [1, -1, 1]", "base_lin_vel = [1, -2, 1]"))
    with pytest.raises(ValueError, match="not a mirror"):
        observation_mirror(parse_spec(SPEC.text.replace("joint_signs = [-1, 1, 1, -1", "joint_signs = [-1, 1, 1, 1")))
    with pytest.raises(ValueError, match="no signs for group 'base_ang_vel'"):
        observation_mirror(parse_spec(SPEC.text.replace("base_ang_vel = [-1, 1, -1]\n", "")))


def _mirror_vel(v: np.ndarray, joints: Mirror, dof_adr: np.ndarray) -> np.ndarray:
    """Mirror of a free-base qvel-like vector: world linear part (x, -y, z), body angular part (-x, y, -z)."""
    out = v * np.r_[1, -1, 1, -1, 1, -1, np.ones(len(v) - 6)]
    out[dof_adr] = joints(v[dof_adr])
    return out


def _mirror_physics(src: gym.Env, dst: gym.Env, joints: Mirror) -> None:
    """Put `dst` in the mirror image of `src`'s physics state (base reflected through the world x-z plane)."""
    layout, d, m = src.core.layout, src.data, dst.data
    m.qpos[:] = d.qpos * np.r_[1, -1, 1, 1, -1, 1, -1, np.ones(len(d.qpos) - 7)]  # quaternion (w, -x, y, -z)
    m.qpos[layout.qpos_adr] = joints(d.qpos[layout.qpos_adr])
    m.qvel[:] = _mirror_vel(d.qvel, joints, layout.dof_adr)
    m.qacc_warmstart[:] = _mirror_vel(d.qacc_warmstart, joints, layout.dof_adr)
    m.ctrl[layout.actuator_ids] = joints(d.ctrl[layout.actuator_ids])
    mujoco.mj_forward(dst.model, m)
    dst.core.current = dst.core._measure()
    dst.core.last_action[:] = joints(src.core.last_action)


def test_mirrored_physics_state_gives_the_mirrored_observation():
    """The mirror of a MuJoCo state observes as the mirror of the observation; its bodies sit at the mirrored places
    (which fixes the HAA sign: with +1 they do not); one step on the mirrored action lands near the mirrored step
    (the URDF's inertias are not exactly symmetric: 0.5 % of the step's change)."""
    joints, obs_mirror = action_mirror(SPEC), observation_mirror(SPEC)
    env = gym.make("AnymalD-MuJoCo-v0").unwrapped
    env.reset(seed=1, options={"command": (0.5, 0.3, 0.4)})
    rng = np.random.default_rng(0)
    for _ in range(15):  # off the keyframe: tilted, turning, legs apart
        obs, *_ = env.step(rng.uniform(-1, 1, 12).astype(np.float32))
    image = gym.make("AnymalD-MuJoCo-v0").unwrapped
    image.reset(seed=2, options={"command": (0.5, -0.3, -0.4)})
    _mirror_physics(env, image, joints)
    np.testing.assert_allclose(image.core.observe()[0], obs_mirror(obs), atol=1e-6)
    np.testing.assert_allclose(image.core.current.state[0], state_mirror(SPEC)(env.core.current.state[0]), atol=1e-4)

    names = [env.model.body(i).name for i in range(env.model.nbody)]
    swapped = [names.index(n.translate(str.maketrans("LR", "RL"))) for n in names]  # LF_HIP <-> RF_HIP, base: base
    np.testing.assert_allclose(image.data.xpos[swapped], env.data.xpos * [1, -1, 1], atol=1e-9)
    wrong = gym.make("AnymalD-MuJoCo-v0").unwrapped
    wrong.reset(seed=2)
    _mirror_physics(env, wrong, Mirror(joints.index, np.abs(joints.sign)))
    assert np.abs(wrong.data.xpos[swapped] - env.data.xpos * [1, -1, 1]).max() > 0.1

    action = rng.uniform(-1, 1, 12).astype(np.float32)
    after, reward, *_ = env.step(action)
    after_image, reward_image, *_ = image.step(joints(action))
    change = np.abs(after - obs).max()
    assert np.abs(after_image - obs_mirror(after)).max() < 0.01 * change
    assert reward_image == pytest.approx(reward, rel=0.02, abs=1e-4)


def test_augmented_buffer_yields_doubled_minibatches_whose_second_half_is_the_mirror():
    from rwm_gym.rl.mirror_buffer import MirroredRolloutBuffer

    obs_mirror, act_mirror = observation_mirror(SPEC), action_mirror(SPEC)
    obs_space = gym.spaces.Box(-np.inf, np.inf, (48,), np.float32)
    act_space = gym.spaces.Box(-1.0, 1.0, (12,), np.float32)
    steps, envs, batch = 6, 4, 8

    class Policy(torch.nn.Module):  # a known log-probability, so the original half's KL can be checked
        @staticmethod
        def evaluate_actions(obs, actions):
            return None, (obs[:, :12] * actions).sum(1) + obs[:, 20], None

        @staticmethod
        def get_distribution(obs):
            return SimpleNamespace(log_prob=lambda actions: Policy.evaluate_actions(obs, actions)[1])

    buffer = MirroredRolloutBuffer(
        steps,
        obs_space,
        act_space,
        "cpu",
        n_envs=envs,
        observation_mirror=obs_mirror,
        action_mirror=act_mirror,
        policy=Policy(),
    )
    rng = np.random.default_rng(0)
    for _ in range(steps):
        buffer.add(
            rng.normal(size=(envs, 48)).astype(np.float32),
            rng.normal(size=(envs, 12)).astype(np.float32),
            rng.normal(size=envs),
            np.zeros(envs, bool),
            torch.randn(envs),
            torch.randn(envs),
        )
    buffer.compute_returns_and_advantage(torch.randn(envs), np.zeros(envs, bool))
    assert buffer.original_kl is None
    batches = list(buffer.get(batch))
    assert len(batches) == steps * envs // batch
    # the KL of the original halves: the policy's log-probability against the rollout's, SB3's approximation
    ratios = [
        Policy.evaluate_actions(b.observations[:batch], b.actions[:batch])[1] - b.old_log_prob[:batch] for b in batches
    ]
    expected = np.mean([float(torch.mean(torch.exp(r) - 1 - r)) for r in ratios])
    assert buffer.original_kl == pytest.approx(expected) and expected > 0
    seen = []
    for b in batches:
        assert b.observations.shape == (2 * batch, 48) and b.actions.shape == (2 * batch, 12)
        first, second = b.observations[:batch].numpy(), b.observations[batch:].numpy()
        np.testing.assert_array_equal(second, obs_mirror(first))
        np.testing.assert_array_equal(b.actions[batch:].numpy(), act_mirror(b.actions[:batch].numpy()))
        for name in ("old_values", "advantages", "returns"):
            values = getattr(b, name)
            assert values.shape == (2 * batch,) and torch.equal(values[:batch], values[batch:])
        # the mirrored half's old log-probability is the original's: that of the rollout policy's mirror image
        assert torch.equal(b.old_log_prob[:batch], b.old_log_prob[batch:])
        seen.append(first)
    # the first halves are the rollout, each sample once
    rollout = buffer.observations.reshape(-1, 48)
    np.testing.assert_array_equal(np.sort(np.concatenate(seen), axis=0), np.sort(rollout, axis=0))


def test_tiny_ppo_with_symmetry_trains_in_imagination_and_saves_a_plain_policy(tmp_path):
    """On the shipped world model, PPO trains on doubled minibatches; the zip loads with plain `PPO.load`, and with an
    env keeps training mirrored."""
    from rwm_gym.rl.mirror_buffer import MirroredRolloutBuffer
    from rwm_gym.rl.ppo import PPOConfig, learn, load_ppo, make_env, make_ppo, save_policy

    config = PPOConfig(num_envs=16, n_steps=16, net_arch=(32, 32), num_minibatches=4, n_epochs=2, symmetry=True)
    env = make_env("imagination", config.num_envs, seed=0, env_kwargs={"episode_steps": 16})
    model = make_ppo(env, config, seed=0)
    assert isinstance(model.rollout_buffer, MirroredRolloutBuffer)
    sizes, evaluate = [], model.policy.evaluate_actions
    model.policy.evaluate_actions = lambda obs, actions: sizes.append(len(obs)) or evaluate(obs, actions)
    before = [p.detach().clone() for p in model.policy.parameters()]
    stats = learn(model, timesteps=2 * config.num_envs * config.n_steps, progress=False)
    assert stats.timesteps == 512 and all(np.isfinite(row["mean_step_reward"]) for row in stats.log)
    batch = config.num_envs * config.n_steps // config.num_minibatches  # SB3's doubled minibatches, nothing more
    assert sizes == [2 * batch] * (4 * 2) * 2
    kl = model.rollout_buffer.original_kl  # the adaptive learning rate's input: the original half's KL, not SB3's
    assert kl is not None and kl >= 0 and kl != model.logger.name_to_value["train/approx_kl"]
    assert any(not torch.equal(a, b) for a, b in zip(before, model.policy.parameters()))

    del model.policy.evaluate_actions
    path = save_policy(model, tmp_path / "mirrored.zip")
    loaded = PPO.load(path, device="cpu")
    obs = np.random.default_rng(0).normal(size=(3, 48)).astype(np.float32)
    np.testing.assert_allclose(loaded.predict(obs, deterministic=True)[0], model.predict(obs, deterministic=True)[0])
    assert b"MirroredRolloutBuffer" not in zipfile.ZipFile(path).read("data")  # nothing of it is saved
    assert not isinstance(PPO.load(path, env=env, device="cpu").rollout_buffer, MirroredRolloutBuffer)
    assert isinstance(load_ppo(path, env, config).rollout_buffer, MirroredRolloutBuffer)


def test_symmetry_is_refused_for_a_spec_without_a_mirror():
    from rwm_gym.commands.ppo import add_arguments
    from rwm_gym.rl.ppo import PPOConfig, make_ppo
    from rwm_gym.vector.sb3_vec_env import DMCSB3VecEnv

    config = PPOConfig(num_envs=2, n_steps=8, net_arch=(8,), num_minibatches=2, symmetry=True)
    one_line = r"^task spec \S+ has no \[symmetry\] table \(the robot's left-right mirror\)$"
    with pytest.raises(ValueError, match=one_line):
        make_ppo(DMCSB3VecEnv(2, "dmc_cheetah_run"), config)
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    assert parser.parse_args(["--symmetry"]).symmetry is True and parser.parse_args([]).symmetry is None
    assert "left-right mirror" in parser.format_help()


def test_side_tokens_give_each_contact_body_and_foot_its_mirror():
    go2, g1 = load_spec("go2"), load_spec("g1_legs")
    assert side_tokens(go2) == {"FL": "FR", "FR": "FL", "RL": "RR", "RR": "RL"}
    assert [go2.privileged.contact_bodies[i] for i in contact_mirror(go2)][:2] == ["FR_thigh", "FL_thigh"]
    assert [g1.privileged.feet[i] for i in foot_mirror(g1)] == ["right_foot", "left_foot"]
    np.testing.assert_array_equal(name_mirror(go2, ["base", "FL_foot", "FR_foot"]), [0, 2, 1])  # base is its own
    with pytest.raises(ValueError, match="'FL_foot' mirrors to 'FR_foot', which is not beside it"):
        name_mirror(go2, ["FL_foot", "RL_foot"])


def test_the_go2_mirror_is_physically_true():
    """From the keyframe (no reset noise), the mirrored actions drive the Go2 along the mirror image of the state,
    contact flags and foot heights (its model is left-right symmetric: 0.4 % of a state's std after 40 steps)."""
    import dataclasses

    from rwm_gym.registration import make_physics_core

    spec = load_spec("go2")
    still = dataclasses.replace(spec.reset, joint_pos_noise=0.0, base_lin_vel_noise=0.0, base_ang_vel_noise=0.0)
    core = make_physics_core(dataclasses.replace(spec, reset=still), 2)
    core.reset(np.arange(2), [0, 0])
    states, actions, contacts, feet = state_mirror(spec), action_mirror(spec), contact_mirror(spec), foot_mirror(spec)
    rng, moved = np.random.default_rng(0), 0.0
    for _ in range(40):
        action = np.clip(rng.normal(0, 0.5, 12), -1, 1).astype(np.float32)
        core.step(np.stack([action, actions(action)]))
        row = core.record()
        error = np.abs(states(row["state"][0]) - row["state"][1]) / np.asarray(spec.state_std)
        assert error.max() < 0.02
        np.testing.assert_array_equal(row["contact"][0][contacts], row["contact"][1])
        np.testing.assert_allclose(row["foot_height"][0][feet], row["foot_height"][1], atol=1e-3)
        moved = max(moved, np.abs(row["state"][0] - states(row["state"][0]))[:6].max())
    assert moved > 0.1  # the robot moved off its own mirror image: the check had something to check


def test_window_mirror_is_the_physical_mirror_in_normalised_units():
    from rwm_gym.model.normalization import Normalizer
    from rwm_gym.model.windows import Window, WindowMirror

    spec = load_spec("go2")
    normalizer, rng = Normalizer.from_spec(spec), np.random.default_rng(0)
    physical = rng.normal(size=(3, 5, 45)) * np.asarray(spec.state_std) + np.asarray(spec.state_mean)
    window = Window(
        torch.as_tensor(normalizer.normalize_state(physical), dtype=torch.float32),
        torch.as_tensor(rng.uniform(-1, 1, (3, 5, 12)), dtype=torch.float32),
        torch.as_tensor(rng.random((3, 5, 8)) < 0.5, dtype=torch.float32),
        torch.as_tensor(rng.random((3, 5, 4)), dtype=torch.float32),
        torch.zeros(3, 5),
    )
    mirror, flip = WindowMirror(spec, normalizer), torch.tensor([True, False, True])
    image = mirror(window, flip)
    expected = normalizer.normalize_state(state_mirror(spec)(physical))
    np.testing.assert_allclose(image.states[0].numpy(), expected[0], atol=1e-5)
    assert torch.equal(image.states[1], window.states[1]) and torch.equal(image.actions[1], window.actions[1])
    np.testing.assert_allclose(image.actions[2].numpy(), action_mirror(spec)(window.actions[2].numpy()))
    assert torch.equal(image.contacts[0], window.contacts[0][:, contact_mirror(spec)])
    twice = mirror(image, flip)
    for name in ("states", "actions", "contacts", "foot_heights"):
        torch.testing.assert_close(getattr(twice, name), getattr(window, name), atol=1e-5, rtol=0)
    with pytest.raises(ValueError, match="no \\[symmetry\\] table"):
        WindowMirror(load_spec("dmc_cheetah_run"), Normalizer.from_spec(load_spec("dmc_cheetah_run")))


def test_a_world_model_trains_on_mirrored_windows_deterministically(tmp_path):
    from synthetic_dynamics import write_linear_dataset

    from rwm_gym.model import model_config_for
    from rwm_gym.model.config import TrainConfig
    from rwm_gym.model.train import train

    data = write_linear_dataset(tmp_path / "linear.h5")
    config = model_config_for("rwm", SPEC, hidden_size=16, num_layers=1, head_hidden=16)
    run = TrainConfig(history=6, forecast=3, batch_size=8, iterations=6, val_every=3, val_fraction=0.25)
    mirrored = [train(data, config, TrainConfig(**{**run.to_dict(), "mirror": True}), progress=False) for _ in "ab"]
    plain = train(data, config, run, progress=False)
    a, b, c = (dict(r.model.state_dict()) for r in (*mirrored, plain))
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert any(not torch.equal(a[k], c[k]) for k in a)
    assert mirrored[0].stats["val_error"] is not None and np.isfinite(mirrored[0].stats["val_error"])

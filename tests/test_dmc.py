"""dm_control suite physics envs: the same checks over every registered `DMC-*` id (checkers, layout, determinism,
single == batched, collection round-trip, a tiny world model trains on the data)."""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import mujoco
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env as gym_check_env
from stable_baselines3.common.env_checker import check_env as sb3_check_env

import rwm_gym  # noqa: F401  (registers the envs)
from rwm_gym.data.collect import collect
from rwm_gym.data.dataset import Dataset
from rwm_gym.physics.dmc import make_core
from rwm_gym.registration import DMC_SPECS
from rwm_gym.spec import load_spec, parse_spec

IDS = sorted(DMC_SPECS)
STEPS = 50


@pytest.fixture(scope="module")
def datasets(tmp_path_factory) -> dict[str, Path]:
    """Two short random episodes of every domain, collected once."""
    folder = tmp_path_factory.mktemp("dmc")
    return {
        env_id: collect(env_id, "random", 2, folder / f"{env_id}.h5", num_envs=2, max_steps=STEPS, progress=False)
        for env_id in IDS
    }


@pytest.mark.parametrize("env_id", IDS)
def test_gymnasium_and_sb3_checkers_pass(env_id: str) -> None:
    gym_check_env(gym.make(f"rwm_gym:{env_id}").unwrapped, skip_render_check=True)
    sb3_check_env(gym.make(env_id).unwrapped, warn=True)


@pytest.mark.parametrize("env_id", IDS)
def test_spaces_and_state_layout_follow_the_spec(env_id: str) -> None:
    env = gym.make(env_id).unwrapped
    spec = env.task_spec
    assert spec.physics_env_id == env_id and spec.command.names == () and spec.privileged.termination_bodies == ()
    assert env.observation_space.shape == (spec.state_dim + spec.action_dim,)
    assert env.action_space.shape == (env.physics.model.nu,)
    obs, _ = env.reset(seed=0)
    record = env.record()
    np.testing.assert_array_equal(obs[: spec.state_dim], record["state"])  # observation = state, then last action
    np.testing.assert_array_equal(obs[spec.state_dim :], 0.0)
    data = env.physics.data.ptr
    np.testing.assert_array_equal(record["qpos"], data.qpos)
    if "projected_gravity" in spec.state_slices:  # a free or planar base: unit gravity in the base frame
        gravity = record["state"][spec.state_slices["projected_gravity"]]
        if len(gravity) == 3:
            np.testing.assert_allclose(np.linalg.norm(gravity), 1.0, atol=1e-5)
        base = mujoco.mj_name2id(env.physics.model.ptr, mujoco.mjtObj.mjOBJ_BODY, spec.base_body)
        assert record["state"][spec.state_slices["base_height"]][0] == pytest.approx(data.xpos[base, 2])
    joint_vel = spec.state_slices["joint_vel"]
    adr = [
        env.physics.model.ptr.jnt_dofadr[mujoco.mj_name2id(env.physics.model.ptr, mujoco.mjtObj.mjOBJ_JOINT, j)]
        for j in spec.state[list(spec.state_slices).index("joint_vel")].columns
    ]
    np.testing.assert_allclose(record["state"][joint_vel], data.qvel[adr], rtol=1e-6)


@pytest.mark.parametrize("env_id", IDS)
def test_same_seed_same_transitions_and_batched_equals_single(env_id: str) -> None:
    def rollout(env: gym.Env, seed: int) -> np.ndarray:
        obs, _ = env.reset(seed=seed)
        rng, rows = np.random.default_rng(seed), [obs]
        for _ in range(20):
            obs, reward, terminated, truncated, _ = env.step(rng.uniform(-1, 1, env.action_space.shape))
            assert not terminated and not truncated
            rows.append(np.append(obs, reward))
        return np.concatenate(rows)

    env = gym.make(env_id).unwrapped
    first = rollout(env, 7)
    np.testing.assert_array_equal(first, rollout(gym.make(env_id).unwrapped, 7))
    assert not np.array_equal(first, rollout(env, 8))
    core = make_core(DMC_SPECS[env_id], 2)
    core.reset(np.arange(2), [8, 7])
    single = gym.make(env_id).unwrapped
    single.reset(seed=7)
    rng = np.random.default_rng(0)
    for _ in range(5):
        action = rng.uniform(-1, 1, (2, core.spec.action_dim))
        batched_obs, batched_reward, *_ = core.step(action)
        obs, reward, *_ = single.step(action[1])
        np.testing.assert_array_equal(batched_obs[1], obs)
        assert batched_reward[1] == reward


def test_episodes_truncate_at_the_time_limit_and_never_terminate() -> None:
    core = make_core("dmc_finger_spin", 1)
    core.reset(np.array([0]), [0])
    for t in range(core.spec.episode_steps):
        _, _, terminated, truncated, _ = core.step(np.zeros((1, core.spec.action_dim)))
        assert not terminated[0] and truncated[0] == (t == core.spec.episode_steps - 1)


def test_contacts_come_from_mujoco_contacts_with_the_partner() -> None:
    env = gym.make("DMC-Walker-Walk-v0").unwrapped
    env.reset(seed=0)
    for _ in range(60):  # zero torques: the walker collapses onto the floor
        env.step(np.zeros(env.action_space.shape))
    contact = env.record()["contact"]
    model, data = env.physics.model.ptr, env.physics.data.ptr
    touching = {
        mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, model.geom_bodyid[g])
        for c in data.contact
        for g in (c.geom1, c.geom2)
    }
    expected = [body in touching for body in env.task_spec.privileged.contact_bodies]
    np.testing.assert_array_equal(contact, expected)
    assert contact.any()


def test_bad_spec_fields_fail_in_one_line() -> None:
    text = load_spec("dmc_cheetah_run").text
    with pytest.raises(ValueError, match=r"\[dm_control\] field 'domain'"):
        make_core(parse_spec(text.replace('domain = "cheetah"', "")))
    with pytest.raises(ValueError, match="policy_dt"):
        make_core(parse_spec(text.replace("policy_dt = 0.01", "policy_dt = 0.02")))
    with pytest.raises(ValueError, match="'bshin_typo' is not in the dm_control model"):
        make_core(parse_spec(text.replace('columns = ["bthigh", "bshin"', 'columns = ["bthigh", "bshin_typo"', 1)))


@pytest.mark.parametrize("env_id", IDS)
def test_collection_round_trips(env_id: str, datasets: dict[str, Path]) -> None:
    ds = Dataset.load(datasets[env_id])
    spec = ds.spec()
    assert ds.info.env_id == env_id and spec.text == load_spec(DMC_SPECS[env_id]).text
    assert ds.num_episodes == 2 and list(ds.episode_lengths) == [STEPS + 1] * 2
    assert ds["state"].shape == (2 * (STEPS + 1), spec.state_dim)
    assert ds["contact"].shape[1] == spec.contact_dim and ds["foot_height"].shape[1] == spec.foot_dim
    assert ds["command"].shape[1] == 0 and not ds["terminated"].any() and ds["truncated"].sum() == 2
    assert ds.info.columns["state"] == list(spec.state_columns)
    assert ds.info.physics_params["domain"] == spec.extra["dm_control"]["domain"]
    assert np.abs(ds["action"]).max() > 0.1  # the random policy moved
    first = ds.episode(0)
    env = gym.make(env_id).unwrapped
    env.reset(seed=0)  # episode k starts from seed k
    np.testing.assert_array_equal(first["state"][0], env.record()["state"])
    for t in range(3):
        _, reward, *_ = env.step(first["action"][t])
        np.testing.assert_allclose(first["state"][t + 1], env.record()["state"], rtol=1e-6, atol=1e-6)
        assert first["reward"][t] == pytest.approx(reward, rel=1e-6)


@pytest.mark.parametrize("env_id", IDS)
def test_a_tiny_world_model_trains_on_each_domain(env_id: str, datasets: dict[str, Path]) -> None:
    torch = pytest.importorskip("torch")
    from rwm_gym.model import TrainConfig, model_config_for
    from rwm_gym.model.train import train

    ds = Dataset.load(datasets[env_id])
    config = model_config_for("rwm", ds.spec(), hidden_size=16, num_layers=1, head_hidden=16)
    run = TrainConfig(history=6, forecast=3, batch_size=8, iterations=6, val_every=3, val_fraction=0.5)
    torch.manual_seed(0)
    result = train(ds, config, run, progress=False)
    assert result.stats["iterations"] == 6 and np.isfinite(result.stats["train_loss"])
    assert np.isfinite(result.stats["val_error"])
    batch = torch.as_tensor(ds["state"][None, :6]), torch.as_tensor(ds["action"][None, :6])
    hidden, _ = result.model.warm_up(*batch)
    _, prediction = result.model.step(hidden, batch[0][:, -1], batch[1][:, -1])
    assert prediction.state_mean.shape == (1, ds.spec().state_dim)

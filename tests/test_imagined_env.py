"""RWM-AnymalD-v0: the world model behind Gymnasium and SB3, checked on a tiny model trained on tiny data."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env as gym_check_env
from stable_baselines3.common.env_checker import check_env as sb3_check_env

import rwm_gym  # noqa: F401
from rwm_gym.data.collect import collect
from rwm_gym.imagination.core import tilt_degrees
from rwm_gym.imagination.env import ImaginedEnv
from rwm_gym.imagination.reset_data import make_reset_data
from rwm_gym.model.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from rwm_gym.model.config import TrainConfig
from rwm_gym.model.factory import model_config_for
from rwm_gym.model.train import train
from rwm_gym.spec import load_spec
from rwm_gym.vector.sb3_vec_env import ImaginedSB3VecEnv

ENV_ID = "RWM-AnymalD-v0"


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    """A tiny RWM (2 ensemble heads) trained 30 iterations on 6 short random episodes, with its reset data."""
    folder = tmp_path_factory.mktemp("rwm")
    data = collect(
        "AnymalD-MuJoCo-v0", "random", 6, folder / "data.h5", seed=0, num_envs=2, max_steps=60, progress=False
    )
    spec = load_spec("anymal_d")
    config = model_config_for("rwm", spec, hidden_size=32, num_layers=1, head_hidden=32, ensemble_size=2)
    path = folder / "model.safetensors"
    train(
        data,
        config,
        TrainConfig(history=8, forecast=4, batch_size=16, iterations=30, val_every=1000, checkpoint_every=1000),
        path,
        progress=False,
    )
    make_reset_data(data, folder / "reset.h5", episodes=4)
    model, meta = load_checkpoint(path)
    save_checkpoint(
        path,
        model,
        meta.spec,
        train_config=meta.train_config,
        provenance=meta.provenance,
        stats=meta.stats,
        extras={"reset_data": "reset.h5"},
    )
    return path


def test_checkers_pass(checkpoint):
    gym_check_env(gym.make(ENV_ID, checkpoint=checkpoint).unwrapped, skip_render_check=True)
    sb3_check_env(ImaginedEnv(checkpoint), warn=True)


def test_spaces_match_the_physics_env(checkpoint):
    imagined, physics = gym.make(ENV_ID, checkpoint=checkpoint), gym.make("AnymalD-MuJoCo-v0")
    assert imagined.observation_space == physics.observation_space
    assert imagined.action_space == physics.action_space


def _rollout(env, seed, steps=25):
    obs, _ = env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    out, rewards = [obs], []
    for _ in range(steps):
        obs, r, term, trunc, _info = env.step(rng.uniform(-1, 1, 12).astype(np.float32))
        out.append(obs)
        rewards.append(r)
        if term or trunc:
            obs, _ = env.reset()
    return np.stack(out), np.array(rewards)


def test_same_seed_same_rollout_also_when_sampling(checkpoint):
    for sample in (False, True):
        a = _rollout(ImaginedEnv(checkpoint, sample_predictions=sample), 3)
        b = _rollout(ImaginedEnv(checkpoint, sample_predictions=sample), 3)
        np.testing.assert_array_equal(a[0], b[0])
        np.testing.assert_array_equal(a[1], b[1])
    assert not np.array_equal(_rollout(ImaginedEnv(checkpoint), 3)[0], _rollout(ImaginedEnv(checkpoint), 4)[0])


def test_reset_replays_a_real_warm_up(checkpoint):
    env = ImaginedEnv(checkpoint)
    env.reset(seed=0)
    core = env.core
    assert any(torch.count_nonzero(h) > 0 for h in core.hidden)  # warmed up, not a cold zero state
    ends = core.reset_windows.ends
    states = core.reset_windows.states[ends]
    assert np.any(np.all(states == core.state[0], axis=1))  # the first state is a real row


def test_batched_env_matches_single_envs(checkpoint):
    n, steps, seed = 3, 20, 5
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, (steps, n, 12)).astype(np.float32)
    vec = gym.make_vec(
        ENV_ID, num_envs=n, vectorization_mode="vector_entry_point", checkpoint=checkpoint, episode_steps=1000
    )
    obs_b, _ = vec.reset(seed=seed)
    trajectory = [obs_b]
    for t in range(steps):
        trajectory.append(vec.step(actions[t])[0])
    for i in range(n):
        env = ImaginedEnv(checkpoint, episode_steps=1000)
        obs, _ = env.reset(seed=seed + i)
        np.testing.assert_allclose(obs, trajectory[0][i], rtol=1e-5, atol=1e-5)
        for t in range(steps):
            obs, _, term, _, _ = env.step(actions[t, i])
            if term:
                break  # the vector env auto-reset here
            np.testing.assert_allclose(obs, trajectory[t + 1][i], rtol=1e-4, atol=1e-4)


def test_divergence_guard_ends_the_episode_without_nan(checkpoint, tmp_path):
    model, meta = load_checkpoint(checkpoint)
    with torch.no_grad():
        for name, p in model.named_parameters():
            if "state_head" in name or "head" in name:
                p.mul_(1e4)
    broken = tmp_path / "broken.safetensors"
    save_checkpoint(
        broken,
        model,
        meta.spec,
        train_config=meta.train_config,
        provenance=meta.provenance,
        extras={"reset_data": str(checkpoint.parent / "reset.h5")},
    )
    env = ImaginedEnv(broken)
    env.reset(seed=0)
    diverged = False
    for _ in range(20):
        obs, reward, terminated, _truncated, info = env.step(np.zeros(12, dtype=np.float32))
        assert np.all(np.isfinite(obs)) and np.isfinite(reward)
        if info["model_diverged"]:
            assert terminated
            diverged = True
            break
        if terminated:
            env.reset()
    assert diverged


def test_sb3_vecenv_and_uncertainty_penalty(checkpoint):
    venv = ImaginedSB3VecEnv(checkpoint, num_envs=4, uncertainty_penalty=10.0)
    venv.seed(0)
    obs = venv.reset()
    assert obs.shape == (4, 48)
    _, rewards, _dones, infos = venv.step(np.zeros((4, 12), dtype=np.float32))
    assert all(info["uncertainty"] >= 0 for info in infos)
    plain = ImaginedSB3VecEnv(checkpoint, num_envs=4)
    plain.seed(0)
    plain.reset()
    _, plain_rewards, _, _ = plain.step(np.zeros((4, 12), dtype=np.float32))
    assert np.all(rewards <= plain_rewards + 1e-6) and np.any(rewards < plain_rewards)


def _first_step(checkpoint, **options):
    venv = ImaginedSB3VecEnv(checkpoint, num_envs=4, **options)
    venv.seed(0)
    venv.reset()
    _, rewards, dones, infos = venv.step(np.zeros((4, 12), dtype=np.float32))
    return rewards, dones, infos


def test_the_penalty_charges_only_disagreement_above_the_floor(checkpoint):
    plain, _, _ = _first_step(checkpoint)
    _, _, infos = _first_step(checkpoint, report_uncertainty=True)
    u = np.array([info["uncertainty"] for info in infos])
    above_all, _, _ = _first_step(checkpoint, uncertainty_penalty=10.0, uncertainty_floor=float(u.max()) + 1.0)
    np.testing.assert_allclose(above_all, plain, atol=1e-6)  # nothing above the floor: nothing charged
    floor = float(np.median(u))
    charged, _, _ = _first_step(checkpoint, uncertainty_penalty=10.0, uncertainty_floor=floor)
    expected = plain - 10.0 * np.maximum(u - floor, 0.0) * load_spec("anymal_d").policy_dt
    np.testing.assert_allclose(charged, expected, atol=1e-6)


def test_tilt_degrees_is_the_angle_from_upright():
    gravity = np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [0.0, 0.0, 2.0], [0.5, 0.0, -0.5]])
    np.testing.assert_allclose(tilt_degrees(gravity), [0.0, 90.0, 180.0, 45.0], atol=1e-9)


def test_fall_tilt_ends_episodes_where_the_predicted_base_tips_over(checkpoint):
    venv = ImaginedSB3VecEnv(checkpoint, num_envs=4)
    venv.seed(0)
    venv.reset()
    venv.step(np.zeros((4, 12), dtype=np.float32))
    gravity = venv.core.state[:, load_spec("anymal_d").state_slices["projected_gravity"]]
    tilt = tilt_degrees(gravity)  # the first step's predicted tilt, the same for the same seed
    threshold = float(np.median(tilt))
    _, dones, infos = _first_step(checkpoint, fall_tilt=threshold)
    tipped = np.array([info["fall_tilt"] for info in infos])
    np.testing.assert_array_equal(tipped, tilt > threshold)
    assert tipped.any() and (~tipped).any() and dones[tipped].all()
    assert not any(info["TimeLimit.truncated"] for info, t in zip(infos, tipped) if t)  # no bootstrap
    _, _, untouched = _first_step(checkpoint)
    assert not any(info["fall_tilt"] for info in untouched)  # off by default


def test_torque_halt_ends_episodes_where_a_predicted_joint_torque_nears_the_limit(checkpoint):
    spec = load_spec("anymal_d")
    venv = ImaginedSB3VecEnv(checkpoint, num_envs=4)
    venv.seed(0)
    venv.reset()
    venv.step(np.zeros((4, 12), dtype=np.float32))
    peak = np.abs(venv.core.state[:, spec.state_slices["joint_torque"]]).max(axis=1)  # same seed, same first step
    fraction = float(np.median(peak)) / spec.actuator.effort_limit
    _, dones, infos = _first_step(checkpoint, torque_halt=fraction)
    saturated = np.array([info["torque_halt"] for info in infos])
    np.testing.assert_array_equal(saturated, peak >= fraction * spec.actuator.effort_limit)
    assert saturated.any() and (~saturated).any() and dones[saturated].all()
    assert not any(info["TimeLimit.truncated"] for info, t in zip(infos, saturated) if t)  # no bootstrap
    _, _, untouched = _first_step(checkpoint)
    assert not any(info["torque_halt"] for info in untouched)  # off by default


def test_the_halt_ends_episodes_where_the_ensemble_disagrees(checkpoint):
    _, _, infos = _first_step(checkpoint, report_uncertainty=True)
    u = np.array([info["uncertainty"] for info in infos])
    threshold = float(np.median(u))
    _, dones, halted_infos = _first_step(checkpoint, uncertainty_halt=threshold)
    halted = np.array([info["uncertainty_halt"] for info in halted_infos])
    np.testing.assert_array_equal(halted, u > threshold)
    assert halted.any() and dones[halted].all()
    assert not any(info["TimeLimit.truncated"] for info, h in zip(halted_infos, halted) if h)  # no bootstrap


def test_an_uncertainty_option_on_a_one_head_model_is_refused(tmp_path):
    """One head has no disagreement: a penalty or halt on it would silently do nothing."""
    data = collect(
        "AnymalD-MuJoCo-v0", "random", 2, tmp_path / "data.h5", seed=0, num_envs=2, max_steps=30, progress=False
    )
    config = model_config_for("rwm", load_spec("anymal_d"), hidden_size=16, num_layers=1, head_hidden=16)
    assert config.ensemble_size == 1
    path = train(
        data,
        config,
        TrainConfig(history=8, forecast=4, batch_size=8, iterations=2, val_every=1000),
        tmp_path / "one_head.safetensors",
        progress=False,
    ).path
    for option in ({"uncertainty_penalty": 10.0}, {"uncertainty_halt": 0.06}):
        with pytest.raises(ValueError, match=r"one_head.safetensors: .*one head .*--ensemble-size 5"):
            ImaginedEnv(path, reset_data=data, **option)
    ImaginedEnv(path, reset_data=data, uncertainty_floor=0.02)  # a floor alone charges nothing


def test_bad_checkpoints_fail_clearly(checkpoint, tmp_path):
    truncated = tmp_path / "cut.safetensors"
    truncated.write_bytes(checkpoint.read_bytes()[:1000])
    with pytest.raises(CheckpointError, match=r"cut.safetensors"):
        ImaginedEnv(truncated)
    with pytest.raises(FileNotFoundError, match=r"missing.safetensors"):
        ImaginedEnv(tmp_path / "missing.safetensors")


def test_nan_action_is_refused(checkpoint):
    env = ImaginedEnv(checkpoint)
    env.reset(seed=0)
    with pytest.raises(ValueError, match="NaN"):
        env.step(np.full(12, np.nan, dtype=np.float32))


def test_render_draws_the_dream(checkpoint):
    env = ImaginedEnv(checkpoint, render_mode="rgb_array", width=160, height=120)
    env.reset(seed=0)
    try:
        first = env.render()
    except Exception as err:  # no OpenGL backend on this machine
        pytest.skip(f"offscreen rendering unavailable (set MUJOCO_GL=egl or osmesa): {err}")
    for _ in range(10):
        env.step(env.action_space.sample())
    later = env.render()
    assert first.shape == later.shape == (120, 160, 3) and first.std() > 0
    assert not np.array_equal(first, later)  # the drawn robot follows the predicted state


def _vec_rollout(checkpoint, steps=30, **options):
    core = ImaginedSB3VecEnv(checkpoint, num_envs=5, episode_steps=12, **options)
    core.seed(7)
    out = [core.reset()]
    rng = np.random.default_rng(0)
    rewards, infos = [], []
    for _ in range(steps):
        obs, reward, _done, info = core.step(rng.uniform(-1, 1, (5, 12)).astype(np.float32))
        out.append(obs)
        rewards.append(reward)
        infos.append(info)
    return np.stack(out), np.stack(rewards), infos


def test_without_the_penalty_each_env_runs_only_its_head_with_the_same_numbers(checkpoint):
    """Penalty 0: only each env's own head runs and no disagreement; obs and rewards equal the full-ensemble path's."""
    obs_full, rewards_full, infos_full = _vec_rollout(checkpoint, report_uncertainty=True)
    obs_own, rewards_own, infos_own = _vec_rollout(checkpoint)
    np.testing.assert_allclose(obs_own, obs_full, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(rewards_own, rewards_full, rtol=1e-5, atol=1e-5)
    assert "uncertainty" in infos_full[0][0] and "uncertainty" not in infos_own[0][0]
    assert any("episode" in info for step in infos_own for info in step)  # the rollout crossed resets


def test_bfloat16_products_give_nearly_the_float32_rollout(checkpoint):
    obs32, rewards32, _ = _vec_rollout(checkpoint, steps=10)
    obs16, rewards16, _ = _vec_rollout(checkpoint, steps=10, matmul_precision="bfloat16")
    np.testing.assert_allclose(rewards16, rewards32, atol=0.02)
    assert not np.array_equal(obs16, obs32)
    with pytest.raises(ValueError, match="matmul_precision 'float16' unknown"):
        ImaginedSB3VecEnv(checkpoint, num_envs=1, matmul_precision="float16")


def test_batched_reset_windows_are_the_sampled_ones(checkpoint):
    windows = ImaginedEnv(checkpoint).core.reset_windows
    ends = np.array([windows.draw(np.random.default_rng(s)) for s in range(4)])
    batch = windows.gather(ends)
    for row, seed in enumerate(range(4)):
        one = windows.sample(np.random.default_rng(seed))
        for name in ("states", "actions", "contact", "foot_height"):
            np.testing.assert_array_equal(getattr(batch, name)[row], getattr(one, name))


def test_sb3_logs_episode_returns_while_training_in_imagination(checkpoint, tmp_path):
    from stable_baselines3 import PPO
    from stable_baselines3.common.logger import configure

    venv = ImaginedSB3VecEnv(checkpoint, num_envs=4, episode_steps=5)
    model = PPO("MlpPolicy", venv, n_steps=8, batch_size=32, n_epochs=1, seed=0)
    model.set_logger(configure(str(tmp_path), ["csv"]))
    model.learn(64)
    header, *rows = (tmp_path / "progress.csv").read_text().splitlines()
    column = header.split(",").index("rollout/ep_rew_mean")
    assert rows and all(np.isfinite(float(row.split(",")[column])) for row in rows)


def test_cached_warm_ups_give_the_numbers_of_fresh_ones(checkpoint):
    """Each reset window warms up once and is reused: same observations and rewards as warming up on every reset."""
    obs_cached, rewards_cached, infos = _vec_rollout(checkpoint)
    obs_fresh, rewards_fresh, _ = _vec_rollout(checkpoint, warm_up_cache_mb=0.0)
    np.testing.assert_allclose(obs_cached, obs_fresh, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(rewards_cached, rewards_fresh, rtol=1e-5, atol=1e-5)
    assert any("episode" in info for step in infos for info in step)  # the rollout crossed resets
    core = ImaginedSB3VecEnv(checkpoint, 4).core
    assert core.warm_up_cache is not None and not core.warm_up_cache.filled.any()
    core.reset(np.arange(4), [0, 1, 2, 3])
    cache = core.warm_up_cache
    filled = int(cache.filled.sum())
    assert 2 <= filled <= 8  # the drawn windows, each once, and as many undrawn ones (the env count) ahead
    assert cache.filled[: filled - 4].all()  # prefetched in index order
    core.reset(np.arange(4), [0, 1, 2, 3])
    assert int(cache.filled.sum()) == filled  # drawn again: no warm-up, nothing fetched
    assert ImaginedSB3VecEnv(checkpoint, 4, warm_up_cache_mb=0.0).core.warm_up_cache is None


def test_random_first_episode_length_spreads_the_first_restarts(checkpoint):
    """rsl_rl's init_at_random_ep_len: the first episode of each env starts at a random step of its time limit (the
    same for the same seed); every later episode runs the full limit."""
    from rwm_gym.imagination.env import make_imagined_core

    def first_steps(**options):
        core = make_imagined_core(checkpoint, 32, episode_steps=10, **options)
        core.reset(np.arange(32), seeds=list(range(32)))
        return core

    assert (first_steps().steps == 0).all()
    core = first_steps(random_first_episode_length=True)
    assert core.steps.min() >= 0 and core.steps.max() < 10 and len(np.unique(core.steps)) >= 5
    np.testing.assert_array_equal(core.steps, first_steps(random_first_episode_length=True).steps)
    later = np.array([0, 5, 31])
    core.reset(later)
    assert (core.steps[later] == 0).all()  # an env's next episode is a whole one
    venv = ImaginedSB3VecEnv(
        checkpoint, num_envs=32, episode_steps=10, random_first_episode_length=True, divergence_bound=1e9
    )
    venv.seed(0)
    venv.reset()
    ends = []
    for _ in range(10):
        _, _, _dones, infos = venv.step(np.zeros((32, 12), dtype=np.float32))
        ends.append(sum(info.get("TimeLimit.truncated", False) for info in infos))
    assert sum(ends) >= 20 and max(ends) < 32  # restarts come on different steps, not all at once


def test_command_from_history_gives_a_share_of_restarts_the_velocity_their_history_moves_at(checkpoint):
    from rwm_gym.imagination.core import HISTORY_COMMAND_ROWS, ImaginedCore
    from rwm_gym.imagination.options import ImaginationOptions

    n = 64
    spec = load_spec("anymal_d")
    drawn = ImaginedCore(checkpoint, n)
    drawn.reset(np.arange(n), seeds=list(range(n)))
    core = ImaginedCore(checkpoint, n, options=ImaginationOptions(command_from_history=0.5))
    core.reset(np.arange(n), seeds=list(range(n)))
    windows = core.reset_windows.gather(np.array([core.reset_windows.draw(np.random.default_rng(i)) for i in range(n)]))
    recent = windows.states[:, -HISTORY_COMMAND_ROWS:]
    s = spec.state_slices
    moving = np.concatenate([recent[:, :, s["base_lin_vel"]][:, :, :2], recent[:, :, s["base_ang_vel"]][:, :, 2:]], 2)
    velocity = np.clip(moving.mean(axis=1), spec.command.low, spec.command.high)
    from_history = np.all(np.isclose(core.command, velocity, atol=1e-5), axis=1)
    kept = np.all(core.command == drawn.command, axis=1)
    assert 16 <= from_history.sum() <= 48 and np.all(from_history | kept)  # each env: its history's, or its draw
    with pytest.raises(ValueError, match="command_from_history"):
        ImaginationOptions(command_from_history=1.5)

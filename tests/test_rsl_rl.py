"""rsl_rl's own OnPolicyRunner on the imagined (and the physics) env through `CoreRslRlVecEnv`, on tiny budgets."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from rwm_gym.rl.ppo import PPOConfig
from rwm_gym.rl.rsl_rl_train_cfg import rsl_rl_train_cfg

TINY = PPOConfig(num_envs=4, n_steps=8, net_arch=(32, 32))
EPISODE_STEPS = 5  # shorter than a rollout, so time limits fall inside it


def test_train_cfg_carries_the_ppo_config():
    cfg = rsl_rl_train_cfg(PPOConfig(n_steps=24, log_std_init=0.0, target_kl=0.01))
    alg = cfg["algorithm"]
    assert cfg["num_steps_per_env"] == 24 and cfg["actor"]["hidden_dims"] == [128, 128, 128]
    assert cfg["actor"]["activation"] == cfg["critic"]["activation"] == "elu"
    assert cfg["actor"]["distribution_cfg"]["init_std"] == 1.0
    assert (alg["clip_param"], alg["num_learning_epochs"], alg["num_mini_batches"]) == (0.2, 5, 4)
    assert (alg["learning_rate"], alg["schedule"], alg["desired_kl"]) == (1e-3, "adaptive", 0.01)
    assert (alg["gamma"], alg["lam"], alg["entropy_coef"], alg["value_loss_coef"]) == (0.99, 0.95, 0.005, 1.0)
    assert rsl_rl_train_cfg(PPOConfig(target_kl=0.0))["algorithm"]["schedule"] == "fixed"
    with pytest.raises(ValueError, match="positive_reward_only"):
        rsl_rl_train_cfg(PPOConfig(positive_reward_only=True))
    with pytest.raises(ValueError, match="lr_anneal_fraction"):  # rsl_rl's schedules are adaptive or fixed
        rsl_rl_train_cfg(PPOConfig(lr_anneal_fraction=0.25))
    with pytest.raises(ValueError, match="symmetry"):
        rsl_rl_train_cfg(PPOConfig(symmetry=True))


@pytest.fixture()
def rsl_rl():
    return pytest.importorskip("rsl_rl", reason="rsl-rl-lib is not installed (pip install 'rwm-gym[rsl-rl]')")


def _recording_env(num_envs: int, seed: int):
    """The imagined VecEnv, remembering what it was given and what it returned at every step."""
    from rwm_gym.vector.rsl_rl_vec_env import ImaginedRslRlVecEnv

    class Recording(ImaginedRslRlVecEnv):
        def __init__(self, *args, **kwargs):
            self.steps_seen: list[dict] = []
            super().__init__(*args, **kwargs)

        def step(self, actions):
            obs, rewards, dones, extras = super().step(actions)
            self.steps_seen.append(
                {
                    "actions": actions.clone(),
                    "obs": obs["policy"].clone(),
                    "rewards": rewards,
                    "dones": dones,
                    "time_outs": extras["time_outs"],
                    "log": extras.get("log"),
                }
            )
            return obs, rewards, dones, extras

    return Recording(None, num_envs, seed=seed, episode_steps=EPISODE_STEPS)


def test_on_policy_runner_trains_in_imagination_on_the_cores_numbers(rsl_rl, tmp_path):
    from rsl_rl.runners import OnPolicyRunner

    from rwm_gym.imagination.env import make_imagined_core
    from rwm_gym.vector.autoreset import step_with_autoreset

    torch.manual_seed(0)
    env = _recording_env(TINY.num_envs, seed=3)
    runner = OnPolicyRunner(env, rsl_rl_train_cfg(TINY), log_dir=str(tmp_path), device="cpu")
    assert (runner.alg.clip_param, runner.alg.num_learning_epochs, runner.alg.num_mini_batches) == (0.2, 5, 4)
    before = [p.detach().clone() for p in runner.alg.actor.parameters()]
    runner.learn(num_learning_iterations=2)

    seen = env.steps_seen
    assert len(seen) == 2 * TINY.n_steps
    for s in seen:
        assert s["obs"].shape == (4, 48) and s["obs"].dtype == torch.float32
        assert s["rewards"].shape == (4,) and s["rewards"].dtype == torch.float32
        assert s["dones"].shape == (4,) and s["time_outs"].shape == (4,) and s["time_outs"].dtype == torch.bool
        assert not (s["time_outs"] & (s["dones"] == 0)).any()  # a time-out is always a done
    assert any(not torch.equal(a, b) for a, b in zip(before, runner.alg.actor.parameters()))
    assert (tmp_path / "model_1.pt").is_file()  # the runner's own checkpoint

    # the same actions on a bare core with the same seeds: the adapter handed over exactly the core's numbers
    core = make_imagined_core(None, TINY.num_envs, episode_steps=EPISODE_STEPS)
    core.reset(np.arange(TINY.num_envs), [3, 4, 5, 6])
    truncations = 0
    for s in seen:
        obs, reward, terminated, truncated, *_ = step_with_autoreset(core, s["actions"].double().numpy())
        np.testing.assert_array_equal(s["rewards"].numpy(), reward.astype(np.float32))
        np.testing.assert_array_equal(s["dones"].numpy(), (terminated | truncated).astype(np.int64))
        np.testing.assert_array_equal(s["time_outs"].numpy(), truncated & ~terminated)
        np.testing.assert_array_equal(s["obs"].numpy(), obs.astype(np.float32))
        truncations += int(truncated.sum())
    assert truncations > 0  # 16 steps with a 5-step limit: time-outs were exercised
    logs = [s["log"] for s in seen if s["log"]]
    assert logs and all("Episode_Termination/time_out" in log for log in logs)
    assert any(key.startswith("Episode_Term/") for key in logs[0])


def test_episode_length_buf_is_the_time_limit(rsl_rl):
    env = _recording_env(3, seed=0)
    assert env.max_episode_length == EPISODE_STEPS and env.episode_length_buf.tolist() == [0, 0, 0]
    env.step(torch.zeros(3, 12))
    assert env.episode_length_buf.tolist() == [1, 1, 1]
    env.episode_length_buf = torch.full((3,), EPISODE_STEPS - 1)  # what init_at_random_ep_len does
    _, _, dones, extras = env.step(torch.zeros(3, 12))
    assert dones.tolist() == [1, 1, 1] and extras["time_outs"].all()
    assert env.episode_length_buf.tolist() == [0, 0, 0]  # reset in the same step
    with pytest.raises(ValueError, match="episode_length_buf must have shape"):
        env.episode_length_buf = torch.zeros(5)
    with pytest.raises(ValueError, match="NaN"):
        env.step(torch.full((3, 12), float("nan")))


def test_physics_env_holds_a_command_and_matches_its_core(rsl_rl):
    from rwm_gym.physics.locomotion import make_core
    from rwm_gym.vector.rsl_rl_vec_env import LocomotionRslRlVecEnv

    env = LocomotionRslRlVecEnv(2, seed=7)
    assert env.num_actions == 12 and env.max_episode_length == 1000 and env.cfg.to_dict()["task"]
    core = make_core("anymal_d", 2)
    core.reset(np.arange(2), [7, 8])
    actions = torch.linspace(-0.3, 0.3, 24).reshape(2, 12)
    for _ in range(3):
        obs, rewards, dones, _ = env.step(actions)
        expected_obs, expected_reward, terminated, truncated, _ = core.step(actions.double().numpy())
        np.testing.assert_array_equal(rewards.numpy(), expected_reward.astype(np.float32))
        np.testing.assert_array_equal(dones.numpy(), (terminated | truncated).astype(np.int64))
        np.testing.assert_array_equal(obs["policy"].numpy(), expected_obs.astype(np.float32))
    obs = env.reset(seed=0, command=(1.0, 0.0, 0.0))
    command = slice(9, 12)  # base lin vel 3, ang vel 3, gravity 3, then the command
    np.testing.assert_array_equal(obs["policy"][:, command].numpy(), [[1.0, 0.0, 0.0]] * 2)


def test_torchrun_trains_on_two_cpu_ranks_with_rsl_rls_multi_gpu_mode(rsl_rl, tmp_path):
    """The example under torchrun: 2 gloo ranks, each its own imagined batch; rsl_rl's collectives (parameter
    broadcast, gradient and normaliser all-reduce) run between them, and rank 0 alone logs and saves."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    env = {
        **os.environ,
        "OMP_NUM_THREADS": "1",
        "PYTHONPATH": os.pathsep.join(filter(None, [str(root), os.environ.get("PYTHONPATH")])),
    }
    command = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2"]
    command += [str(root / "examples" / "rsl_rl_imagination.py"), "--num-envs", "2", "--iterations", "2"]
    command += ["--episode-steps", "10", "--score-seeds", "0", "--log-dir", str(tmp_path)]
    done = subprocess.run(command, env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "trained 192 imagined steps on 2 process(es)" in done.stdout  # 2 iterations x 24 steps x 2 envs x 2 ranks
    assert "Total steps: 192" in done.stdout  # rsl_rl counts both ranks' steps
    assert done.stdout.count("trained ") == 1  # rank 0 reports
    assert (tmp_path / "model_1.pt").is_file()
    assert len(list(tmp_path.glob("events.out.tfevents.*"))) == 1

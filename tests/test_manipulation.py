"""The Kinova Jaco arm of dm_control.manipulation (DMC-Jaco-ReachSite-v0, DMC-Jaco-LiftBrick-v0): the goal's reward
and success from the state against dm_control's own, the generated specs, and a tiny collect -> train -> evaluate ->
PPO in imagination -> physics success chain through the CLI. The checks every `DMC-*` id shares (checkers, layout,
determinism, collection, a tiny world model) run in tests/test_dmc.py and tests/test_imagined_dmc.py."""

from __future__ import annotations

import json
from pathlib import Path

import gymnasium as gym
import mujoco
import numpy as np
import pytest

import rwm_gym  # noqa: F401  (registers the envs)
from rwm_gym.cli import main
from rwm_gym.data.dataset import Dataset
from rwm_gym.imagination.options import ImaginationOptions
from rwm_gym.physics.dmc import make_core
from rwm_gym.policies.factory import make_policy
from rwm_gym.spec import load_spec, parse_spec
from rwm_gym.task.manipulation_reward import ManipulationReward
from rwm_gym.task.tasks import state_reward

REACH, LIFT = "DMC-Jaco-ReachSite-v0", "DMC-Jaco-LiftBrick-v0"
SPECS = {REACH: "dmc_jaco_reach_site", LIFT: "dmc_jaco_lift_brick"}


def _site(env, name: str) -> int:
    return mujoco.mj_name2id(env.physics.model.ptr, mujoco.mjtObj.mjOBJ_SITE, name)


def test_reach_reward_and_success_from_the_state_match_dm_control_in_physics() -> None:
    env = gym.make(REACH).unwrapped
    reward = state_reward(env.task_spec)
    ours, theirs = [], []
    for seed in range(3):
        env.reset(seed=seed)
        rng, action = np.random.default_rng(seed), np.zeros(env.action_space.shape)
        for _ in range(60):
            action = np.clip(0.9 * action + 0.5 * rng.standard_normal(action.shape), -1, 1)
            _, physics_reward, _, _, info = env.step(action)
            state = env.record()["state"][None]
            ours.append(reward(state)[0])
            theirs.append(physics_reward)
            assert info["success"] == reward.success(state)[0] == (physics_reward >= 1.0)
    assert np.abs(np.array(ours) - np.array(theirs)).mean() < 1e-6
    # the target moved to 3 cm beside the pinch site (inside dm_control's 5 cm radius): the goal is met
    model, data = env.physics.model.ptr, env.physics.data.ptr
    model.site_pos[_site(env, "target_site")] = data.site_xpos[_site(env, "jaco_arm/jaco_hand/pinchsite")] + [
        0.03,
        0,
        0,
    ]
    _, physics_reward, _, _, info = env.step(np.zeros(env.action_space.shape))
    assert physics_reward == 1.0 and info["success"] and reward.success(env.record()["state"][None])[0]


def test_lift_reward_from_the_state_matches_dm_control_over_brick_poses() -> None:
    env = gym.make(LIFT).unwrapped
    env.reset(seed=0)
    reward, task = ManipulationReward(env.task_spec), env.core.envs[0].env.task
    model, data = env.physics.model.ptr, env.physics.data.ptr
    brick = model.jnt_qposadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, "duplo2x4/")]
    rng, ours, theirs = np.random.default_rng(0), [], []
    for height in np.linspace(0.0, 0.45, 16):
        quaternion = rng.standard_normal(4)
        data.qpos[brick : brick + 7] = [*rng.uniform(-0.1, 0.1, 2), height, *quaternion / np.linalg.norm(quaternion)]
        mujoco.mj_forward(model, data)
        state = env.core.layout.state(data)[None]
        ours.append(reward(state)[0])
        theirs.append(task.get_reward(env.physics))
    np.testing.assert_allclose(ours, theirs, atol=1e-5)
    assert min(theirs) < 0.5 and max(theirs) == 1.0  # the poses span the reward from rest to the goal


@pytest.mark.parametrize("env_id", [REACH, LIFT])
def test_the_shipped_spec_is_what_spec_from_dmc_writes(env_id: str, tmp_path: Path) -> None:
    shipped = load_spec(SPECS[env_id])
    task = shipped.extra["dm_control"]["task"]
    out = tmp_path / "arm.toml"
    assert (
        main(["spec", "--from-dmc", f"manipulation-{task}", "--out", str(out), "--episodes", "1", "--steps", "5"]) == 0
    )
    made = load_spec(out)
    assert made.physics_env_id == env_id and made.imagined_env_id == shipped.imagined_env_id
    assert made.state_columns == shipped.state_columns and made.actuator.joints == shipped.actuator.joints
    assert made.privileged == shipped.privileged and made.observation == shipped.observation
    assert made.extra == shipped.extra and (made.policy_dt, made.episode_steps) == (0.04, 250)


def test_bad_manipulation_input_fails_in_one_line(tmp_path: Path, capsys) -> None:
    out = str(tmp_path / "x.toml")
    assert main(["spec", "--from-dmc", "manipulation-reach_nowhere", "--out", out]) == 2
    assert "dm_control.manipulation has no task 'reach_nowhere'" in capsys.readouterr().err
    assert main(["spec", "--from-dmc", "manipulation-reach_site_vision", "--out", out]) == 2
    assert "use a *_features task" in capsys.readouterr().err
    text = load_spec(SPECS[REACH]).text
    with pytest.raises(ValueError, match=r"\[manipulation\] field 'target_radius' missing for goal 'reach'"):
        ManipulationReward(parse_spec(text.replace("target_radius = 0.05", "")))
    with pytest.raises(ValueError, match=r"\[manipulation\] goal 'push' unknown"):
        ManipulationReward(parse_spec(text.replace('goal = "reach"', 'goal = "push"')))
    with pytest.raises(ValueError, match="column 'target_site' is not NAME:component"):
        make_core(parse_spec(text.replace('"target_site:x"', '"target_site"')))


TINY_TRAIN = ["--iterations", "4", "--history", "4", "--forecast", "2", "--batch-size", "8", "--hidden-size", "16"]
TINY_TRAIN += ["--num-layers", "1", "--head-hidden", "16", "--val-fraction", "0.25", "--quiet"]


def test_reach_from_collection_to_ppo_in_imagination_judged_by_success_in_physics(tmp_path: Path) -> None:
    data, ckpt, policy = tmp_path / "reach.h5", tmp_path / "reach.safetensors", tmp_path / "reach_ppo.zip"
    collect = ["collect", "--env", REACH, "--policy", "random", "--episodes", "4", "--num-envs", "2"]
    assert main([*collect, "--max-steps", "30", "--out", str(data)]) == 0
    assert main(["train", "--data", str(data), "--out", str(ckpt), *TINY_TRAIN]) == 0
    evaluate = ["evaluate", "--checkpoint", str(ckpt), "--data", str(data), "--history", "4", "--horizons", "2"]
    assert main([*evaluate, "--max-horizon", "4", "--all-episodes", "--quiet"]) == 0
    imagined = gym.make("RWM-Jaco-ReachSite-v0", checkpoint=str(ckpt))
    start, _ = imagined.reset(seed=0)
    observations = [imagined.step(imagined.action_space.sample())[0] for _ in range(5)]
    info = imagined.step(imagined.action_space.sample())[-1]
    assert isinstance(info["success"], (bool, np.bool_))  # judged on the predicted state
    spec = load_spec(SPECS[REACH])
    target = [spec.state_columns.index(f"site_pos/target_site:{c}") for c in "xyz"]
    hand = [spec.state_columns.index(f"site_pos/jaco_arm/jaco_hand/pinchsite:{c}") for c in "xyz"]
    assert all(np.array_equal(obs[target], start[target]) for obs in observations)  # the goal is held, not predicted
    assert not np.array_equal(observations[-1][hand], start[hand])  # the hand moves
    # angles and the hand are the arm's kinematics of the predicted velocities: closing the step again changes nothing
    from rwm_gym.imagination.kinematics import KinematicClosure

    closure, s = KinematicClosure.of(spec), spec.state_dim
    closed = observations[1][None, :s].astype(np.float64)
    closure.apply(observations[0][None, :s].astype(np.float64), closed)
    assert np.allclose(closed[0], observations[1][:s], atol=1e-5)
    free = gym.make("RWM-Jaco-ReachSite-v0", checkpoint=str(ckpt), options=ImaginationOptions(kinematics=False))
    free.reset(seed=0)
    first, second = (free.step(action)[0] for action in [imagined.action_space.sample()] * 2)
    reclosed = second[None, :s].astype(np.float64)
    closure.apply(first[None, :s].astype(np.float64), reclosed)
    assert not np.allclose(reclosed[0], second[:s], atol=1e-5)  # without it, the model's own prediction
    ppo = ["ppo", "--checkpoint", str(ckpt), "--timesteps", "64", "--num-envs", "4", "--n-steps", "16"]
    assert main([*ppo, "--net-arch", "16", "--eval-seeds", "2", "--eval-steps", "10", "--out", str(policy)]) == 0
    evaluation = json.loads(policy.with_suffix(".json").read_text())["evaluation"]
    assert evaluation["env_id"] == REACH and evaluation["episodes"] == 2 and evaluation["steps"] == 10
    assert 0.0 <= evaluation["success_rate"] <= 1.0 and 0.0 <= evaluation["episode_return"] <= 10.0


def test_the_scripted_reach_meets_the_target_in_physics_and_noise_makes_it_miss() -> None:
    from rwm_gym.policies.reach import ReachPolicy
    from rwm_gym.rl.evaluate_dmc import evaluate_episodes

    spec = load_spec(SPECS[REACH])
    clean = evaluate_episodes(ReachPolicy(spec, 6).act, REACH, seeds=6)
    assert clean.success_rate >= 5 / 6 and clean.success_steps > 0.5
    noisy = ReachPolicy(spec, 6, action_noise=0.5)
    noisy.reset(np.arange(6), [np.random.default_rng(k) for k in range(6)])
    assert evaluate_episodes(noisy.act, REACH, seeds=6).success_steps < clean.success_steps / 2


def test_collect_with_the_reach_policy_is_deterministic(tmp_path: Path) -> None:
    runs = []
    for name in ("a.h5", "b.h5"):
        collect = ["collect", "--env", REACH, "--policy", "reach", "--action-noise", "0.2", "--episodes", "3"]
        assert main([*collect, "--num-envs", "2", "--max-steps", "20", "--out", str(tmp_path / name)]) == 0
        runs.append(Dataset.load(tmp_path / name))
    assert runs[0].info.policy == "reach"
    np.testing.assert_array_equal(runs[0]["state"], runs[1]["state"])
    with pytest.raises(ValueError, match="needs a \\[manipulation\\] goal = 'reach'"):
        make_policy("reach", load_spec(SPECS[LIFT]), 1)


def test_ppo_in_physics_trains_on_a_dm_control_task_and_is_judged_by_success(tmp_path: Path, capsys) -> None:
    policy = tmp_path / "reach_physics.zip"
    ppo = ["ppo", "--in", "physics", "--env", REACH, "--timesteps", "32", "--num-envs", "2", "--n-steps", "16"]
    assert main([*ppo, "--net-arch", "16", "--eval-seeds", "2", "--eval-steps", "10", "--out", str(policy)]) == 0
    report = json.loads(policy.with_suffix(".json").read_text())
    assert report["where"] == "physics" and report["env"] == REACH and report["physics_samples"] >= 32
    assert report["evaluation"]["env_id"] == REACH and 0.0 <= report["evaluation"]["success_rate"] <= 1.0
    with pytest.raises(SystemExit, match="--env applies to --in physics"):
        main(["ppo", "--env", REACH, "--timesteps", "32", "--out", str(tmp_path / "x.zip")])

"""The shipped Unitree Go2: its physics env stands on its own figures, and a user's chain runs on it end to end."""

from __future__ import annotations

import json
from pathlib import Path

import gymnasium as gym
import mujoco
import numpy as np

import rwm_gym  # noqa: F401  (registers the envs)
from rwm_gym.cli import main
from rwm_gym.resources import assets_dir
from rwm_gym.spec import load_spec
from tests.test_new_robot import TINY_TRAIN


def test_the_go2_stands_still_on_zero_actions_with_its_own_torque_limits() -> None:
    spec = load_spec("go2")
    env = gym.make("Go2-MuJoCo-v0")
    model = env.unwrapped.model
    for joint, limit in zip(spec.actuator.joints, spec.actuator.per_joint("effort_limit")):
        a = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_ACTUATOR, joint)
        assert model.actuator_forcerange[a].tolist() == [-limit, limit]
    assert sorted(set(spec.actuator.per_joint("effort_limit"))) == [23.7, 45.43]  # hips and thighs, calves
    env.reset(seed=0, options={"command": (0.0, 0.0, 0.0)})
    for _ in range(250):  # 5 s
        _, _, terminated, _, _ = env.step(np.zeros(12, np.float32))
        assert not terminated
    core = env.unwrapped.core
    assert core.current.contact[0, 4:].all() and not core.current.contact[0, :4].any()  # feet down, thighs up
    assert 0.26 < env.unwrapped.data.qpos[2] < 0.31


def test_go2_commands_scores_and_the_imagined_id_are_its_own() -> None:
    spec = load_spec("go2")
    assert (spec.physics_env_id, spec.imagined_env_id) == ("Go2-MuJoCo-v0", "RWM-Go2-v0")
    assert spec.model_path == assets_dir() / "go2" / "scene.xml"
    assert max(spec.command.high) >= 1.0  # at least 1 m/s forward


def test_a_go2_from_its_mjcf_to_a_scored_imagination_policy(tmp_path: Path, capsys) -> None:
    """spec -> collect -> train -> PPO in imagination -> score in physics, on tiny budgets, as a user would."""
    spec, data, ckpt = tmp_path / "go2.toml", tmp_path / "go2.h5", tmp_path / "go2.safetensors"
    xml = str(assets_dir() / "go2" / "scene.xml")
    assert main(["spec", "--mjcf", xml, "--out", str(spec), "--episodes", "1", "--steps", "20"]) == 0
    assert load_spec(spec).actuator.per_joint("effort_limit").tolist() == [23.7, 23.7, 45.43] * 4
    collect = ["collect", "--env", str(spec), "--policy", "random", "--episodes", "2", "--max-steps", "40"]
    assert main([*collect, "--out", str(data)]) == 0
    assert main(["train", "--data", str(data), "--out", str(ckpt), *TINY_TRAIN]) == 0
    policy = tmp_path / "policy.zip"
    ppo = ["ppo", "--in", "imagination", "--checkpoint", str(ckpt), "--timesteps", "256", "--num-envs", "16"]
    assert main([*ppo, "--n-steps", "8", "--no-eval", "--out", str(policy)]) == 0
    score = ["score", "--policy", str(policy), "--env", str(spec), "--out", str(tmp_path / "score"), "--seeds", "1"]
    assert main([*score, "--commands", "1", "--steps", "30"]) == 0
    report = json.loads((tmp_path / "score" / "score.json").read_text())
    assert report["task"] == load_spec(spec).name and report["episodes"] == 3
    assert 0.0 <= report["tracking"] <= 1.0 and report["floor"]["falls"] == 0


def test_score_refuses_an_env_that_is_not_the_checkpoints_task(tmp_path: Path, capsys) -> None:
    ckpt = assets_dir() / "checkpoints" / "anymal_d_rwm.safetensors"
    args = ["score", "--policy", "zero", "--checkpoint", str(ckpt), "--env", "Go2-MuJoCo-v0"]
    try:
        code, message = main([*args, "--out", str(tmp_path / "s")]), capsys.readouterr().err
    except SystemExit as err:  # the command's one-line refusal, as a message or a code with the line on stderr
        code = 2 if isinstance(err.code, str) else err.code
        message = err.code if isinstance(err.code, str) else capsys.readouterr().err
    assert code == 2 and "AnymalD model" in message and "Go2" in message

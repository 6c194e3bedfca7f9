"""What a user of the physics and imagined envs relies on: a public command API, Gymnasium 1.x vector infos, SB3
episode infos, bounded `num_envs`, no step before reset, and a shipped checkpoint that still loads when copied."""

from __future__ import annotations

import shutil

import gymnasium as gym
import numpy as np
import pytest

import rwm_gym
from rwm_gym.imagination.core import default_checkpoint
from rwm_gym.task.observation import observation_slices
from rwm_gym.vector.sb3_vec_env import ImaginedSB3VecEnv

PHYSICS, IMAGINED = "AnymalD-MuJoCo-v0", "RWM-AnymalD-v0"
COMMAND = (0.6, -0.2, 0.3)


def make_vec(env_id: str, num_envs: int, **kwargs):
    extra = {"nthread": 1} if env_id == PHYSICS else {}
    return gym.make_vec(env_id, num_envs=num_envs, vectorization_mode="vector_entry_point", **extra, **kwargs)


@pytest.mark.parametrize("env_id", [PHYSICS, IMAGINED])
def test_reset_options_command_is_observed_and_held(env_id):
    env = gym.make(env_id)
    command_slice = observation_slices(env.unwrapped.task_spec)["command"]
    obs, info = env.reset(seed=0, options={"command": COMMAND})
    np.testing.assert_allclose(info["command"], COMMAND, rtol=1e-6)
    np.testing.assert_allclose(obs[command_slice], COMMAND, rtol=1e-6)
    with pytest.raises(ValueError, match="command must be 3 finite numbers"):
        env.reset(options={"command": (1.0, 2.0)})
    with pytest.raises(ValueError, match="unknown reset option 'speed'"):
        env.reset(options={"speed": 1.0})
    env.close()


def test_a_held_command_survives_the_resample_period_and_a_sampled_one_does_not():
    env = gym.make(IMAGINED, episode_steps=2000)
    period = env.unwrapped.core.task.period
    for options, changes in (({"command": COMMAND}, False), (None, True)):
        env.reset(seed=1, options=options)
        first = env.unwrapped.core.command[0].copy()
        for _ in range(period + 1):  # a step's info shows the command its action was chosen under
            *_, info = env.step(np.zeros(12, np.float32))
        assert (not np.array_equal(info["command"], first)) == changes


def test_resample_commands_switch_on_the_physics_env():
    env = gym.make(PHYSICS, resample_commands=False)
    env.reset(seed=0)
    assert not env.unwrapped.core.task.resample_commands


@pytest.mark.parametrize("env_id", [PHYSICS, IMAGINED])
def test_vector_env_holds_the_command_through_auto_resets(env_id):
    vec = make_vec(env_id, 2, **({"episode_steps": 3} if env_id == IMAGINED else {"xml_file": None}))
    vec.reset(seed=0, options={"command": COMMAND})
    for _ in range(4):
        _obs, _, _terminated, _truncated, info = vec.step(np.zeros((2, 12), np.float32))
    np.testing.assert_allclose(info["command"], np.tile(COMMAND, (2, 1)), rtol=1e-6)


@pytest.mark.parametrize("env_id", [PHYSICS, IMAGINED])
def test_vector_env_refuses_step_before_reset(env_id):
    vec = make_vec(env_id, 2)
    with pytest.raises(gym.error.ResetNeeded):
        vec.step(np.zeros((2, 12), np.float32))


@pytest.mark.parametrize("env_id", [PHYSICS, IMAGINED])
def test_vector_infos_follow_gymnasium_key_masks(env_id):
    vec = make_vec(env_id, 2)
    vec.reset(seed=0)
    _, _, _, _, info = vec.step(np.zeros((2, 12), np.float32))
    keys = [k for k in info if not k.startswith("_")]
    assert "command" in keys
    for key in keys:
        assert info[f"_{key}"].dtype == bool and info[f"_{key}"].shape == (2,)


@pytest.mark.parametrize("num_envs", [0, -1, 100_000, 2.5])
@pytest.mark.parametrize("env_id", [PHYSICS, IMAGINED])
def test_num_envs_out_of_range_is_refused_in_one_line(env_id, num_envs):
    with pytest.raises(ValueError, match="num_envs must be an integer from 1 to"):
        make_vec(env_id, num_envs)


def test_imagined_sb3_vec_env_reports_episode_returns():
    venv = ImaginedSB3VecEnv(num_envs=2, episode_steps=3)
    venv.seed(0)
    venv.reset()
    total = np.zeros(2)
    for _ in range(3):
        _, reward, done, infos = venv.step(np.zeros((2, 12), np.float32))
        total += reward
    assert done.all()
    for i in range(2):
        assert infos[i]["episode"]["l"] == 3
        assert infos[i]["episode"]["r"] == pytest.approx(total[i], rel=1e-5)


def test_sb3_infos_hold_each_envs_entries_of_the_batched_arrays():
    from rwm_gym.vector.sb3_vec_env import per_env_infos

    info = {"reward/lin_vel": np.array([0.5, 0.25]), "fall_tilt": np.array([True, False]), "command": np.eye(2)}
    infos = per_env_infos(info, 2)
    assert [d["reward/lin_vel"] for d in infos] == [0.5, 0.25] and [d["fall_tilt"] for d in infos] == [True, False]
    assert all(np.array_equal(infos[i]["command"], np.eye(2)[i]) for i in range(2))
    infos[0]["terminal_observation"] = 1  # each env's own dict
    assert "terminal_observation" not in infos[1] and per_env_infos({}, 3) == [{}, {}, {}]


def test_a_copy_of_the_shipped_checkpoint_finds_its_reset_data(tmp_path):
    copy = tmp_path / "mine.safetensors"
    shutil.copy(default_checkpoint(), copy)
    env = gym.make(IMAGINED, checkpoint=copy)
    obs, _ = env.reset(seed=0)
    assert np.isfinite(obs).all()


def test_reset_data_of_another_task_is_refused(tmp_path):
    from rwm_gym.data.collect import collect

    other = collect("DMC-Cheetah-Run-v0", "random", 1, tmp_path / "cheetah.h5", max_steps=3, progress=False)
    with pytest.raises(ValueError, match=r"reset data .* is of task DMC-Cheetah-Run, the world model .* of AnymalD"):
        gym.make(IMAGINED, reset_data=other)


def test_physics_dt_that_disagrees_with_the_mjcf_is_refused_in_one_line():
    from rwm_gym.physics.locomotion import LocomotionCore
    from rwm_gym.spec import load_spec, parse_spec

    text = load_spec("anymal_d").text.replace("physics_dt = 0.005", "physics_dt = 0.004")
    with pytest.raises(ValueError, match=r"physics_dt is 0.004 s but the MJCF .* steps 0.005 s"):
        LocomotionCore(parse_spec(text))


def test_render_fps_and_excitation_step_come_from_the_spec():
    from rwm_gym.policies.excitation import ExcitationConfig, ExcitationPolicy
    from rwm_gym.spec import load_spec, parse_spec

    assert gym.make(IMAGINED).metadata["render_fps"] == gym.make(PHYSICS).metadata["render_fps"] == 50
    spec = load_spec("anymal_d")
    slow = parse_spec(spec.text.replace("policy_dt = 0.02", "policy_dt = 0.04"))
    for task, dt in ((spec, 0.02), (slow, 0.04)):
        policy = ExcitationPolicy(task, 1, ExcitationConfig())
        policy.reset(np.array([0]), [np.random.default_rng(0)])
        before = policy.phase.copy()
        policy.act(np.zeros((1, 48)))
        np.testing.assert_allclose(policy.phase - before, 2 * np.pi * policy.freq * dt)


def test_record_video_writes_an_mp4_with_the_video_extra(tmp_path):
    pytest.importorskip("moviepy", reason="the [video] extra (moviepy) is not installed")
    env = gym.make(PHYSICS, render_mode="rgb_array", width=64, height=48)
    try:
        env.reset(seed=0)
        env.render()
    except Exception as err:  # no OpenGL backend on this machine
        pytest.skip(f"offscreen rendering unavailable (set MUJOCO_GL=egl or osmesa): {err}")
    env = gym.wrappers.RecordVideo(
        env, str(tmp_path / "videos"), episode_trigger=lambda episode: True, disable_logger=True
    )
    env.reset(seed=0)
    for _ in range(10):
        env.step(np.zeros(12, np.float32))
    env.close()
    videos = list((tmp_path / "videos").glob("*.mp4"))
    assert len(videos) == 1 and videos[0].stat().st_size > 0


@pytest.mark.parametrize("env_id", [PHYSICS, IMAGINED])
def test_a_rendering_script_that_forgets_close_exits_without_a_traceback(env_id):
    import os
    import subprocess
    import sys
    from pathlib import Path

    script = (
        f"import gymnasium as gym, rwm_gym\nenv = gym.make({env_id!r}, render_mode='rgb_array', width=64, "
        f"height=48)\nenv.reset(seed=0)\nprint(env.render().shape)\n"
    )
    root = str(Path(rwm_gym.__file__).parents[1])
    done = subprocess.run(
        [sys.executable, "-c", script],
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "PYTHONPATH": root},
    )
    if done.returncode != 0:
        pytest.skip(f"offscreen rendering unavailable: {done.stderr.strip().splitlines()[-1:]}")
    assert "(48, 64, 3)" in done.stdout
    assert "Traceback" not in done.stderr and "Exception ignored" not in done.stderr


@pytest.mark.parametrize(
    ("env_id", "not_imported"),
    [
        (PHYSICS, {"stable_baselines3", "torch"}),
        ("DMC-Cheetah-Run-v0", {"stable_baselines3", "torch"}),
        (IMAGINED, {"stable_baselines3"}),
    ],
)
def test_a_gymnasium_vector_env_does_not_import_sb3(env_id, not_imported):
    """`rwm_gym.vector` keeps each API's adapters in their own module: a Gymnasium user steps physics without SB3 or
    torch, and imagination without SB3."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    script = (
        f"import sys, gymnasium as gym, rwm_gym\n"
        f"env = gym.make_vec({env_id!r}, num_envs=2, vectorization_mode='vector_entry_point')\n"
        f"env.reset(seed=0)\nenv.step(env.action_space.sample())\n"
        f"print(sorted(set({sorted(not_imported)!r}) & set(sys.modules)))\n"
    )
    root = str(Path(rwm_gym.__file__).parents[1])
    done = subprocess.run(
        [sys.executable, "-c", script],
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "PYTHONPATH": root},
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip().splitlines()[-1] == "[]"

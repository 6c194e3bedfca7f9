"""Collections: what `rwm-gym collect` writes reads back exactly, is deterministic, and survives being killed."""

from __future__ import annotations

import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from rwm_gym.cli import main
from rwm_gym.data.collect import collect, diverged_episodes, finished_collection
from rwm_gym.data.dataset import Dataset, DatasetError
from rwm_gym.spec import load_spec

ENV_ID = "AnymalD-MuJoCo-v0"


def test_collected_file_round_trips(tmp_path):
    path = collect(ENV_ID, "random", 3, tmp_path / "d.h5", seed=5, num_envs=2, max_steps=40, progress=False)
    ds = Dataset.load(path)
    spec = load_spec("anymal_d")
    assert ds.num_episodes == 3 and ds.info.complete
    assert ds.info.env_id == ENV_ID and ds.info.spec_text == spec.text and ds.info.dt == spec.policy_dt
    assert ds.info.policy == "random" and ds.info.seed == 5
    assert ds.info.columns["state"] == list(spec.state_columns)
    assert ds.info.physics_params["kp_scale"] == 1.0
    assert ds["qpos"].shape[1] == 19 and ds["qvel"].shape[1] == 18
    for i in range(ds.num_episodes):
        ep = ds.episode(i)
        assert ep["terminated"][-1] or ep["truncated"][-1]
        assert not ep["terminated"][:-1].any() and not ep["truncated"][:-1].any()
        assert np.all(ep["action"][-1] == 0)
    # state[t+1] follows from (state[t], action[t]): re-simulating row 0 with action 0 reproduces row 1.
    from rwm_gym.physics.locomotion import LocomotionEnv

    env = LocomotionEnv()
    env.reset(seed=5)  # episode 0 starts from seed + 0
    ep = ds.episode(0)
    np.testing.assert_array_equal(env.record()["state"], ep["state"][0])
    env.step(ep["action"][0])
    np.testing.assert_allclose(env.record()["state"], ep["state"][1], rtol=1e-6, atol=1e-6)


def test_collection_is_deterministic_and_independent_of_env_count(tmp_path):
    a = Dataset.load(collect(ENV_ID, "random", 2, tmp_path / "a.h5", seed=1, num_envs=1, max_steps=25, progress=False))
    b = Dataset.load(collect(ENV_ID, "random", 2, tmp_path / "b.h5", seed=1, num_envs=2, max_steps=25, progress=False))
    for field in ("state", "action", "contact", "qpos", "reward"):
        np.testing.assert_array_equal(a[field], b[field])


def test_workers_and_env_counts_write_the_same_bytes(tmp_path):
    """Episodes of different lengths (random actions make ANYmal fall) finish out of order; the file does not show
    it."""
    kwargs = dict(seed=0, max_steps=100, progress=False)
    one = collect(ENV_ID, "random", 7, tmp_path / "one.h5", num_envs=1, **kwargs)
    two = collect(ENV_ID, "random", 7, tmp_path / "two.h5", num_envs=3, workers=2, **kwargs)
    wide = collect(ENV_ID, "random", 7, tmp_path / "wide.h5", num_envs=4, **kwargs)
    lengths = Dataset.load(one).episode_lengths
    assert len(set(lengths)) > 1  # the case where the finishing order differs from the episode order
    assert one.read_bytes() == two.read_bytes() == wide.read_bytes()


def test_an_episode_whose_physics_blows_up_ends_before_the_blow_up(tmp_path, capsys):
    """The MJCF's 4 solver iterations blow up on ice (ground friction 0.05) in the first walking episode; MuJoCo
    resets the robot and would carry on from there."""
    out = tmp_path / "ice.h5"
    physics = '{"ground_friction": 0.05}'
    args = ["collect", "--policy", "gait", "--episodes", "2", "--max-steps", "150", "--physics", physics]
    assert main([*args, "--out", str(out)]) == 0
    assert "the physics blew up in 1 of 2 episodes" in capsys.readouterr().err
    ds = Dataset.load(out)
    assert diverged_episodes(ds).tolist() == [0] and ds.episode_lengths.tolist() == [24, 151]
    first = ds.episode(0)
    assert first["truncated"][-1] and not first["terminated"].any()  # a log that stops, not a fall
    solved = {"physics": {"ground_friction": 0.05}, "solver": {"iterations": 100, "ls_iterations": 50}}
    converged = collect(ENV_ID, "gait", 2, tmp_path / "solved.h5", max_steps=150, env_kwargs=solved, progress=False)
    assert len(diverged_episodes(Dataset.load(converged))) == 0


def test_the_zero_policy_stands_still_and_its_noise_is_seeded(tmp_path):
    path = collect(ENV_ID, "zero", 2, tmp_path / "zero.h5", seed=0, max_steps=40, progress=False)
    assert np.all(Dataset.load(path)["action"] == 0.0)
    noisy = [
        collect(ENV_ID, "zero", 2, tmp_path / f"noisy{k}.h5", seed=0, max_steps=40, action_noise=0.1, progress=False)
        for k in range(2)
    ]
    actions = Dataset.load(noisy[0])["action"]
    assert 0.05 < actions.std() < 0.15 and np.array_equal(actions, Dataset.load(noisy[1])["action"])


def test_workers_need_a_policy_by_name(tmp_path):
    from rwm_gym.policies.factory import make_policy

    with pytest.raises(ValueError, match="workers must be >= 1"):
        collect(ENV_ID, "random", 2, tmp_path / "a.h5", workers=0, progress=False)
    policy = make_policy("random", load_spec("anymal_d"), 1)
    with pytest.raises(ValueError, match="name or a path"):
        collect(ENV_ID, policy, 2, tmp_path / "b.h5", workers=2, progress=False)
    assert not (tmp_path / "a.h5").exists() and not (tmp_path / "b.h5").exists()


def test_corrupt_file_gives_one_line_error(tmp_path):
    path = collect(ENV_ID, "random", 1, tmp_path / "d.h5", seed=0, max_steps=10, progress=False)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(DatasetError) as err:
        Dataset.load(path)
    assert str(path) in str(err.value) and "\n" not in str(err.value)


def test_finished_collection_keeps_a_whole_part_and_refuses_another_seeds_file(tmp_path):
    """What the scripts that collect fixed parts (make_base_mix, make_coverage_model) resume on."""
    part = tmp_path / "part.h5"
    assert not finished_collection(part, episodes=2, seed=7)  # nothing yet
    collect("AnymalD-MuJoCo-v0", "random", 2, part, seed=7, max_steps=10, progress=False)
    assert finished_collection(part, episodes=2, seed=7)
    assert not finished_collection(part, episodes=3, seed=7)  # fewer episodes than asked: collected again
    with pytest.raises(DatasetError, match=r"part\.h5 exists and is not part 3 \(seed 7, not 8\)"):
        finished_collection(part, episodes=2, seed=8, what="part 3")


def test_killed_collection_keeps_finished_episodes(tmp_path):
    out = tmp_path / "killed.h5"
    cmd = [
        sys.executable,
        "-m",
        "rwm_gym.cli",
        "collect",
        "--policy",
        "random",
        "--episodes",
        "1000",
        "--num-envs",
        "1",
        "--max-steps",
        "20",
        "--out",
        str(out),
    ]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.time() + 60
        while not list(tmp_path.glob("killed.h5.partial-*")) and time.time() < deadline:
            time.sleep(0.2)
        time.sleep(4.0)  # a few 20-step episodes get written (the writer holds the file lock meanwhile)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    assert not out.exists()  # --out only ever holds a whole file; the killed run's episodes are in the partial file
    (partial,) = tmp_path.glob("killed.h5.partial-*")
    ds = Dataset.load(partial)
    assert 1 <= ds.num_episodes < 1000 and not ds.info.complete
    assert np.all(ds.episode_lengths >= 2)


@pytest.mark.parametrize(
    "bad, message",
    [
        (["--episodes", "0"], "--episodes: must be >= 1, got 0"),
        (["--episodes", "-3"], "--episodes: must be >= 1, got -3"),
        (["--max-steps", "-5"], "--max-steps: must be >= 1, got -5"),
        (["--num-envs", "0"], "--num-envs: must be >= 1, got 0"),
        (["--env", "Nope-v0"], "unknown env 'Nope-v0'"),
        (["--policy", "nope"], "unknown policy 'nope'"),
        (["--physics", "{bad"], "--physics is not valid JSON"),
    ],
)
def test_bad_collect_options_give_one_line_errors_and_write_nothing(tmp_path, capsys, bad, message):
    out = tmp_path / "d.h5"
    assert main(["collect", "--out", str(out), "--episodes", "1", "--max-steps", "2", *bad]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert not list(tmp_path.iterdir())


def test_collect_refuses_an_existing_file_naming_the_overwrite_option(tmp_path, capsys):
    out = tmp_path / "d.h5"
    out.write_bytes(b"mine")
    assert main(["collect", "--out", str(out), "--episodes", "1", "--max-steps", "2"]) == 2
    assert "--overwrite" in capsys.readouterr().err and out.read_bytes() == b"mine"

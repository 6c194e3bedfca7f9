"""A resumable PPO run in physics: a killed process keeps its finished episodes and resumes to the same budget."""

import csv
import json
import os
import signal
import subprocess
import sys
import time

import numpy as np

from rwm_gym.data.dataset import Dataset

ARGS = [
    "--in",
    "physics",
    "--num-envs",
    "32",
    "--n-steps",
    "16",
    "--positive-reward-only",
    "--save-every",
    "1",
    "--snapshot-every",
    "2",
    "--record-every",
    "4",
    "--threads",
    "1",
    "--seed",
    "3",
]


def _ppo(run_dir, timesteps, **kw):
    cmd = [
        sys.executable,
        "-m",
        "rwm_gym.cli",
        "ppo",
        *ARGS,
        "--run-dir",
        str(run_dir),
        "--timesteps",
        str(timesteps),
        "--out",
        str(run_dir / "final.zip"),
    ]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, **kw)


def test_a_killed_run_keeps_its_episodes_and_resumes_to_the_budget(tmp_path):
    run = tmp_path / "run"
    first = _ppo(run, 10**7)
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline:  # wait for a resume point and a finished experience episode
        if (run / "state.json").is_file() and first.poll() is None:
            parts = list((run / "experience").glob("part_*.h5"))
            try:
                if parts and Dataset.load(parts[0]).num_episodes >= 1:
                    break
            except ValueError:
                pass
        time.sleep(0.5)
    first.send_signal(signal.SIGKILL)
    first.wait()
    killed = Dataset.load(run / "experience" / "part_000.h5")  # readable though the writer was killed
    assert killed.num_episodes >= 1 and not killed.info.complete
    iterations = killed["ppo_iteration"]
    assert iterations.dtype == np.int32 and (np.diff(iterations[: killed.episode_lengths[0] - 1]) >= 0).all()

    done_before = int(json.loads((run / "state.json").read_text())["timesteps"])
    budget = done_before + 2 * 32 * 16
    second = _ppo(run, budget)
    _, err = second.communicate(timeout=240)
    assert second.returncode == 0, err[-2000:]
    state = json.loads((run / "state.json").read_text())
    assert state["timesteps"] == budget and state["restarts"] == 1
    assert (run / "final.zip").is_file() and (run / "experience" / "part_001.h5").is_file()
    with (run / "log.csv").open() as f:
        steps = [int(row["timesteps"]) for row in csv.DictReader(f)]
    assert steps[-1] == budget and steps == sorted(steps)
    # the teacher-data example turns the run into world-model data: merged experience plus held-out episodes
    data = tmp_path / "teacher"
    example = subprocess.run(
        [
            sys.executable,
            "examples/make_teacher_data.py",
            "--run-dir",
            str(run),
            "--out",
            str(data),
            "--episodes",
            "1",
            "--num-envs",
            "1",
        ],
        capture_output=True,
        text=True,
        timeout=240,
        cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
    )
    assert example.returncode == 0, example.stderr[-2000:]
    manifest = json.loads((data / "manifest.json").read_text())
    merged = Dataset.load(data / "experience.h5")
    assert merged.num_episodes == manifest["experience"]["episodes"] >= killed.num_episodes
    assert set(manifest["stages"]) == {"early", "middle", "final"}
    assert all(Dataset.load(s["file"]).num_episodes == 1 for s in manifest["stages"].values())


def test_a_run_folder_refuses_other_settings(tmp_path):
    run = tmp_path / "run"
    first = _ppo(run, 32 * 16)
    assert first.wait(timeout=240) == 0
    cmd = [
        sys.executable,
        "-m",
        "rwm_gym.cli",
        "ppo",
        *ARGS,
        "--n-epochs",
        "3",
        "--run-dir",
        str(run),
        "--timesteps",
        "2048",
    ]
    result = subprocess.run(cmd, capture_output=True, text=True, timeout=240)
    assert result.returncode != 0 and "other PPO settings" in result.stderr


def test_ppo_curve_spaces_the_snapshots_it_scores(tmp_path):
    """`benchmarks/ppo_curve.py --every N`: the first snapshot at or past each multiple of N, in order; 0 keeps all."""
    from script_loader import BENCHMARKS, load_script

    spaced = load_script(BENCHMARKS / "ppo_curve.py", "ppo_curve").spaced
    snapshots = [tmp_path / f"step_{n}.zip" for n in (0, 491_520, 983_040, 3_932_160, 4_423_680, 8_355_840)]
    assert spaced(snapshots, 4_000_000) == [snapshots[i] for i in (0, 4, 5)]
    assert spaced(snapshots, 1_000_000) == [snapshots[i] for i in (0, 3, 4, 5)]
    assert spaced(snapshots, 0) == snapshots


def test_a_run_folder_takes_a_minutes_budget_counted_over_its_restarts(tmp_path):
    """--run-dir with --minutes alone: the run trains until its training time reaches the budget, and a rerun of
    the same command finds the budget spent instead of training again."""
    run = tmp_path / "run"
    cmd = [sys.executable, "-m", "rwm_gym.cli", "ppo", *ARGS, "--run-dir", str(run), "--minutes", "0.05"]
    cmd += ["--eval-seeds", "1", "--eval-steps", "10", "--out", str(run / "final.zip")]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    first = subprocess.run(cmd, capture_output=True, text=True, timeout=240, env=env)
    assert first.returncode == 0, first.stderr
    state = json.loads((run / "state.json").read_text())
    assert state["wall_s"] >= 3.0 and state["timesteps"] > 0
    again = subprocess.run([*cmd, "--overwrite"], capture_output=True, text=True, timeout=240, env=env)
    assert again.returncode == 0, again.stderr
    assert "already has its 0.05 min" in again.stdout
    assert json.loads((run / "state.json").read_text())["timesteps"] == state["timesteps"]

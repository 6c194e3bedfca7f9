"""Files a user can trust, second half: no command writes over a file it was not asked to replace, a killed collection
keeps its episodes through a rerun, every option and API argument is checked at the edge by the rule its dataclass
field carries, and every error is one line with the documented exit status (docs/reference/cli.md: 2 bad input,
1 a failure while running, 130 interrupted)."""

from __future__ import annotations

import errno
import math
import os
import re
import signal
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import gymnasium as gym
import h5py
import numpy as np
import pytest
import torch
from synthetic_dynamics import write_linear_dataset

from rwm_gym.cli import EXIT_BAD_INPUT, EXIT_INTERRUPTED, build_parser, main
from rwm_gym.data.dataset import Dataset, DatasetError
from rwm_gym.resources import assets_dir

REPO = Path(__file__).resolve().parents[1]


def status(argv: list[str]) -> int:
    """`rwm-gym ARGV`'s exit status, in this process (the parser and the commands' own messages exit by raising)."""
    try:
        return main(argv)
    except SystemExit as stop:
        return stop.code


def one_line(capsys, *words: str) -> str:
    """stderr, progress bars aside, is one line holding every one of `words`."""
    lines = [line for line in re.split(r"[\r\n]+", capsys.readouterr().err.strip()) if not re.search(r"\d+%\|", line)]
    assert len(lines) == 1 and "Traceback" not in lines[0], lines
    for word in words:
        assert word in lines[0], lines[0]
    return lines[0]


# Options and API arguments: one rule per field, shared by the parser and the dataclass -----------------------------

NO_GPU = not torch.cuda.is_available()


@pytest.mark.parametrize(
    "argv, flag",
    [
        (["train", "--data", "d.h5", "--out", "m.safetensors", "--minutes", "nan"], "--minutes"),
        (["train", "--data", "d.h5", "--out", "m.safetensors", "--minutes", "-1"], "--minutes"),
        (["train", "--data", "d.h5", "--out", "m.safetensors", "--minutes", "inf"], "--minutes"),
        (["train", "--data", "d.h5", "--out", "m.safetensors", "--cpu-minutes", "nan"], "--cpu-minutes"),
        (["train", "--data", "d.h5", "--out", "m.safetensors", "--grad-clip", "nan"], "--grad-clip"),
        (["ppo", "--learning-rate", "0"], "--learning-rate"),
        (["ppo", "--episode-steps", "0"], "--episode-steps"),
        (["ppo", "--episode-steps", "-5"], "--episode-steps"),
        (["ppo", "--n-steps", "0"], "--n-steps"),
        (["ppo", "--timesteps", "64.5"], "--timesteps"),
        (["ppo", "--device", "banana"], "--device"),
        (["evaluate", "--checkpoint", "m", "--data", "d.h5", "--noise", "nan"], "--noise"),
        (["score", "--policy", "zero", "--out", "s", "--seeds", "0"], "--seeds"),
        (["collect", "--out", "d.h5", "--episodes", "0"], "--episodes"),
        (["make-measured", "--out", "m.h5", "--noise-scale", "-1"], "--noise-scale"),
        (["mbpo", "--data", "d.h5", "--out", "r", "--history", "0"], "--history"),
        pytest.param(["ppo", "--device", "cuda"], "--device", marks=pytest.mark.skipif(not NO_GPU, reason="a GPU")),
        pytest.param(
            ["train", "--data", "d.h5", "--out", "m", "--device", "cuda"],
            "--device",
            marks=pytest.mark.skipif(not NO_GPU, reason="a GPU"),
        ),
    ],
)
def test_bad_option_values_are_one_line_naming_the_flag_exit_2(argv, flag, capsys, tmp_path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)  # were a value let through, its run writes here
    assert status(argv) == EXIT_BAD_INPUT
    one_line(capsys, flag)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("text, value", [("64", 64), ("64.0", 64), ("6.4e1", 64)])
def test_counts_take_integral_floats(text: str, value: int) -> None:
    args = build_parser("ppo").parse_args(["ppo", "--timesteps", text, "--n-steps", text])
    assert args.timesteps == value and args.n_steps == value and isinstance(args.n_steps, int)


def _ppo_config(**kw):
    from rwm_gym.rl.ppo import PPOConfig

    return PPOConfig(**kw)


def _imagination(**kw):
    from rwm_gym.imagination.options import ImaginationOptions

    return ImaginationOptions(**kw)


def _train_config(**kw):
    from rwm_gym.model.config import TrainConfig

    return TrainConfig(**kw)


def _eval_config(**kw):
    from rwm_gym.model.evaluate import EvalConfig

    return EvalConfig(**kw)


def _physics(**kw):
    from rwm_gym.physics.params import PhysicsParams

    return PhysicsParams.from_dict(kw)


@pytest.mark.parametrize(
    "make, kwargs, name",
    [
        (_ppo_config, {"learning_rate": 0.0}, "learning_rate"),
        (_ppo_config, {"n_steps": 0}, "n_steps"),
        (_ppo_config, {"gamma": math.nan}, "gamma"),
        (_imagination, {"episode_steps": 0}, "episode_steps"),
        (_imagination, {"episode_steps": -5}, "episode_steps"),
        (_imagination, {"history": 0}, "history"),
        (_train_config, {"grad_clip": math.nan}, "grad_clip"),
        (_train_config, {"minutes": math.inf}, "minutes"),
        (_train_config, {"minutes": -1.0}, "minutes"),
        (_eval_config, {"noise_levels": (0.1, math.nan)}, "noise_levels"),
        (_physics, {"payload_mass": -2e4}, "payload_mass"),
        (_physics, {"kp_scale": -0.5}, "kp_scale"),
        (_physics, {"joint_friction": [0.1] * 11 + [-0.1]}, "joint_friction"),
        (_physics, {"ground_friction": 1e300}, "ground_friction"),
    ],
)
def test_the_api_refuses_what_the_command_line_refuses(make, kwargs, name) -> None:
    with pytest.raises(ValueError, match=rf"{name}.* must be "):
        make(**kwargs)


@pytest.mark.parametrize(
    "physics, words",
    [
        ({"payload_com": [1.0, 2.0]}, "needs 3 numbers"),
        ({"payload_mass": [1.0, 2.0]}, "must be one number"),
        ({"kp_scale": [[1.0, 2.0]]}, "must be one number or one per joint"),
        ({"solver": 5}, "must be a dict of solver settings"),
    ],
)
def test_physics_values_of_the_wrong_shape_are_refused_naming_the_parameter(physics: dict, words: str) -> None:
    with pytest.raises(ValueError, match=rf"physics parameter '{next(iter(physics))}' {words}"):
        _physics(**physics)


def test_sensor_noise_is_a_finite_std() -> None:
    from rwm_gym.gap.measured import SensorNoise

    with pytest.raises(ValueError, match="sensor noise joint_vel must be >= 0"):
        SensorNoise(joint_vel=-1.0)


def test_physics_flag_with_an_unphysical_or_too_deep_value_is_one_line(tmp_path: Path, capsys) -> None:
    argv = ["collect", "--episodes", "1", "--max-steps", "2", "--out", str(tmp_path / "d.h5")]
    assert status([*argv, "--physics", '{"payload_mass": -3e4}']) == EXIT_BAD_INPUT
    one_line(capsys, "--physics", "payload_mass", ">= -10000")
    assert status([*argv, "--physics", "[" * 100_000 + "]" * 100_000]) == EXIT_BAD_INPUT
    one_line(capsys, "--physics", "nested too deeply")
    assert list(tmp_path.iterdir()) == []


def test_gym_make_refuses_what_the_cli_refuses() -> None:
    with pytest.raises(ValueError, match="history must be >= 1"):
        gym.make("RWM-AnymalD-v0", history=0)
    with pytest.raises(ValueError, match="episode_steps must be >= 1"):
        gym.make("RWM-AnymalD-v0", episode_steps=-5)


def test_a_reset_command_far_outside_the_specs_range_is_refused() -> None:
    env = gym.make("AnymalD-MuJoCo-v0")
    try:
        with pytest.raises(ValueError, match=r"vx = 100 is far outside the spec's range \[-1, 1\]"):
            env.reset(seed=0, options={"command": (100.0, 0.0, 0.0)})
        with pytest.raises(ValueError, match="finite"):
            env.reset(seed=0, options={"command": (math.nan, 0.0, 0.0)})
        _, info = env.reset(seed=0, options={"command": (1.5, 0.0, 0.0)})  # past the sampled range: a probe
        assert info["command"][0] == pytest.approx(1.5)
    finally:
        env.close()


def test_a_dataset_with_a_negative_dt_or_wrapping_episode_lengths_is_refused(tmp_path: Path) -> None:
    bad_dt = write_linear_dataset(tmp_path / "dt.h5", num_episodes=2)
    with h5py.File(bad_dt, "r+") as f:
        f.attrs["dt"] = -0.02
    with pytest.raises(DatasetError, match="attribute 'dt'"):
        Dataset.load(bad_dt)
    wrapped = write_linear_dataset(tmp_path / "wrap.h5", num_episodes=2)
    with h5py.File(wrapped, "r+") as f:
        rows = int(f["episode_lengths"][:].sum())
        big = np.array([2**62, 2**62, 2**62, 2**62 + rows], dtype=np.int64)
        assert int(big.sum()) == rows  # the int64 sum wraps to the row count
        f["episode_lengths"].resize((4,))
        f["episode_lengths"][:] = big
    with pytest.raises(DatasetError, match="episode_lengths"):
        Dataset.load(wrapped)


# Valid input that was refused ------------------------------------------------------------------------------------


def test_a_spec_can_be_drafted_from_the_shipped_anymal_mjcf(tmp_path: Path) -> None:
    out = tmp_path / "anymal.toml"
    argv = ["spec", "--mjcf", str(assets_dir() / "anymal_d" / "anymal_d.xml"), "--out", str(out)]
    assert status([*argv, "--episodes", "1", "--steps", "10"]) == 0
    text = out.with_suffix(".rwm.xml").read_text()
    assert text.count('name="LF_FOOT"') == 2  # its geom and its own site, kept
    assert text.count("<touch") == 9  # the model's own touch sensors, none added twice


def test_score_has_the_trust_option_its_error_names_and_shac_says_why_it_cannot(monkeypatch, capsys) -> None:
    assert build_parser("score").parse_args(["score", "--policy", "zero", "--out", "s", "--trust-entry-points"])
    import rwm_gym.model.checkpoint as checkpoint

    spec = SimpleNamespace(name="planted", extra={"imagination": {"reward": "planted:reward"}})
    monkeypatch.setattr(checkpoint, "read_meta", lambda path: SimpleNamespace(spec=spec))
    argv = ["shac", "--checkpoint", "m.safetensors", "--run-dir", "run", "--timesteps", "64"]
    assert status(argv) == EXIT_BAD_INPUT
    line = one_line(capsys, "planted:reward", "SHAC differentiates")
    assert "pass trust_entry_points" not in line


# No silent overwrite ---------------------------------------------------------------------------------------------


def test_ppo_refuses_to_replace_an_unrelated_report_png_or_clone_beside_its_zip(tmp_path: Path, capsys) -> None:
    out = tmp_path / "p.zip"
    argv = ["ppo", "--in", "physics", "--timesteps", "64", "--out", str(out)]
    for name in ("p.json", "p.png"):
        mine = tmp_path / name
        mine.write_text("a file of hours")
        assert status(argv) == EXIT_BAD_INPUT
        one_line(capsys, name, "--overwrite")
        assert mine.read_text() == "a file of hours" and not out.exists()
        mine.unlink()
    (tmp_path / "p_bc.zip").write_text("mine")
    assert status([*argv, "--bc-data", str(tmp_path / "d.h5")]) == EXIT_BAD_INPUT
    one_line(capsys, "p_bc.zip", "--overwrite")
    assert (tmp_path / "p_bc.zip").read_text() == "mine"


def test_shac_refuses_an_existing_out_and_a_foreign_run_folder_without_overwrite(tmp_path: Path, capsys) -> None:
    out, run = tmp_path / "policy.zip", tmp_path / "run"
    out.write_text("a policy of hours")
    argv = ["shac", "--run-dir", str(run), "--timesteps", "64", "--out", str(out)]
    assert status(argv) == EXIT_BAD_INPUT
    one_line(capsys, "--overwrite")
    assert out.read_text() == "a policy of hours"
    out.unlink()
    run.mkdir()
    (run / "notes.txt").write_text("someone else's notes")
    assert status(argv) == EXIT_BAD_INPUT
    one_line(capsys, "--run-dir", "--overwrite")
    assert sorted(p.name for p in run.iterdir()) == ["notes.txt"]


def test_a_run_killed_before_its_first_resume_point_is_continued_not_refused(tmp_path: Path, capsys) -> None:
    from rwm_gym.output_guard import OutputError, check_folder
    from rwm_gym.rl.training_run import TrainingRun

    run = TrainingRun(tmp_path / "run")
    run.snapshots.mkdir(parents=True)
    run.log_path.write_text("rollout,timesteps\n")  # what a run writes before its first resume point
    assert run.holds_only_a_run() and not run.resumable
    (run.folder / "notes.txt").write_text("mine")
    assert not run.holds_only_a_run()
    with pytest.raises(OutputError, match="--overwrite"):
        check_folder(run.folder, continues=run.holds_only_a_run(), flag="--run-dir")


def test_score_files_follow_overwrite_and_a_refused_score_leaves_no_folder(tmp_path: Path, capsys) -> None:
    folder = tmp_path / "s"
    folder.mkdir()
    (folder / "score.md").write_text("my notes")
    assert status(["score", "--policy", "zero", "--out", str(folder), "--steps", "2"]) == EXIT_BAD_INPUT
    one_line(capsys, "score.md", "--overwrite")
    assert (folder / "score.md").read_text() == "my notes"
    fresh = tmp_path / "new" / "deeper"
    argv = ["score", "--policy", "zero", "--out", str(fresh), "--reset-data", str(tmp_path / "h.h5"), "--steps", "2"]
    assert status(argv) == EXIT_BAD_INPUT  # refused after taking the output's lock
    one_line(capsys, "--reset-data")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s"]


def test_evaluate_and_mbpo_refuse_an_out_folder_holding_their_data(tmp_path: Path, capsys) -> None:
    data = write_linear_dataset(tmp_path / "d.h5", num_episodes=2)
    (tmp_path / "m.safetensors").write_bytes(b"")
    checkpoint = str(tmp_path / "m.safetensors")
    evaluate = ["evaluate", "--checkpoint", checkpoint, "--data", str(data), "--out", str(tmp_path)]
    assert status(evaluate) == EXIT_BAD_INPUT
    one_line(capsys, "holds the input")
    assert status(["mbpo", "--data", str(data), "--out", str(tmp_path)]) == EXIT_BAD_INPUT
    one_line(capsys, "holds the input")
    report = tmp_path / "eval"
    report.mkdir()
    (report / "error_vs_horizon.png").write_bytes(b"my figure")
    evaluate[-1] = str(report)
    assert status(evaluate) == EXIT_BAD_INPUT
    one_line(capsys, "error_vs_horizon.png", "--overwrite")
    assert (report / "error_vs_horizon.png").read_bytes() == b"my figure"


@pytest.mark.parametrize("command", ["mbpo", "gap"])
def test_a_folder_of_other_files_is_written_into_only_with_overwrite(tmp_path: Path, capsys, command) -> None:
    data = write_linear_dataset(tmp_path / "d.h5", num_episodes=2)
    folder = tmp_path / "out"
    folder.mkdir()
    (folder / "notes.txt").write_text("mine")
    if command == "mbpo":
        argv = ["mbpo", "--data", str(data), "--out", str(folder)]
    else:
        argv = ["gap", "--measured", str(data), "--out", str(folder), "--world-model", "none"]
    assert status(argv) == EXIT_BAD_INPUT
    one_line(capsys, "--out", "--overwrite")
    assert sorted(p.name for p in folder.iterdir()) == ["notes.txt"]


@pytest.mark.parametrize("command", ["mbpo", "gap"])
def test_a_refused_run_leaves_no_empty_out_folder(tmp_path: Path, capsys, command) -> None:
    data, out = tmp_path / "d.h5", tmp_path / "new" / "out"
    data.write_bytes(b"")  # not a dataset: refused once the run has made its folder
    flag = "--data" if command == "mbpo" else "--measured"
    extra = [] if command == "mbpo" else ["--world-model", "none"]
    assert status([command, flag, str(data), "--out", str(out), *extra]) == EXIT_BAD_INPUT
    one_line(capsys, "d.h5")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d.h5"]


def test_a_failed_policy_save_leaves_no_temp_zip(tmp_path: Path) -> None:
    from rwm_gym.rl.policy_file import save_policy

    class FullDisk:
        def save(self, path: str) -> None:
            Path(path).write_bytes(b"half a zip")
            raise OSError(errno.ENOSPC, "No space left on device")

    with pytest.raises(OSError, match="No space left"):
        save_policy(FullDisk(), tmp_path / "p.zip")
    assert list(tmp_path.iterdir()) == []


# A killed collection keeps its episodes through a rerun -------------------------------------------------------------

KILLED_AFTER = """
import os, signal, sys
from rwm_gym.data.dataset import DatasetWriter
append = DatasetWriter.append_episode
def append_then_die(self, episode):
    if self.num_episodes == int(sys.argv[1]):
        os.kill(os.getpid(), signal.SIGKILL)
    append(self, episode)
DatasetWriter.append_episode = append_then_die
from rwm_gym.cli import main
main(sys.argv[2:])
"""


def _collect(out: Path, seed: int = 0) -> list[str]:
    small = ["--episodes", "4", "--max-steps", "3", "--num-envs", "2"]
    return ["collect", "--policy", "random", *small, "--seed", str(seed), "--out", str(out)]


def _kill_collect(after: int, argv: list[str]) -> None:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    done = subprocess.run([sys.executable, "-c", KILLED_AFTER, str(after), *argv], env=env, capture_output=True)
    assert done.returncode == -signal.SIGKILL, done.stderr.decode()


def test_a_killed_collection_resumes_from_its_finished_episodes(tmp_path: Path, capsys) -> None:
    out = tmp_path / "d.h5"
    _kill_collect(2, _collect(out))
    (partial,) = tmp_path.glob("d.h5.partial-*")
    assert Dataset.load(partial).num_episodes == 2 and not out.exists()
    assert status(_collect(out)) == 0
    assert "resuming from the 2 finished episodes" in capsys.readouterr().err
    assert status(_collect(tmp_path / "whole.h5")) == 0
    resumed, whole = Dataset.load(out), Dataset.load(tmp_path / "whole.h5")
    assert resumed.info.complete and resumed.num_episodes == 4
    for name in whole.fields:  # episode k starts from seed + k: the same episodes as a run never killed
        np.testing.assert_array_equal(resumed[name], whole[name])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d.h5", "whole.h5"]


def test_a_killed_collection_with_other_settings_is_kept_and_named(tmp_path: Path, capsys) -> None:
    out = tmp_path / "d.h5"
    _kill_collect(2, _collect(out, seed=7))
    assert status(_collect(out)) == 0  # seed 0 now: the seed-7 episodes are not this collection's
    err = capsys.readouterr().err
    (kept,) = tmp_path.glob("d.interrupted-*.h5")
    assert str(kept) in err and "2 finished episodes" in err
    assert Dataset.load(kept).num_episodes == 2 and Dataset.load(kept).info.seed == 7
    assert Dataset.load(out).info.seed == 0 and Dataset.load(out).num_episodes == 4


# Exit statuses: 2 bad input, 1 a failure while running, 130 interrupted --------------------------------------------


def test_a_commands_own_refusal_exits_2_not_1_in_a_real_process(tmp_path: Path) -> None:
    done = subprocess.run(
        [sys.executable, "-m", "rwm_gym.cli", "score", "--policy", str(tmp_path / "no.zip"), "--out", str(tmp_path)],
        capture_output=True,
        text=True,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
    )
    assert done.returncode == EXIT_BAD_INPUT
    assert done.stderr.strip().splitlines() == [f"rwm-gym score: --policy {tmp_path / 'no.zip'}: no such file"]


def test_ctrl_c_exits_130(monkeypatch, capsys, tmp_path: Path) -> None:
    import rwm_gym.commands.export as export
    import rwm_gym.commands.train as train

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(export, "run", interrupted)  # a command that leaves Ctrl-C to the CLI
    assert status(["export", "--minari", "d.h5", "--out", "x"]) == EXIT_INTERRUPTED
    one_line(capsys, "rwm-gym export: interrupted")
    monkeypatch.setattr(train, "train", interrupted)  # one that says what it kept
    data = write_linear_dataset(tmp_path / "d.h5", num_episodes=4)
    argv = ["train", "--data", str(data), "--out", str(tmp_path / "m.safetensors"), "--iterations", "1"]
    assert status([*argv, "--quiet"]) == EXIT_INTERRUPTED
    one_line(capsys, "rwm-gym train: interrupted")


def test_a_full_disk_under_safetensors_is_one_line_naming_out(tmp_path: Path, capsys, monkeypatch) -> None:
    from safetensors import SafetensorError

    import rwm_gym.model.checkpoint as checkpoint

    def full(tensors, path, metadata=None):
        Path(path).write_bytes(b"half")
        raise SafetensorError('Error while serializing: IoError(Os { code: 28, message: "No space left on device" })')

    monkeypatch.setattr(checkpoint, "save_file", full)
    data = write_linear_dataset(tmp_path / "d.h5", num_episodes=4)
    out = tmp_path / "m.safetensors"
    small = ["--iterations", "1", "--history", "4", "--forecast", "2", "--batch-size", "2", "--hidden-size", "8"]
    argv = ["train", "--data", str(data), "--out", str(out), *small, "--num-layers", "1", "--head-hidden", "8"]
    assert status([*argv, "--val-fraction", "0.25", "--quiet"]) == EXIT_BAD_INPUT
    one_line(capsys, f"--out {out}", "No space left on device")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d.h5"]


def test_the_exit_statuses_are_documented() -> None:
    text = (REPO / "docs" / "reference" / "cli.md").read_text()
    for code, meaning in ((0, "success"), (1, "while running"), (2, "bad input"), (130, "interrupted")):
        assert re.search(rf"\|\s*`{code}`\s*\|[^|\n]*{meaning}", text), (code, meaning)

"""`--tensorboard DIR` of `rwm-gym ppo`, `mbpo` and `shac`: tiny runs write event files, read back here with
TensorBoard's own reader; the scalars the docs name are there, with finite values."""

from __future__ import annotations

import math

import pytest

from rwm_gym.cli import main as cli

pytest.importorskip("tensorboard", reason="the [tensorboard] extra (tensorboard) is not installed")

TINY_PPO = ["--num-envs", "8", "--n-steps", "16", "--net-arch", "32", "32", "--threads", "1"]


def scalars(folder) -> dict[str, list[tuple[int, float]]]:
    """Every scalar tag of the event files in `folder`: its (step, value) points."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(folder), size_guidance={"scalars": 0})
    events.Reload()
    return {tag: [(e.step, e.value) for e in events.Scalars(tag)] for tag in events.Tags()["scalars"]}


def assert_finite(logged: dict, tags) -> None:
    missing = [tag for tag in tags if tag not in logged]
    assert not missing, f"missing {missing}; logged: {sorted(logged)}"
    for tag in tags:
        assert logged[tag] and all(math.isfinite(value) for _, value in logged[tag]), (tag, logged[tag])


def test_ppo_in_imagination_logs_sb3s_scalars_and_the_imagined_envs(tmp_path):
    board = tmp_path / "tb"
    command = [
        "ppo",
        *TINY_PPO,
        "--timesteps",
        "384",  # three rollouts of 8 x 16
        "--episode-steps",
        "20",
        "--fall-tilt",
        "30",
        "--torque-halt",
        "0.95",
        "--report-uncertainty",
        "--no-eval",
        "--out",
        str(tmp_path / "policy.zip"),
        "--tensorboard",
        str(board),
    ]
    assert cli(command) == 0
    logged = scalars(board)
    halts = [f"termination/{flag}" for flag in ("model_diverged", "uncertainty_halt", "fall_tilt", "torque_halt")]
    assert_finite(
        logged,
        [
            "train/approx_kl",
            "train/value_loss",
            "rollout/ep_len_mean",
            "reward/track_lin_vel_xy",
            "episode/length",
            "episode/count",
            *halts,
            "termination/any",
            "uncertainty/mean",
            "uncertainty/max",
        ],
    )
    assert [step for step, _ in logged["reward/track_lin_vel_xy"]] == [128, 256, 384]  # one point per rollout
    assert all(0.0 <= value <= 1.0 for tag in halts for _, value in logged[tag])


def test_mbpo_logs_ppos_scalars_and_each_iterations_physics_score_and_model_error(tmp_path):
    from rwm_gym.data.collect import collect
    from rwm_gym.model.config import TrainConfig
    from rwm_gym.model.factory import model_config_for
    from rwm_gym.model.train import train
    from rwm_gym.spec import load_spec

    data = collect("AnymalD-MuJoCo-v0", "random", 4, tmp_path / "data.h5", num_envs=4, max_steps=60, progress=False)
    config = model_config_for("rwm", load_spec("anymal_d"), hidden_size=32, num_layers=1, head_hidden=32)
    train_config = TrainConfig(history=8, forecast=4, iterations=10, batch_size=16, val_every=10, val_fraction=0.25)
    checkpoint = train(data, config, train_config, tmp_path / "tiny.safetensors", progress=False).path
    board = tmp_path / "tb"
    command = ["mbpo", "--data", str(data), "--out", str(tmp_path / "run"), "--checkpoint", str(checkpoint)]
    command += ["--iterations", "1", "--ppo-timesteps", "128", "--num-envs", "8", "--imagined-episode-steps", "20"]
    command += ["--collect-episodes", "2", "--collect-steps", "48", "--model-iterations", "2", "--eval-seeds", "1"]
    command += ["--eval-steps", "10", "--threads", "1"]
    assert cli([*command, "--tensorboard", str(board)]) == 0
    logged = scalars(board)
    fields = ("tracking", "falls", "physics_return", "lin_vel_error", "physics_samples", "imagined_steps")
    assert_finite(logged, [f"mbpo/{name}" for name in fields])
    assert [step for step, _ in logged["mbpo/tracking"]] == [0, 1]  # the starting policy, then iteration 1
    errors = [tag for tag in logged if tag.startswith("mbpo/model_error_fresh/")]
    assert errors and [step for step, _ in logged[errors[0]]] == [1]
    assert_finite(logged, [*errors, "mbpo/imagined_step_reward", "train/approx_kl", "reward/track_lin_vel_xy"])


def test_train_logs_the_world_models_losses(tmp_path):
    from rwm_gym.data.collect import collect

    data = collect("AnymalD-MuJoCo-v0", "random", 2, tmp_path / "data.h5", num_envs=2, max_steps=40, progress=False)
    board = tmp_path / "tb"
    command = ["train", "--data", str(data), "--out", str(tmp_path / "m.safetensors"), "--hidden-size", "16"]
    command += ["--history", "8", "--forecast", "4", "--iterations", "4", "--batch-size", "8", "--val-every", "2"]
    assert cli([*command, "--quiet", "--tensorboard", str(board)]) == 0
    logged = scalars(board)
    assert_finite(logged, ["train_loss", "val_error", "lr", "wall_s"])
    assert [step for step, _ in logged["train_loss"]] == [2, 4]


def test_shac_logs_its_update_stats(tmp_path):
    from dataclasses import fields

    from rwm_gym.rl.shac import UpdateStats

    board = tmp_path / "tb"
    command = ["shac", "--num-envs", "8", "--horizon", "4", "--critic-iterations", "1", "--episode-steps", "20"]
    command += ["--fall-tilt", "30", "--run-dir", str(tmp_path / "run"), "--threads", "1", "--timesteps", "96"]
    assert cli([*command, "--out", str(tmp_path / "policy.zip"), "--tensorboard", str(board)]) == 0
    logged = scalars(board)
    tags = [f"shac/{f.name}" for f in fields(UpdateStats) if f.name != "timesteps"]
    assert_finite(logged, tags)
    assert [step for step, _ in logged["shac/imagined_return"]] == [32, 64, 96]  # one point per update


def test_a_resumed_ppo_run_continues_its_curves(tmp_path):
    board, run = tmp_path / "tb", tmp_path / "run"
    command = ["ppo", *TINY_PPO, "--episode-steps", "20", "--no-eval", "--run-dir", str(run), "--save-every", "1"]
    command += ["--out", str(tmp_path / "policy.zip"), "--tensorboard", str(board)]
    assert cli([*command, "--timesteps", "256"]) == 0
    assert cli([*command, "--timesteps", "384"]) == 0  # the same run, resumed to a larger budget
    assert [step for step, _ in scalars(board)["reward/track_lin_vel_xy"]] == [128, 256, 384]


def test_tensorboard_leaves_the_training_unchanged(tmp_path):
    """The KL rule reads the previous update's KL from SB3's logger: a logger that outlives `learn` must not change
    what it reads (two `learn` calls with a critic warm-up between, with and without TensorBoard)."""
    import torch

    def run(board):
        out = tmp_path / f"policy_{board is not None}.zip"
        extra = ["--tensorboard", str(board)] if board else []
        common = ["--timesteps", "256", "--critic-warmup-steps", "128", "--episode-steps", "20", "--no-eval"]
        assert cli(["ppo", *TINY_PPO, *common, "--out", str(out), *extra]) == 0
        from rwm_gym.policy_zip import load_policy

        return load_policy(out).policy.state_dict()

    plain, logged = run(None), run(tmp_path / "tb")
    assert all(torch.equal(plain[k], logged[k]) for k in plain)


def test_a_missing_tensorboard_is_one_line_naming_the_extra(tmp_path, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "tensorboard", None)  # import tensorboard raises ImportError
    for command in (
        ["ppo", "--timesteps", "128"],
        ["shac", "--timesteps", "128", "--run-dir", str(tmp_path / "run")],
        ["mbpo", "--data", "d.h5", "--out", str(tmp_path / "mbpo")],
        ["train", "--data", "d.h5", "--out", str(tmp_path / "m.safetensors")],
    ):
        with pytest.raises(SystemExit, match=r"--tensorboard needs the tensorboard package: pip install 'rwm-gym\["):
            cli([*command, "--tensorboard", str(tmp_path / "tb")])

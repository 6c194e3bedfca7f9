"""`rwm-gym mbpo --recipe`: one command collects the recipe's starting data, trains its starting model, runs the loop
with the recipe's settings (a flag given a non-default value wins), counts every physics row, writes policies that
`rwm-gym score` reads, and continues where it stopped."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import pytest
import torch

from rwm_gym.cli import build_parser
from rwm_gym.cli import main as cli
from rwm_gym.commands.mbpo import config_from, load_recipe
from rwm_gym.data.dataset import Dataset
from rwm_gym.model.checkpoint import read_meta
from rwm_gym.resources import assets_dir

TINY_RECIPE = {
    "start_data": {"policy": "random", "episodes": 4, "max_steps": 40, "seed": 5, "num_envs": 4},
    "start_model": {
        "model": {"hidden_size": 32, "num_layers": 1, "head_hidden": 32},
        "train": {"history": 8, "forecast": 4, "iterations": 6, "batch_size": 16, "val_every": 6, "val_fraction": 0.25},
    },
    "mbpo": {
        "iterations": 1,
        "ppo_timesteps": 128,
        "num_envs": 8,
        "positive_reward_only": True,
        "log_std_init": -1.0,
        "collect_episodes": 2,
        "collect_steps": 60,
        "model_iterations": 3,
        "model_finetune": True,
        "model_lr": 3e-4,
        "eval_seeds": 1,
        "eval_steps": 10,
        "imagination": {"episode_steps": 20, "fall_tilt": 30.0, "command_from_history": 0.5},
    },
}


def _args(argv: list[str]) -> argparse.Namespace:
    return build_parser("mbpo").parse_args(["mbpo", *argv])


def test_the_shipped_recipe_is_the_fast_history_recipe_from_random_data():
    recipe = load_recipe("anymal_d_mbpo_history")
    config = config_from(_args(["--out", "x", "--recipe", "anymal_d_mbpo_history"]), recipe)
    assert config.num_envs == 1024 and config.model_finetune and recipe["start_data"]["policy"] == "random"
    assert config.imagination.command_from_history == 0.5 and config.imagination.matmul_precision == "bfloat16"
    assert config.imagination.fall_tilt == 30 and config.imagination.episode_steps == 50
    flags = ["--out", "x", "--num-envs", "512", "--fall-tilt", "20", "--no-model-finetune"]
    overridden = config_from(_args(flags), recipe)
    assert overridden.num_envs == 512 and overridden.imagination.fall_tilt == 20 and not overridden.model_finetune
    assert overridden.ppo_timesteps == config.ppo_timesteps  # the rest stays the recipe's
    with pytest.raises(ValueError, match="no such recipe"):
        load_recipe("no_such_recipe")


@pytest.mark.parametrize("name", sorted(p.stem for p in (assets_dir() / "recipes").glob("*.json")))
def test_every_shipped_recipe_builds_its_loop_and_starting_model(name):
    """Each shipped recipe reads into an `MBPOConfig` (its fields known, its values in range), says what it is, how
    its loop ran and the command that runs it, and starts from random-action data."""
    recipe = load_recipe(name)
    config = config_from(_args(["--out", "x", "--recipe", name]), recipe)
    assert config.iterations > 0 and config.imagination.matmul_precision == "bfloat16"
    assert recipe["what"] and recipe["status"] and f"--recipe {name}" in recipe["command"]
    assert recipe["start_data"]["policy"] == "random" and recipe["start_model"]["train"]["iterations"] > 0


def test_one_command_runs_the_recipe_from_nothing_counts_every_row_and_resumes(tmp_path):
    recipe_file = tmp_path / "tiny.json"
    recipe_file.write_text(json.dumps(TINY_RECIPE))
    out = tmp_path / "run"
    command = ["mbpo", "--recipe", str(recipe_file), "--out", str(out), "--threads", "1"]
    assert cli(command) == 0
    data = out / "data_0.h5"
    start_rows = Dataset.load(data).num_steps
    assert Dataset.load(data).num_episodes == 4 and Dataset.load(data).info.seed == 5
    report = json.loads((out / "mbpo.json").read_text())
    assert report["start_train"]["iterations"] == 6 and report["config"]["num_envs"] == 8
    assert read_meta(out / "model_0.safetensors").model_config.hidden_size == 32
    log = report["log"]
    assert log[0]["physics_samples"] == start_rows  # the model was trained on the same data: counted once
    assert log[1]["physics_samples"] == start_rows + Dataset.load(out / "data_1.h5").num_steps
    assert read_meta(out / "model_1.safetensors").provenance["physics_rows"] == log[1]["physics_samples"]
    stamp = data.stat().st_mtime_ns
    assert cli([*command, "--iterations", "2"]) == 0  # continues: one more iteration, the data kept
    assert data.stat().st_mtime_ns == stamp
    assert [row["iteration"] for row in json.loads((out / "mbpo.json").read_text())["log"]] == [0, 1, 2]
    with pytest.raises(SystemExit, match="other settings"):
        cli([*command, "--iterations", "2", "--model-lr", "1e-3"])
    score = ["score", "--policy", str(out / "policy_2.zip"), "--out", str(tmp_path / "score"), "--seeds", "1"]
    assert cli([*score, "--steps", "10"]) == 0


def test_without_data_or_a_recipe_that_collects_it_is_one_line(tmp_path):
    with pytest.raises(SystemExit, match="--data is required") as refused:
        cli(["mbpo", "--out", str(tmp_path / "run")])
    assert refused.value.code == 2
    assert not Path(tmp_path / "run").exists()


def test_a_run_killed_while_training_a_model_continues_that_model_from_its_checkpoint(tmp_path, monkeypatch):
    import rwm_gym.model.train as training
    from rwm_gym.model.checkpoint import load_checkpoint

    recipe_file = tmp_path / "tiny.json"
    recipe_file.write_text(json.dumps({**TINY_RECIPE, "mbpo": {**TINY_RECIPE["mbpo"], "iterations": 0}}))
    command = ["mbpo", "--recipe", str(recipe_file), "--threads", "1"]
    assert cli([*command, "--out", str(tmp_path / "whole")]) == 0

    train, trained, stop_at = training.train, [], [3]

    def killed_at_iteration_3(*args, **kwargs):
        def callback(iteration, stats):
            trained.append(iteration)
            if iteration in stop_at:
                raise KeyboardInterrupt

        return train(*args, **kwargs, callback=callback)

    monkeypatch.setattr(training, "train", killed_at_iteration_3)
    killed = tmp_path / "killed"
    assert cli([*command, "--out", str(killed)]) == 130  # interrupted
    assert read_meta(killed / "model_0.safetensors").stats["iterations"] == 3
    trained.clear()
    stop_at.clear()
    assert cli([*command, "--out", str(killed)]) == 0
    assert trained == [4, 5, 6]  # the model's three iterations left, not all six again
    whole, resumed = (load_checkpoint(f / "model_0.safetensors")[0].state_dict() for f in (tmp_path / "whole", killed))
    assert all(torch.equal(whole[name], resumed[name]) for name in whole)


def test_a_loop_with_symmetry_trains_every_policy_on_mirrored_samples(tmp_path, monkeypatch):
    import rwm_gym.rl.mirror_buffer as mirror_buffer

    use_mirrored_buffer, mirrored = mirror_buffer.use_mirrored_buffer, []

    def recorded(model, spec):
        mirrored.append(spec.name)
        return use_mirrored_buffer(model, spec)

    monkeypatch.setattr(mirror_buffer, "use_mirrored_buffer", recorded)
    recipe_file = tmp_path / "tiny.json"
    recipe_file.write_text(json.dumps(TINY_RECIPE))
    out = tmp_path / "run"
    assert cli(["mbpo", "--recipe", str(recipe_file), "--out", str(out), "--threads", "1", "--symmetry"]) == 0
    assert json.loads((out / "mbpo.json").read_text())["config"]["symmetry"] is True
    assert mirrored == ["AnymalD", "AnymalD"]  # the fresh policy of iteration 0 and iteration 1's, loaded again

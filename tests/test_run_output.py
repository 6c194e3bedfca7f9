"""What a run shows its user: progress bars that end at their totals (a step budget counted in the steps the run
really takes, a time budget in seconds), figures printed to a sensible precision, the physics samples behind a
policy (or why they are unknown), and `--help` texts that name every default."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from synthetic_dynamics import SPEC, write_linear_dataset

from rwm_gym.cli import COMMANDS, build_parser, main
from rwm_gym.data.dataset import Dataset
from rwm_gym.model import model_config_for
from rwm_gym.model.checkpoint import dataset_rows, load_checkpoint, save_checkpoint
from rwm_gym.model.config import TrainConfig
from rwm_gym.model.train import train
from rwm_gym.rl.ppo import PPOConfig, learn, make_env, make_ppo

TINY_PPO = PPOConfig(num_envs=8, n_steps=16, net_arch=(16,))  # one rollout: 128 steps
TINY_MODEL = dict(hidden_size=8, head_hidden=8)


def last_count(err: str) -> tuple[str, str]:
    """The last 'n/total' a tqdm bar wrote."""
    counts = re.findall(r"(\d+(?:\.\d+)?k?)/(\d+(?:\.\d+)?k?)", err)
    assert counts, err
    return counts[-1]


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    return write_linear_dataset(tmp_path_factory.mktemp("data") / "linear.h5")


def test_ppo_bar_counts_the_whole_rollouts_sb3_runs(capsys):
    model = make_ppo(make_env("physics", TINY_PPO.num_envs, seed=0), TINY_PPO, seed=0)
    stats = learn(model, timesteps=200, progress=True)  # SB3 stops only between rollouts: 2 x 128
    assert stats.timesteps == 256
    assert last_count(capsys.readouterr().err) == ("256", "256")  # was 256/200


def test_ppo_bar_with_only_minutes_counts_seconds_of_the_budget(capsys):
    model = make_ppo(make_env("physics", TINY_PPO.num_envs, seed=0), TINY_PPO, seed=0)
    learn(model, minutes=0.5 / 60, progress=True)
    err = capsys.readouterr().err
    assert "s of the budget" in err and last_count(err)[1] == "1"  # was a bare step count with no total
    assert "steps=" in err


def test_train_bar_with_only_minutes_counts_seconds_of_the_budget(data, capsys):
    config = TrainConfig(
        history=4, forecast=2, batch_size=4, iterations=0, minutes=0.5 / 60, val_every=5, val_fraction=0.25
    )
    ticks = iter(range(10**6))
    clock = lambda: 0.05 * next(ticks)  # noqa: E731  (each reading 50 ms later: the same run on any machine)
    result = train(data, model_config_for("mlp", SPEC, **TINY_MODEL), config, progress=True, clock=clock)
    err = capsys.readouterr().err
    assert result.stats["iterations"] > 0
    assert "s of the budget" in err and last_count(err) == ("1", "1")  # was "12it" with no total
    assert f"its={result.stats['iterations']:,}" in err


def test_physics_samples_come_from_provenance_or_say_why_unknown(data, tmp_path):
    out = tmp_path / "m.safetensors"
    config = TrainConfig(history=4, forecast=2, batch_size=4, iterations=2, val_every=2, val_fraction=0.25)
    train(data, model_config_for("mlp", SPEC, **TINY_MODEL), config, out, progress=False)
    rows = dataset_rows(out)
    assert rows[0] == Dataset.load(data).num_steps and "provenance" in rows[1]
    model, meta = load_checkpoint(out)
    older = tmp_path / "older.safetensors"  # a checkpoint from before dataset_steps: the file is read instead
    save_checkpoint(
        older, model, meta.spec, provenance={k: v for k, v in meta.provenance.items() if k != "dataset_steps"}
    )
    assert dataset_rows(older) == (rows[0], f"rows of {data}, the world model's dataset")
    elsewhere = tmp_path / "elsewhere.safetensors"
    save_checkpoint(elsewhere, model, meta.spec, provenance={"dataset": "runs/gone.h5", "sha256": "0" * 64})
    count, why = dataset_rows(elsewhere)
    assert count is None and "runs/gone.h5" in why and why.startswith("unknown")
    nameless = tmp_path / "nameless.safetensors"
    save_checkpoint(nameless, model, meta.spec)
    assert dataset_rows(nameless) == (None, f"unknown: {nameless} names no dataset in its provenance")


OPTIONAL_INPUTS = {
    "--out",
    "--init",
    "--tensorboard",
    "--sim-kwargs",
    "--physics",
    "--xml-file",
    "--from-dmc",
    "--mjcf",
    "--checkpoint",
    "--bc-data",
    "--run-dir",
}
"""Options whose absence is its own meaning (no such input): their help need not name a default."""


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_every_subcommand_help_names_its_defaults(command):
    parser = build_parser(command)
    sub = parser._subparsers._group_actions[0].choices[command]
    if sub.get_default("_missing"):
        pytest.skip(f"{command} is not available in this build")
    for action in sub._actions:
        flag = max(action.option_strings, key=len, default="")
        if not flag or (action.nargs == 0 and action.default in (False, None)) or flag == "--help":
            continue  # positional arguments, switches and --help
        if action.required or (flag in OPTIONAL_INPUTS and action.default is None):
            continue
        text = sub.formatter_class(prog="x")._format_action(action)  # the option's lines as --help prints them
        assert "default" in text, f"rwm-gym {command} {flag}: help names no default ({text!r})"


def test_help_is_printed_with_the_defaults(capsys):
    with pytest.raises(SystemExit) as done:
        main(["ppo", "--help"])
    assert done.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "--seed SEED (default 0)" in text and "8 when --timesteps is not given either" in text

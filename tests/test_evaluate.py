"""The long-horizon metric: exact on a hand-checkable case, held-out episodes, robustness rows, CLI outputs."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from synthetic_dynamics import SPEC, info_for, write_linear_dataset

from rwm_gym.cli import main
from rwm_gym.data.dataset import Dataset, write_dataset
from rwm_gym.model import build_model, model_config_for
from rwm_gym.model.checkpoint import read_meta, save_checkpoint
from rwm_gym.model.config import TrainConfig
from rwm_gym.model.evaluate import EvalConfig, evaluate, evaluate_checkpoint
from rwm_gym.model.normalization import Normalizer
from rwm_gym.model.train import train


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    return write_linear_dataset(tmp_path_factory.mktemp("data") / "linear.h5", num_episodes=6)


def test_no_change_error_matches_a_hand_computation(data: Path) -> None:
    ds = Dataset.load(data)
    norm = Normalizer.from_spec(SPEC)
    config = EvalConfig(history=10, horizons=(5,), max_horizon=5, noise_levels=(), max_windows=10_000)
    result = evaluate(build_model(model_config_for("no_change", SPEC)), ds, norm, SPEC, config, progress=False)
    assert result["horizons"] == [5] and result["longest"] == 5
    errors, mean_errors = [], []
    data_mean = norm.normalize_state(ds["state"].astype(np.float64)).mean(0)
    for e in range(ds.num_episodes):
        z = norm.normalize_state(ds.episode(e)["state"].astype(np.float64))
        for start in range(len(z) - 15 + 1):
            last, future = z[start + 9], z[start + 10 : start + 15]  # prediction = the last history row, 5 steps on
            errors.append((np.abs(future - last).sum(-1) / np.abs(future).sum(-1)).mean())
            mean_errors.append((np.abs(future - data_mean).sum(-1) / np.abs(future).sum(-1)).mean())
    assert result["windows"]["5"] == len(errors)
    assert result["error"]["5"] == pytest.approx(np.mean(errors), rel=1e-4)
    # the floors come without a model: the no-change row is this model's error, the mean row a constant's
    assert result["floors"]["no change"]["5"] == pytest.approx(np.mean(errors), rel=1e-4)
    assert result["floors"]["predict the mean"]["5"] == pytest.approx(np.mean(mean_errors), rel=1e-4)
    assert result["max_abs"]["5"]["prediction"] <= result["max_abs"]["5"]["data"] + 1e-6  # no change stays in range
    assert result["contact_accuracy"]["5"] == pytest.approx(float((~ds["contact"]).mean()), abs=0.05)


def test_checkpoint_evaluation_uses_held_out_episodes_and_reports_noise(data: Path, tmp_path: Path) -> None:
    out = tmp_path / "rwm.safetensors"
    run = TrainConfig(history=8, forecast=4, batch_size=8, iterations=5, val_fraction=0.34)
    train(data, model_config_for("rwm", SPEC, hidden_size=16, num_layers=1, head_hidden=16), run, out, progress=False)
    config = EvalConfig(history=8, horizons=(4, 16, 1000), max_horizon=20, noise_levels=(0.2, 0.8), max_windows=64)
    result = evaluate_checkpoint(out, data, config, progress=False)
    assert result["episode_set"] == "validation episodes" and result["episodes"] == 2
    assert result["horizons"] == [4, 16, 20] and len(result["curve"]) == 20
    assert set(result["group_error"]["4"]) == set(SPEC.state_slices)
    assert set(result["noise"]) == {"0.2", "0.8"} and set(result["noise"]["0.8"]) == {"4", "16", "20"}
    everything = evaluate_checkpoint(out, data, config, all_episodes=True, progress=False)
    assert everything["episodes"] == 6


def test_episodes_that_repeat_training_episodes_are_left_out(data: Path, tmp_path: Path) -> None:
    """A held-out file collected with a training file's policy and seed repeats its episodes: those are not held out."""
    out = tmp_path / "rwm.safetensors"
    run = TrainConfig(history=8, forecast=4, batch_size=8, iterations=1, val_fraction=0.34)
    train(data, model_config_for("rwm", SPEC, hidden_size=16, num_layers=1, head_hidden=16), run, out, progress=False)
    provenance = read_meta(out).provenance
    trained, fresh = (
        Dataset.load(data),
        Dataset.load(write_linear_dataset(tmp_path / "fresh.h5", num_episodes=3, seed=7)),
    )
    mixed = tmp_path / "mixed.h5"  # one training episode, one validation episode, three new ones
    write_dataset(
        mixed,
        info_for(SPEC),
        [
            trained.episode(provenance["train_episodes"][0]),
            trained.episode(provenance["val_episodes"][0]),
            *(fresh.episode(i) for i in range(3)),
        ],
    )
    config = EvalConfig(history=8, horizons=(4,), max_horizon=4, noise_levels=(), max_windows=64)
    result = evaluate_checkpoint(out, mixed, config, progress=False)
    assert result["episodes"] == 4 and "left out" in result["episode_set"]
    assert evaluate_checkpoint(out, mixed, config, all_episodes=True, progress=False)["episodes"] == 5
    also = evaluate_checkpoint(out, mixed, config, progress=False, training_data=[tmp_path / "fresh.h5"])
    assert also["episodes"] == 1  # only the validation episode is new to both files
    with pytest.raises(ValueError, match="repeats a training episode"):
        evaluate_checkpoint(out, tmp_path / "fresh.h5", config, progress=False, training_data=[tmp_path / "fresh.h5"])


def test_cli_prints_table_and_writes_json_and_plot(data: Path, tmp_path: Path, capsys) -> None:
    ckpt = save_checkpoint(tmp_path / "still.safetensors", build_model(model_config_for("no_change", SPEC)), SPEC)
    code = main(
        [
            "evaluate",
            "--checkpoint",
            str(ckpt),
            "--data",
            str(data),
            "--out",
            str(tmp_path / "ev"),
            "--history",
            "8",
            "--horizons",
            "4",
            "--noise",
            "0.1",
            "--quiet",
        ]
    )
    assert code == 0
    printed = capsys.readouterr().out
    assert "no_change" in printed and "joint_torque" in printed and "noise std" in printed
    assert "no change | predict the mean" in printed
    saved = json.loads((tmp_path / "ev" / "evaluation.json").read_text())
    assert saved["model"] == "no_change" and saved["error"]["4"] > 0
    assert (tmp_path / "ev" / "error_vs_horizon.png").read_bytes()[:4] == b"\x89PNG"
    assert main(["evaluate", "--checkpoint", str(tmp_path / "nope.safetensors"), "--data", str(data)]) == 2
    other = write_linear_dataset(tmp_path / "other.h5", num_episodes=3, seed=7)  # several sources, one table each
    assert (
        main(
            [
                "evaluate",
                "--checkpoint",
                str(ckpt),
                "--data",
                str(data),
                str(other),
                "--out",
                str(tmp_path / "two"),
                "--history",
                "8",
                "--horizons",
                "4",
                "--noise",
                "--quiet",
            ]
        )
        == 0
    )
    assert capsys.readouterr().out.count("no_change on") == 2
    saved = json.loads((tmp_path / "two" / "evaluation.json").read_text())
    assert set(saved["sources"]) == {"linear", "other"}
    assert all(len(r["running_mean"]) == r["longest"] for r in saved["sources"].values())


def test_the_plotted_line_meets_every_table_value(data: Path, tmp_path: Path) -> None:
    """Each horizon has its own windows: the plot's running mean must be over those, ending at the table's value."""
    from rwm_gym.model.evaluate import plot_running_mean

    ds = Dataset.load(data)
    config = EvalConfig(history=10, horizons=(3, 8), max_horizon=20, noise_levels=(), max_windows=7)
    result = evaluate(
        build_model(model_config_for("no_change", SPEC)), ds, Normalizer.from_spec(SPEC), SPEC, config, progress=False
    )
    by_horizon = result["running_mean_by_horizon"]
    assert sorted(by_horizon, key=int) == [str(n) for n in result["horizons"]]
    for key, error in result["error"].items():
        assert len(by_horizon[key]) == int(key) and by_horizon[key][-1] == pytest.approx(error, rel=1e-6)
    longest = str(result["longest"])  # the older single curve, over the longest horizon's windows, misses them
    assert any(
        abs(result["running_mean"][int(k) - 1] - result["error"][k]) > 1e-6 for k in result["error"] if k != longest
    )
    plot_running_mean({"no change": result}, tmp_path / "plot.png")
    assert (tmp_path / "plot.png").stat().st_size > 0


def test_the_defaults_skip_the_slow_extras(data: Path) -> None:
    """By default evaluate reports the asked horizons only (no longer cap, no robustness passes); each extra is an
    option: `max_horizon` adds the longest horizon the episodes allow, `noise_levels` a pass per level."""
    ds = Dataset.load(data)
    model, norm = build_model(model_config_for("no_change", SPEC)), Normalizer.from_spec(SPEC)
    assert EvalConfig().noise_levels == () and EvalConfig().max_horizon is None and EvalConfig().max_windows == 256
    quick = evaluate(model, ds, norm, SPEC, EvalConfig(history=8, horizons=(4, 8)), progress=False)
    assert quick["horizons"] == [4, 8] and quick["noise"] == {}
    more = EvalConfig(history=8, horizons=(4, 8), max_horizon=20, noise_levels=(0.1,))
    full = evaluate(model, ds, norm, SPEC, more, progress=False)
    assert full["horizons"] == [4, 8, 20] and set(full["noise"]["0.1"]) == {"4", "8", "20"}
    assert full["error"]["8"] == quick["error"]["8"]  # the same windows: an extra adds rows, it changes none

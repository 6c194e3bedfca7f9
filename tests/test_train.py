"""The trainer: windows stay inside episodes, validation is held out by episode, runs are deterministic and resume to
the same weights, every kind trains, and a tiny RWM learns a linear system better than "no change"."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import torch
from synthetic_dynamics import SPEC, write_linear_dataset

from rwm_gym.cli import main
from rwm_gym.data.dataset import Dataset
from rwm_gym.model import MODEL_KINDS, build_model, model_config_for
from rwm_gym.model.checkpoint import CheckpointError, read_meta
from rwm_gym.model.config import TrainConfig
from rwm_gym.model.heads import soft_bound
from rwm_gym.model.normalization import Normalizer
from rwm_gym.model.train import learning_rate_factor, train
from rwm_gym.model.windows import WindowData

TINY = dict(hidden_size=16, num_layers=1, head_hidden=16, transformer_dim=16, transformer_context=6, rssm_latent=4)
FAST = TrainConfig(
    history=6, forecast=3, batch_size=8, iterations=4, val_every=2, checkpoint_every=2, val_fraction=0.25
)


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    return write_linear_dataset(tmp_path_factory.mktemp("data") / "linear.h5")


def weights(model) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone() for k, v in model.state_dict().items()}


def test_windows_never_cross_an_episode_boundary(data: Path) -> None:
    ds = Dataset.load(data)
    windows = WindowData(ds, Normalizer.from_spec(SPEC))
    rows = 20
    starts = windows.window_starts(range(ds.num_episodes), rows).numpy()
    assert len(starts) == sum(max(0, n - rows + 1) for n in ds.episode_lengths)
    episode = np.searchsorted(ds.episode_starts, starts, side="right") - 1
    ends = ds.episode_starts[episode] + ds.episode_lengths[episode]
    assert (starts + rows <= ends).all()  # the last row of a window is at most the episode's last row
    assert (starts + rows == ends).any()  # ... and windows do reach it (terminal rows are targets)
    batch = windows.gather(torch.as_tensor(starts), rows)
    terminal_inside = batch.terminated[:, :-1].sum()
    assert terminal_inside == 0  # a terminal row is only ever a window's last row
    only_long = windows.window_starts([0], int(ds.episode_lengths[0]) + 1)
    assert len(only_long) == 0  # an episode shorter than a window contributes none


def test_validation_is_held_out_by_episode(data: Path, tmp_path: Path) -> None:
    out = tmp_path / "m.safetensors"
    train(data, model_config_for("mlp", SPEC, **TINY), FAST, out, progress=False)
    provenance = read_meta(out).provenance
    train_ids, val_ids = set(provenance["train_episodes"]), set(provenance["val_episodes"])
    assert train_ids and val_ids and not train_ids & val_ids
    assert train_ids | val_ids == set(range(Dataset.load(data).num_episodes))
    assert provenance["sha256"] == Dataset.load(data).file_hash()
    assert provenance["dataset_steps"] == Dataset.load(data).num_steps  # the physics samples a model cost


@pytest.mark.parametrize("kind", MODEL_KINDS)
def test_every_kind_trains(kind: str, data: Path) -> None:
    config = model_config_for(kind, SPEC, **TINY, ensemble_size=2)
    torch.manual_seed(0)
    before = weights(build_model(config))
    result = train(data, config, FAST, progress=False)
    assert result.stats["val_error"] is not None and np.isfinite(result.stats["val_error"])
    if kind == "no_change":
        assert result.stats["iterations"] == 0
    else:
        assert result.stats["iterations"] == 4 and np.isfinite(result.stats["train_loss"])
        assert any(not torch.equal(before[k], v) for k, v in weights(result.model).items())


def test_same_seed_same_weights_and_resume_matches_uninterrupted_run(data: Path, tmp_path: Path) -> None:
    config = model_config_for("rwm", SPEC, **TINY, ensemble_size=2)
    run = TrainConfig(
        history=6, forecast=3, batch_size=8, iterations=20, val_every=5, checkpoint_every=7, val_fraction=0.25
    )
    full = weights(train(data, config, run, tmp_path / "full.safetensors", progress=False).model)
    again = weights(train(data, config, run, progress=False).model)
    assert all(torch.equal(full[k], again[k]) for k in full)

    def interrupt_at_10(iteration: int, stats: dict) -> None:
        if iteration == 10:
            raise KeyboardInterrupt

    out = tmp_path / "resumed.safetensors"
    with pytest.raises(KeyboardInterrupt):
        train(data, config, run, out, progress=False, callback=interrupt_at_10)
    assert read_meta(out).stats["iterations"] == 10
    resumed = train(data, config, run, out, resume=True, progress=False)
    assert resumed.stats["iterations"] == 20
    assert all(torch.equal(full[k], weights(resumed.model)[k]) for k in full)
    different = TrainConfig(**{**run.to_dict(), "history": 5})
    with pytest.raises(CheckpointError, match="history"):
        train(data, config, different, out, resume=True, progress=False)


def test_schedule_start_restarts_the_learning_rate_on_a_resumed_run(data: Path, tmp_path: Path) -> None:
    config = model_config_for("rwm", SPEC, **TINY)
    first = TrainConfig(**{**FAST.to_dict(), "iterations": 6, "val_every": 1, "checkpoint_every": 6})
    restarted, continued = tmp_path / "restarted.safetensors", tmp_path / "continued.safetensors"
    for out in (restarted, continued):
        train(data, config, first, out, progress=False)
    longer = TrainConfig(**{**first.to_dict(), "iterations": 12})
    plain = train(data, config, longer, continued, resume=True, progress=False)
    warm = train(
        data, config, TrainConfig(**{**longer.to_dict(), "schedule_start": 6}), restarted, resume=True, progress=False
    )
    lr = {
        name: {row["iteration"]: row["lr"] for row in r.stats["log"]} for name, r in (("plain", plain), ("warm", warm))
    }
    assert lr["warm"][7] == pytest.approx(longer.lr) and lr["plain"][7] < 0.8 * longer.lr  # the schedule starts over
    assert lr["warm"][12] == pytest.approx(longer.lr * learning_rate_factor("cosine", 5 / 6))  # its last step
    assert read_meta(restarted).train_config.schedule_start == 6
    assert any(not torch.equal(a, b) for a, b in zip(weights(plain.model).values(), weights(warm.model).values()))
    with pytest.raises(ValueError, match="schedule_start"):
        TrainConfig(iterations=6, schedule_start=6)


def test_forecast_curriculum_trains_each_length_for_its_share(data: Path, tmp_path: Path, monkeypatch) -> None:
    import rwm_gym.model.train as trainer

    seen, sample = [], trainer.sample_batch

    def spy(windows, starts, config, *args):
        seen.append(config.forecast)
        return sample(windows, starts, config, *args)

    monkeypatch.setattr(trainer, "sample_batch", spy)
    config = model_config_for("rwm", SPEC, **TINY)
    run = TrainConfig(**{**FAST.to_dict(), "iterations": 6, "forecast_curriculum": [2, 3, 5]})
    assert run.forecast_curriculum == (2, 3, 5) and run.forecasts == (2, 3, 5)
    curriculum = train(data, config, run, progress=False)
    assert seen == [2, 2, 3, 3, 5, 5]
    seen.clear()
    constant = train(data, config, TrainConfig(**{**run.to_dict(), "forecast_curriculum": ()}), progress=False)
    assert seen == [FAST.forecast] * 6
    assert any(
        not torch.equal(a, b) for a, b in zip(weights(curriculum.model).values(), weights(constant.model).values())
    )
    out = tmp_path / "curriculum.safetensors"
    args = ["train", "--data", str(data), "--out", str(out), "--iterations", "3", "--history", "6", "--batch-size", "8"]
    assert (
        main([*args, "--forecast-curriculum", "2", "4", "--hidden-size", "16", "--head-hidden", "16", "--quiet"]) == 0
    )
    assert read_meta(out).train_config.forecast_curriculum == (2, 4)


def test_tiny_rwm_beats_no_change(data: Path) -> None:
    run = TrainConfig(history=8, forecast=4, batch_size=16, iterations=300, lr=3e-3, val_every=300, val_fraction=0.25)
    options = dict(hidden_size=64, num_layers=1, head_hidden=64)
    rwm = train(data, model_config_for("rwm", SPEC, **options), run, progress=False).stats["val_error"]
    still = train(data, model_config_for("no_change", SPEC), run, progress=False).stats["val_error"]
    assert rwm < 0.8 * still, (rwm, still)


def test_cli_teacher_forcing_and_bad_data(data: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "tf.safetensors"
    code = main(
        [
            "train",
            "--data",
            str(data),
            "--model",
            "mlp",
            "--out",
            str(out),
            "--teacher-forcing",
            "--iterations",
            "3",
            "--history",
            "4",
            "--hidden-size",
            "8",
            "--head-hidden",
            "8",
            "--quiet",
            "--branches",
            "2",
            "--batch-size",
            "8",
            "--unit-gravity",
            "--no-joint-limits",
        ]
    )
    assert code == 0
    summary = capsys.readouterr().out
    assert "3 iterations in" in summary and not re.search(r"\d\.\d{5,}", summary)  # no raw floats
    meta = read_meta(out)
    assert meta.train_config.forecast == 1 and meta.train_config.iterations == 3
    assert meta.train_config.branches == 2 and meta.model_config.unit_gravity and not meta.model_config.joint_limits
    assert meta.model_config.hidden_size == 8 and meta.stats["iterations"] == 3
    assert main(["train", "--data", str(tmp_path / "missing.h5"), "--out", str(out)]) == 2
    assert "missing.h5" in capsys.readouterr().err


def test_init_from_checkpoint_starts_from_its_weights(data: Path, tmp_path: Path) -> None:
    config = model_config_for("rwm", SPEC, **TINY)
    first = train(data, config, FAST, tmp_path / "a.safetensors", progress=False)
    tiny_step = TrainConfig(**{**FAST.to_dict(), "iterations": 1, "lr": 1e-9, "seed": 5})
    tuned = train(data, config, tiny_step, init=first.path, progress=False)
    for name, value in weights(first.model).items():
        torch.testing.assert_close(weights(tuned.model)[name], value, atol=1e-6, rtol=0)
    other = model_config_for("rwm", SPEC, **{**TINY, "hidden_size": 8})
    with pytest.raises(CheckpointError, match="hidden_size"):
        train(data, other, tiny_step, init=first.path, progress=False)


def test_reset_std_band_frees_the_std_of_a_fine_tune(data: Path, tmp_path: Path) -> None:
    """An mse-trained model's std sits on its band's floor; the reset puts band and std where the options say before
    the first step, keeps the predicted means, and needs a checkpoint to start from."""
    config = model_config_for("rwm", SPEC, **{**TINY, "ensemble_size": 2})
    first = train(data, config, FAST, tmp_path / "a.safetensors", progress=False)
    frozen = TrainConfig(
        **{**FAST.to_dict(), "iterations": 1, "lr": 1e-9, "loss": "nll", "reset_std_band": True, "reset_log_std": -1.5}
    )
    tuned = train(data, config, frozen, init=first.path, progress=False).model
    head = tuned.heads.state
    torch.testing.assert_close(head.min_log_std.detach(), torch.full_like(head.min_log_std, config.log_std_min_init))
    torch.testing.assert_close(head.max_log_std.detach(), torch.full_like(head.max_log_std, config.log_std_max_init))
    x = torch.randn(5, 7, SPEC.state_dim + SPEC.action_dim)
    states, actions = x[..., : SPEC.state_dim], x[..., SPEC.state_dim :]
    with torch.no_grad():
        before = first.model.forecast(states, actions, 1, sample=False, member=torch.zeros(5, dtype=torch.long))[0]
        after = tuned.forecast(states, actions, 1, sample=False, member=torch.zeros(5, dtype=torch.long))[0]
    expected = soft_bound(torch.tensor(-1.5), head.min_log_std.detach(), head.max_log_std.detach()).exp()
    torch.testing.assert_close(after.state_std, expected.expand_as(after.state_std), atol=1e-5, rtol=0)
    torch.testing.assert_close(after.state_mean, before.state_mean, atol=1e-5, rtol=0)
    with pytest.raises(ValueError, match="reset_std_band"):
        train(data, config, frozen, progress=False)


def test_cli_init_takes_the_checkpoints_model_config(data: Path, tmp_path: Path, capsys) -> None:
    """Fine-tuning needs no model options: `--init`'s config is their default; a different family is refused."""
    config = model_config_for("rwm", SPEC, **{**TINY, "ensemble_size": 2})
    first = train(data, config, FAST, tmp_path / "a.safetensors", progress=False).path
    common = [
        "train",
        "--data",
        str(data),
        "--init",
        str(first),
        "--history",
        "6",
        "--forecast",
        "3",
        "--batch-size",
        "8",
        "--iterations",
        "1",
        "--val-every",
        "1",
        "--val-fraction",
        "0.25",
        "--quiet",
    ]
    assert main([*common, "--out", str(tmp_path / "b.safetensors")]) == 0
    assert read_meta(tmp_path / "b.safetensors").model_config == config
    assert main([*common, "--out", str(tmp_path / "c.safetensors"), "--model", "mlp"]) == 2
    assert "cannot start a mlp model from a rwm checkpoint" in capsys.readouterr().err


def test_recent_share_draws_that_share_of_each_batch_from_the_last_episodes(data: Path, monkeypatch) -> None:
    import rwm_gym.model.train as trainer

    ds = Dataset.load(data)
    episode_of = np.repeat(np.arange(ds.num_episodes), ds.episode_lengths)
    drawn, sample = [], trainer.sample_batch

    def spy(windows, starts, config, ensemble_size, generator, world, mirror, recent):
        batch = sample(windows, starts, config, ensemble_size, generator, world, mirror, recent)
        first_rows = torch.argmin((batch.window.states[:, :1] - windows.states.unsqueeze(0)).abs().sum(-1), 1)
        drawn.append(episode_of[first_rows.numpy()])
        return batch

    monkeypatch.setattr(trainer, "sample_batch", spy)
    config = model_config_for("rwm", SPEC, **TINY)
    recent = TrainConfig(
        **{**FAST.to_dict(), "batch_size": 16, "iterations": 20, "recent_episodes": 2, "recent_share": 0.5}
    )
    train(data, config, recent, progress=False)
    last = ds.num_episodes - 2
    assert all((episodes[:8] >= last).all() for episodes in drawn)  # the first half: the last two episodes
    assert any((episodes[8:] < last).any() for episodes in drawn)  # the rest: the whole training split
    drawn.clear()
    train(data, config, TrainConfig(**{**recent.to_dict(), "recent_share": 0.0}), progress=False)
    assert np.mean(np.concatenate(drawn) >= last) < 0.5  # uniform: the last two of the episodes are a small share

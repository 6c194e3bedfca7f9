"""The trainer keeps what the user has: an existing checkpoint is never replaced unasked, and a run stopped by Ctrl-C
in the middle of an iteration resumes to the same weights as a run that was never stopped."""

from __future__ import annotations

import signal
from pathlib import Path

import pytest
import torch
from synthetic_dynamics import SPEC, write_linear_dataset

import rwm_gym.model.train as train_module
from rwm_gym.cli import main
from rwm_gym.model import model_config_for
from rwm_gym.model.checkpoint import read_meta
from rwm_gym.model.config import TrainConfig
from rwm_gym.model.train import train

TINY = dict(hidden_size=16, num_layers=1, head_hidden=16)


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    return write_linear_dataset(tmp_path_factory.mktemp("data") / "linear.h5")


def test_train_refuses_an_existing_out_without_resume_or_overwrite(data: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "model.safetensors"
    common = [
        "train",
        "--data",
        str(data),
        "--out",
        str(out),
        "--model",
        "mlp",
        "--hidden-size",
        "8",
        "--history",
        "4",
        "--forecast",
        "2",
        "--batch-size",
        "4",
        "--val-every",
        "2",
        "--quiet",
    ]
    assert main([*common, "--iterations", "6"]) == 0
    before = out.read_bytes()
    assert main([*common, "--iterations", "2"]) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert out.read_bytes() == before and read_meta(out).stats["iterations"] == 6
    assert main([*common, "--iterations", "2", "--overwrite"]) == 0
    assert read_meta(out).stats["iterations"] == 2


def test_ctrl_c_inside_an_iteration_then_resume_matches_the_uninterrupted_run(
    data: Path, tmp_path: Path, monkeypatch
) -> None:
    config = model_config_for("rwm", SPEC, **TINY)
    run = TrainConfig(
        history=6, forecast=3, batch_size=8, iterations=12, val_every=4, checkpoint_every=100, val_fraction=0.25
    )
    full = train(data, config, run, progress=False).model.state_dict()

    calls, step = [0], train_module.train_step

    def ctrl_c_then_step(*args, **kwargs):
        """SIGINT arrives after the iteration drew its batch, as a Ctrl-C during a real run does."""
        calls[0] += 1
        if calls[0] == 5:
            signal.raise_signal(signal.SIGINT)
        return step(*args, **kwargs)

    out = tmp_path / "stopped.safetensors"
    monkeypatch.setattr(train_module, "train_step", ctrl_c_then_step)
    with pytest.raises(KeyboardInterrupt):
        train(data, config, run, out, progress=False)
    monkeypatch.setattr(train_module, "train_step", step)
    resumed = train(data, config, run, out, resume=True, progress=False).model.state_dict()
    assert all(torch.equal(full[k], resumed[k]) for k in full)


def test_training_on_an_interrupted_collection_warns(data: Path, tmp_path: Path) -> None:
    from rwm_gym.data.dataset import Dataset, DatasetWriter

    source, cut = Dataset.load(data), tmp_path / "cut.h5"
    with pytest.raises(KeyboardInterrupt):
        with DatasetWriter(cut, source.info) as writer:
            for i in range(4):
                writer.append_episode(source.episode(i))
            raise KeyboardInterrupt
    run = TrainConfig(history=4, forecast=2, batch_size=4, iterations=1, val_every=1, val_fraction=0.25)
    with pytest.warns(UserWarning, match="complete=false"):
        train(cut, model_config_for("mlp", SPEC, hidden_size=8), run, progress=False)


@pytest.mark.parametrize(
    "command",
    [
        ["train", "--model", "mlp", "--batch-size", "0", "--out", "{tmp}/m.safetensors"],
        ["evaluate", "--checkpoint", "{tmp}/none.safetensors", "--horizons", "-3"],
    ],
)
def test_bad_numbers_give_one_line_errors(data: Path, tmp_path: Path, capsys, command) -> None:
    assert main([c.format(tmp=tmp_path) for c in command] + ["--data", str(data), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "must be >= 1" in err

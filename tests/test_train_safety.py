"""The trainer keeps what the user has: an existing checkpoint is never replaced unasked, and a run stopped by Ctrl-C
in the middle of an iteration resumes to the same weights as a run that was never stopped."""

from __future__ import annotations

import signal
from pathlib import Path

import pytest
import torch

import rwm_gym.model.train as train_module
from rwm_gym.cli import main
from rwm_gym.model import model_config_for
from rwm_gym.model.checkpoint import read_meta
from rwm_gym.model.config import TrainConfig
from rwm_gym.model.train import train
from synthetic_dynamics import SPEC, write_linear_dataset

TINY = dict(hidden_size=16, num_layers=1, head_hidden=16)


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    return write_linear_dataset(tmp_path_factory.mktemp("data") / "linear.h5")


def test_train_refuses_an_existing_out_without_resume_or_overwrite(data: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "model.safetensors"
    common = ["train", "--data", str(data), "--out", str(out), "--model", "mlp", "--hidden-size", "8",
              "--history", "4", "--forecast", "2", "--batch-size", "4", "--val-every", "2", "--quiet"]
    assert main([*common, "--iterations", "6"]) == 0
    before = out.read_bytes()
    assert main([*common, "--iterations", "2"]) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert out.read_bytes() == before and read_meta(out).stats["iterations"] == 6
    assert main([*common, "--iterations", "2", "--overwrite"]) == 0
    assert read_meta(out).stats["iterations"] == 2


def test_ctrl_c_inside_an_iteration_then_resume_matches_the_uninterrupted_run(data: Path, tmp_path: Path,
                                                                              monkeypatch) -> None:
    config = model_config_for("rwm", SPEC, **TINY)
    run = TrainConfig(history=6, forecast=3, batch_size=8, iterations=12, val_every=4, checkpoint_every=100,
                      val_fraction=0.25)
    full = train(data, config, run, progress=False).model.state_dict()

    calls, loss = [0], train_module.window_loss

    def loss_then_ctrl_c(*args, **kwargs):
        """SIGINT arrives after the iteration drew its batch, as a Ctrl-C during a real run does."""
        calls[0] += 1
        if calls[0] == 5:
            signal.raise_signal(signal.SIGINT)
        return loss(*args, **kwargs)

    out = tmp_path / "stopped.safetensors"
    monkeypatch.setattr(train_module, "window_loss", loss_then_ctrl_c)
    with pytest.raises(KeyboardInterrupt):
        train(data, config, run, out, progress=False)
    monkeypatch.setattr(train_module, "window_loss", loss)
    resumed = train(data, config, run, out, resume=True, progress=False).model.state_dict()
    assert all(torch.equal(full[k], resumed[k]) for k in full)

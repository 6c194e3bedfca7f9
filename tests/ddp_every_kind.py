"""Run under torchrun by tests/test_distributed.py: every model kind, 1 and 3 heads, trained data-parallel with
forecast noise; prints one JSON line per run and rank (rank, kind, ensemble, weights checksum, logged loss)."""

import json
import os
import sys

import torch

from rwm_gym.data.dataset import Dataset
from rwm_gym.model import MODEL_KINDS, distributed, model_config_for
from rwm_gym.model.config import TrainConfig
from rwm_gym.model.train import train


def emit(record: dict) -> None:
    """One write per line: both ranks share the pipe, and a line written in one call (< PIPE_BUF) never interleaves."""
    os.write(sys.stdout.fileno(), (json.dumps(record) + "\n").encode())


TINY = dict(hidden_size=16, num_layers=1, head_hidden=16, transformer_dim=16, transformer_context=6, rssm_latent=4)

data = Dataset.load(sys.argv[1])
config = TrainConfig(history=6, forecast=3, batch_size=8, iterations=3, val_every=3, val_fraction=0.25)
for kind in MODEL_KINDS:
    for ensemble in (1,) if kind == "no_change" else (1, 3):
        result = train(
            data, model_config_for(kind, data.spec(), ensemble_size=ensemble, **TINY), config, progress=False
        )
        with torch.no_grad():
            checksum = sum(float(p.double().sum()) for p in result.model.parameters())
        emit(
            {
                "rank": distributed.current_world().rank,
                "kind": kind,
                "ensemble": ensemble,
                "weights": checksum,
                "train_loss": result.stats["train_loss"],
            }
        )
# A time budget: the ranks must agree on the learning rate and on when to stop.
timed = TrainConfig(history=6, forecast=3, batch_size=8, iterations=0, minutes=0.01, val_every=5, val_fraction=0.25)
result = train(data, model_config_for("rwm", data.spec(), **TINY), timed, progress=False)
with torch.no_grad():
    checksum = sum(float(p.double().sum()) for p in result.model.parameters())
emit(
    {
        "rank": distributed.current_world().rank,
        "kind": "rwm-minutes",
        "ensemble": 1,
        "weights": checksum,
        "train_loss": result.stats["train_loss"],
        "iterations": result.stats["iterations"],
    }
)
distributed.close_world()

"""Reproduce the ANYmal D world model shipped in `assets/checkpoints/` (the default of `RWM-AnymalD-v0`).

    python examples/make_default_checkpoint.py [--out assets/checkpoints] [--iterations 2000] [--threads 1]

Collects physics data with fixed seeds (correlated random actions, and the scripted trot with two levels of action
noise under random commands), trains RWM (2 x 256 GRUs, 5 ensemble heads, history 32, forecast 8) for a fixed number
of iterations, and writes the checkpoint plus a small reset dataset (real 32-step histories the imagined env starts
from). The command line is stored in the checkpoint's `extras["made_by"]`.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

from rwm_gym.data.collect import collect
from rwm_gym.data.dataset import merge_datasets
from rwm_gym.imagination.reset_data import make_reset_data
from rwm_gym.model.checkpoint import load_checkpoint, save_checkpoint
from rwm_gym.model.config import TrainConfig
from rwm_gym.model.factory import model_config_for
from rwm_gym.model.train import train
from rwm_gym.spec import load_spec

# (policy, episodes, max steps, action noise, seed): the data mix of the shipped model.
DATA_MIX = (
    ("random", 200, 300, 0.0, 100),
    ("gait", 160, 500, 0.1, 1000),
    ("gait", 60, 500, 0.3, 5000),
)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("assets/checkpoints"))
    parser.add_argument("--data", type=Path, default=Path("data/default_checkpoint"))
    parser.add_argument("--iterations", type=int, default=2000)
    parser.add_argument("--threads", type=int, default=1, help="torch threads (1 is fastest on a busy 2-core CPU)")
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    parts = []
    for policy, episodes, steps, noise, seed in DATA_MIX:
        path = args.data / f"{policy}_noise{noise}_seed{seed}.h5"
        if not path.exists():
            collect("AnymalD-MuJoCo-v0", policy, episodes, path, seed=seed, num_envs=16, action_noise=noise,
                    max_steps=steps)
        parts.append(path)
    data = args.data / "anymal_d_mix.h5"
    if not data.exists():
        merge_datasets(parts, data)

    spec = load_spec("anymal_d")
    checkpoint = args.out / "anymal_d_rwm.safetensors"
    config = TrainConfig(iterations=args.iterations, device=args.device, seed=0, val_every=250, checkpoint_every=250)
    train(data, model_config_for("rwm", spec, ensemble_size=5), config, checkpoint, resume=True)

    reset = make_reset_data(parts[1], args.out / "anymal_d_reset.h5", episodes=24, rows=160, seed=0)
    model, meta = load_checkpoint(checkpoint)
    extras = {"reset_data": reset.name, "made_by": "python examples/make_default_checkpoint.py " + " ".join(sys.argv[1:]),
              "data_mix": [dict(zip(("policy", "episodes", "max_steps", "action_noise", "seed"), m)) for m in DATA_MIX]}
    save_checkpoint(checkpoint, model, meta.spec, train_config=meta.train_config, provenance=meta.provenance,
                    stats=meta.stats, extras=extras)
    print(f"wrote {checkpoint} and {reset}")


if __name__ == "__main__":
    main()

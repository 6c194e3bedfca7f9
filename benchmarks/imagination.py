"""Imagined env-steps/s of RWM-AnymalD-v0 next to batched physics env-steps/s, on the same machine.

    python benchmarks/imagination.py [--envs 1 64 1024 4096] [--seconds 10] [--threads 1] [--device cpu]

Both sides step random actions in [-0.3, 0.3] and restart finished envs (imagined restarts replay the 32-step warm-up),
as a learner would. Physics runs on `mujoco.batch` with `--threads` threads; the world model with `--threads` torch
threads (1 is fastest on a busy 2-core machine). Prints a table with the ratio and writes JSON.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from rwm_gym.imagination.vec_env import make_imagined_core
from rwm_gym.physics.batched import make_core


def rate(core, seconds: float) -> float:
    """Env-steps per second of a batched core with auto-restart."""
    n = core.num_envs
    core.reset(np.arange(n), list(range(n)))
    actions = np.random.default_rng(0).uniform(-0.3, 0.3, (8, n, core.spec.action_dim))
    steps, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds or steps < 3:
        _, _, terminated, truncated, _ = core.step(actions[steps % 8])
        done = np.flatnonzero(terminated | truncated)
        if len(done):
            core.reset(done)
        steps += 1
    return steps * n / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", type=int, nargs="+", default=[1, 64, 1024, 4096])
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--checkpoint", default=None, help="world model (default: the shipped one)")
    parser.add_argument("--out", type=Path, default=Path("results/imagination_speed.json"))
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    rows = []
    for n in args.envs:
        imagined = rate(make_imagined_core(args.checkpoint, n, device=args.device), args.seconds)
        physics = rate(make_core("anymal_d", n, nthread=args.threads), args.seconds)
        rows.append({"envs": n, "imagined_steps_per_s": imagined, "physics_steps_per_s": physics,
                     "ratio": imagined / physics})
    print(f"| envs | imagined env-steps/s ({args.device}) | physics env-steps/s ({args.threads} threads) | ratio |")
    print("|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r['envs']} | {r['imagined_steps_per_s']:,.0f} | {r['physics_steps_per_s']:,.0f} | {r['ratio']:.2f} |")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"threads": args.threads, "device": args.device, "rows": rows}, indent=2))


if __name__ == "__main__":
    main()

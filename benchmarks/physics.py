"""Physics throughput and the zero-action standing check of AnymalD-MuJoCo-v0.

    python benchmarks/physics.py [--envs 1 64 1024] [--threads 2] [--seconds 5] [--out results/physics.json]

Prints env-steps/s (policy steps of 4 physics substeps each) for each batch size on `--threads` threads, and how many
of `--stand-seeds` robots stand 20 s with zero action.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from rwm_gym.physics.batched import make_core
from rwm_gym.physics.locomotion import LocomotionEnv


def steps_per_second(num_envs: int, threads: int, seconds: float) -> float:
    core = make_core("anymal_d", num_envs, nthread=threads)
    core.reset(np.arange(num_envs), list(range(num_envs)))
    rng = np.random.default_rng(0)
    actions = rng.uniform(-0.3, 0.3, (16, num_envs, core.spec.action_dim))
    core.step(actions[0])  # warm-up
    steps, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        core.step(actions[steps % 16])
        done = np.flatnonzero(core.current.terminated | (core.steps >= core.spec.episode_steps))
        if len(done):
            core.reset(done)
        steps += 1
    return steps * num_envs / (time.perf_counter() - start)


def stands(seed: int) -> bool:
    env = LocomotionEnv()
    env.reset(seed=seed)
    for _ in range(env.task_spec.episode_steps):
        if env.step(np.zeros(12))[2]:
            return False
    return True


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", type=int, nargs="+", default=[1, 64, 1024])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--seconds", type=float, default=5.0)
    parser.add_argument("--stand-seeds", type=int, default=5)
    parser.add_argument("--out", type=Path, default=Path("results/physics.json"))
    args = parser.parse_args()

    rates = {n: steps_per_second(n, args.threads, args.seconds) for n in args.envs}
    print(f"| envs | physics env-steps/s ({args.threads} threads) |\n|---:|---:|")
    for n, rate in rates.items():
        print(f"| {n} | {rate:,.0f} |")
    standing = [stands(seed) for seed in range(args.stand_seeds)]
    print(f"zero action, 20 s: {sum(standing)}/{len(standing)} seeds stand without falling")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"threads": args.threads, "env_steps_per_s": rates,
                                    "zero_action_stands": standing}, indent=2))


if __name__ == "__main__":
    main()

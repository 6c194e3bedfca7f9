"""Benchmark of the scripted trot (`rwm_gym.policies.gait.GaitPolicy`) on the ANYmal D physics env.

Three scenarios, 10 seeds each, full 20 s episodes: a fixed command vx = 1 m/s, a zero command, and the env's own
random commands (resampled every 10 s). Prints one table per scenario (seed, forward distance, fell, tracking errors)
and writes them to JSON.

    python benchmarks/gait.py [--seeds 10] [--steps 1000] [--out benchmarks/results/gait.json]
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
from pathlib import Path

import numpy as np
from tqdm import tqdm

from rwm_gym.physics.locomotion import LocomotionCore
from rwm_gym.physics.options import PhysicsOptions
from rwm_gym.policies.gait import GaitPolicy
from rwm_gym.spec import TaskSpec, load_spec
from rwm_gym.task.observation import observation_slices


def rollout(
    spec: TaskSpec, seeds: list[int], steps: int, command: tuple[float, float, float] | None, **gait: float
) -> dict[str, np.ndarray]:
    """Run one env per seed for `steps` policy steps; `command` fixes the command (None: the env samples it).

    Returns per seed: `distance` (m, base x displacement in the world at the end or at the fall), `fell` (bool),
    `error_xy` (m/s, mean |commanded - measured| planar body velocity), `error_yaw` (rad/s), over upright steps.
    """
    n = len(seeds)
    core = LocomotionCore(spec, n, options=PhysicsOptions(nthread=min(n, os.cpu_count() or 1)))
    obs = core.reset(np.arange(n), seeds, None if command is None else np.tile(np.float32(command), (n, 1)))
    policy = GaitPolicy(spec, n, **gait)
    policy.reset(np.arange(n), [np.random.default_rng([seed, 1]) for seed in seeds])
    s = observation_slices(spec)
    start = core.sim.arrays()["qpos"][:, 0].copy()
    distance = np.zeros(n)
    fell = np.zeros(n, dtype=bool)
    error_xy, error_yaw, count = np.zeros(n), np.zeros(n), np.zeros(n)
    for _ in tqdm(range(steps), desc=f"command {command}", leave=False):
        cmd = obs[:, s["command"]]
        obs, _, terminated, _, _ = core.step(policy.act(obs))
        up = ~fell
        error_xy += up * np.linalg.norm(cmd[:, :2] - obs[:, s["base_lin_vel"]][:, :2], axis=1)
        error_yaw += up * np.abs(cmd[:, 2] - obs[:, s["base_ang_vel"]][:, 2])
        count += up
        distance = np.where(up, core.sim.arrays()["qpos"][:, 0] - start, distance)
        fell |= terminated
    count = np.maximum(count, 1)
    return {
        "seed": np.asarray(seeds),
        "distance": distance,
        "fell": fell,
        "error_xy": error_xy / count,
        "error_yaw": error_yaw / count,
    }


def print_table(title: str, result: dict[str, np.ndarray]) -> None:
    print(f"\n{title}")
    print(f"{'seed':>5} {'distance m':>11} {'fell':>5} {'err xy m/s':>11} {'err yaw rad/s':>14}")
    for i in range(len(result["seed"])):
        print(
            f"{result['seed'][i]:>5} {result['distance'][i]:>11.2f} {bool(result['fell'][i])!s:>5} "
            f"{result['error_xy'][i]:>11.3f} {result['error_yaw'][i]:>14.3f}"
        )
    print(
        f"{'mean':>5} {result['distance'].mean():>11.2f} {int(result['fell'].sum()):>4}/{len(result['seed'])} "
        f"{result['error_xy'].mean():>11.3f} {result['error_yaw'].mean():>14.3f}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=10, help="episodes per scenario, seeds 0..N-1")
    parser.add_argument("--steps", type=int, default=1000, help="policy steps per episode (50 Hz)")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/gait.json"), help="JSON results")
    args = parser.parse_args()
    spec = load_spec("anymal_d")
    seeds = list(range(args.seeds))
    scenarios = {"vx = 1 m/s": (1.0, 0.0, 0.0), "zero command": (0.0, 0.0, 0.0), "random commands": None}
    results = {}
    for title, command in scenarios.items():
        result = rollout(spec, seeds, args.steps, command)
        print_table(title, result)
        results[title] = {k: v.tolist() for k, v in result.items()}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.NamedTemporaryFile("w", dir=args.out.parent, suffix=".tmp", delete=False) as f:
        json.dump({"steps": args.steps, "results": results}, f, indent=1)
    os.replace(f.name, args.out)
    print(f"\nwrote {args.out}")


if __name__ == "__main__":
    main()

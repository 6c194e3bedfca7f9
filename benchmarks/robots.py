"""The legged robots side by side: physics env-steps/s, measured alternately in one run, and the standing floor.

    python benchmarks/robots.py [--robots AnymalD-MuJoCo-v0 Go2-MuJoCo-v0 my_robot.toml ...] [--envs 256]
                                [--threads 1] [--seconds 4] [--rounds 3] [--floor] [--out results/robots]

Each robot is a physics env id or a spec file (e.g. one written by `rwm-gym spec --mjcf robot.xml --fast-physics`).
Every robot steps uniform random actions in [-1, 1] through the package's SB3 vector env at the same number of envs
and threads, in turn for `--seconds`, over `--rounds` rounds, so every ratio is measured under the same load; the
median of the rounds is reported, with its ratio to the first robot. `--floor` adds each robot's zero-action
tracking score and falls on its own scoring commands (`rwm-gym score --policy zero --env ROBOT`). Writes `<out>.json`
and `<out>.md`.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np
from physics import timed_rate  # benchmarks/physics.py: run as a script, this folder is on the path

from rwm_gym.atomic import write_json, write_text
from rwm_gym.registration import resolve_spec
from rwm_gym.rl.score import score
from rwm_gym.vector.sb3_vec_env import LocomotionSB3VecEnv


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--robots", nargs="+", default=["AnymalD-MuJoCo-v0", "Go2-MuJoCo-v0"])
    parser.add_argument("--envs", type=int, default=256)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--seconds", type=float, default=4.0)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--floor", action="store_true", help="also score the zero-action floor of each robot")
    parser.add_argument("--out", type=Path, default=Path("results/robots"))
    args = parser.parse_args()

    specs = {robot: resolve_spec(robot) for robot in args.robots}
    envs = {robot: LocomotionSB3VecEnv(args.envs, spec=spec, nthread=args.threads) for robot, spec in specs.items()}
    rng = np.random.default_rng(0)
    actions = {r: rng.uniform(-1, 1, (16, args.envs, s.action_dim)) for r, s in specs.items()}
    for env in envs.values():
        env.seed(0)
        env.reset()
    rates: dict[str, list[float]] = {robot: [] for robot in specs}
    loads = []
    for k in range(args.rounds):
        for robot, env in envs.items():
            rates[robot].append(timed_rate(env, actions[robot], args.seconds))
        loads.append(os.getloadavg()[0])
        print(f"round {k + 1}: " + ", ".join(f"{r} {v[-1]:,.0f}" for r, v in rates.items()), flush=True)
    for env in envs.values():
        env.close()
    first = args.robots[0]
    rows = []
    for robot, spec in specs.items():
        median = float(np.median(rates[robot]))
        row = {
            "robot": robot,
            "task": spec.name,
            "env_steps_per_s": median,
            "ratio": median / float(np.median(rates[first])),
            "rounds": rates[robot],
        }
        if args.floor:
            floor = score("zero", spec=spec)
            row["floor"] = {"tracking": floor.tracking, "falls": floor.falls, "episodes": floor.episodes}
        rows.append(row)
    lines = [
        f"{args.envs} envs, {args.threads} thread(s), random actions, median of {args.rounds} rounds of "
        f"{args.seconds:g} s; load average {min(loads):.2f}-{max(loads):.2f}",
        "",
        f"| robot | env-steps/s | ratio to {first} |" + (" standing floor (falls) |" if args.floor else ""),
        "|---|---:|---:|" + ("---:|" if args.floor else ""),
    ]
    for r in rows:
        floor = (
            f" {r['floor']['tracking']:.3f} ({r['floor']['falls']}/{r['floor']['episodes']}) |" if args.floor else ""
        )
        lines.append(f"| {r['robot']} | {r['env_steps_per_s']:,.0f} | {r['ratio']:.2f} |{floor}")
    table = "\n".join(lines)
    print(table)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_text(args.out.with_suffix(".md"), table + "\n")
    write_json(
        args.out.with_suffix(".json"), {"envs": args.envs, "threads": args.threads, "loadavg": loads, "rows": rows}
    )


if __name__ == "__main__":
    main()

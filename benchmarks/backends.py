"""The workers' backends timed: `rwm-gym collect` and `rwm-gym score` with 1 and N workers, as spawned processes and
as Ray tasks, each timed as the command a user types (process start-up included), in alternating rounds.

Prints a table (wall seconds, speed-up against 1 process, the load average before and after each run) and writes
`backends.json` to --out; checks that every collection is byte-identical and every score the same. With RAY_ADDRESS
set (or a `ray start --head` on this machine) the Ray runs use that cluster; otherwise each starts a local one, whose
start-up (seconds) it then includes. On a shared machine the load average says how much the figures mean: N workers
on N busy cores gain little or nothing.

    python benchmarks/backends.py                                  # 2 workers, this machine
    ray start --head && python benchmarks/backends.py --workers 16 # a Ray cluster already running
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

from rwm_gym.atomic import write_json
from rwm_gym.options import parse_dataclass_args


@dataclass(frozen=True)
class Options:
    """Collection and scoring with 1 and N workers on each backend, timed."""

    out: str = "benchmarks/results/backends"
    """Folder for the collected files, the scores and backends.json."""
    workers: int = 2
    """N: workers compared with 1."""
    rounds: int = 1
    """Alternating rounds per measurement."""
    episodes: int = 8
    """Episodes of the scripted trot per collection."""
    episode_steps: int = 500
    """Policy steps per collected and per scored episode."""
    num_envs: int = 4
    """Simulations per collection worker."""
    score_seeds: int = 2
    """Scored episodes per command."""
    score_commands: int = 6
    """Random commands of the scoring set, beside standing and 1 m/s forward."""


def timed(command: list[str]) -> dict:
    load = os.getloadavg()
    tic = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True)
    if done.returncode:
        raise SystemExit(f"failed: {' '.join(command)}\n{done.stderr[-2000:]}")
    return {"wall_s": time.perf_counter() - tic, "loadavg_before": load, "loadavg_after": os.getloadavg()}


def figures(score_dir: Path) -> dict:
    report = json.loads((score_dir / "score.json").read_text())
    for evaluation in (report["evaluation"], report["floor_evaluation"]):
        evaluation.pop("wall_s")
    return report


def main(argv: list[str] | None = None) -> dict:
    options = parse_dataclass_args(Options, argv)
    out = Path(options.out)
    out.mkdir(parents=True, exist_ok=True)
    cli = [sys.executable, "-m", "rwm_gym.cli"]
    setups = [("processes", 1), ("processes", options.workers), ("ray", 1), ("ray", options.workers)]
    runs: dict[str, list[dict]] = {}
    for _ in range(options.rounds):
        for backend, n in setups:
            name = f"{backend} x{n}"
            workers = ["--workers", str(n), "--backend", backend]
            collect = [*cli, "collect", "--policy", "gait", "--episodes", str(options.episodes)]
            collect += ["--max-steps", str(options.episode_steps), "--num-envs", str(options.num_envs)]
            collect += ["--out", str(out / f"collect_{backend}_{n}.h5"), "--overwrite", *workers]
            runs.setdefault(f"collect {name}", []).append(timed(collect))
            score = [*cli, "score", "--policy", "gait", "--seeds", str(options.score_seeds)]
            score += ["--steps", str(options.episode_steps), "--commands", str(options.score_commands)]
            score += ["--out", str(out / f"score_{backend}_{n}"), "--overwrite", *workers]
            runs.setdefault(f"score {name}", []).append(timed(score))
    collections = {(out / f"collect_{b}_{n}.h5").read_bytes() for b, n in setups}
    scores = [figures(out / f"score_{b}_{n}") for b, n in setups]
    result = {
        "options": asdict(options),
        "cpu_count": os.cpu_count(),
        "ray_address": os.environ.get("RAY_ADDRESS", ""),
        "identical_collections": len(collections) == 1,
        "identical_scores": all(s == scores[0] for s in scores),
        "runs": runs,
    }
    write_json(out / "backends.json", result)
    print(f"{'run':22s} {'best wall s':>11s} {'speed-up':>8s} {'load before':>11s} {'load after':>10s}")
    for name, entries in runs.items():
        best = min(entries, key=lambda e: e["wall_s"])
        base = min(e["wall_s"] for e in runs[f"{name.split()[0]} processes x1"])
        print(
            f"{name:22s} {best['wall_s']:11.1f} {base / best['wall_s']:8.2f} {best['loadavg_before'][0]:11.2f} "
            f"{best['loadavg_after'][0]:10.2f}"
        )
    same = result["identical_collections"], result["identical_scores"]
    print(f"collections byte-identical: {same[0]}; scores identical: {same[1]}")
    return result


if __name__ == "__main__":
    main()

"""Scaling out on one machine: `rwm-gym collect --workers 1` vs `--workers N`, and `rwm-gym train` in one process vs
`torchrun --nproc_per_node=N` (DDP), each timed as the command a user types, in alternating rounds of one run.

Prints a table (wall seconds, episodes or iterations per second, speed-up against 1, load average before each run)
and writes `scaling.json` to --out. On a shared machine the load average says how much the figures mean: N processes
on N busy cores gain little or nothing.

    python benchmarks/scaling.py                                  # 2 processes, CPU
    python benchmarks/scaling.py --processes 8 --device cuda      # 8 GPUs (not run here: no GPU)
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

from rwm_gym.options import parse_dataclass_args
from rwm_gym.resources import assets_dir


@dataclass(frozen=True)
class Options:
    """Collection workers and data-parallel training ranks against one process, timed."""

    out: str = "benchmarks/results/scaling"
    """Folder for the collected files, checkpoints and scaling.json."""
    processes: int = 2
    """N: collection workers and training ranks compared with 1."""
    rounds: int = 1
    """Alternating rounds (1, N, 1, N, ...) per measurement."""
    episodes: int = 16
    """Episodes of the scripted trot per collection."""
    episode_steps: int = 200
    """Policy steps per collected episode."""
    num_envs: int = 4
    """Simulations per collection worker."""
    data: str = ""
    """Dataset to train on (default: the shipped ANYmal D demonstrations)."""
    iterations: int = 40
    """Training iterations per run."""
    batch_size: int = 64
    """Global batch (windows), split over the ranks."""
    device: str = "cpu"
    """torch device of training (cuda: one GPU per rank)."""


def timed(command: list[str]) -> dict:
    load = os.getloadavg()[0]
    tic = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True)
    if done.returncode:
        raise SystemExit(f"failed: {' '.join(command)}\n{done.stderr[-2000:]}")
    entry = {"wall_s": time.perf_counter() - tic, "loadavg_before": load}
    summary = [line for line in done.stdout.splitlines() if line.endswith("}") and "{" in line]
    if summary:  # rwm-gym train's own timing of its loop, without process start-up and data loading
        entry["loop_s"] = json.loads(summary[-1][summary[-1].index("{") :])["wall_s"]
    return entry


def main(argv: list[str] | None = None) -> dict:
    options = parse_dataclass_args(Options, argv)
    out = Path(options.out)
    out.mkdir(parents=True, exist_ok=True)
    cli = [sys.executable, "-m", "rwm_gym.cli"]
    data = options.data or str(assets_dir() / "checkpoints" / "anymal_d_demos.h5")
    runs: dict[str, list[dict]] = {}
    for _ in range(options.rounds):
        for n in (1, options.processes):
            path = out / f"collect_{n}.h5"
            runs.setdefault(f"collect x{n}", []).append(
                timed(
                    [
                        *cli,
                        "collect",
                        "--policy",
                        "gait",
                        "--episodes",
                        str(options.episodes),
                        "--max-steps",
                        str(options.episode_steps),
                        "--num-envs",
                        str(options.num_envs),
                        "--workers",
                        str(n),
                        "--out",
                        str(path),
                        "--overwrite",
                    ]
                )
            )
            launcher = (
                cli
                if n == 1
                else [
                    sys.executable,
                    "-m",
                    "torch.distributed.run",
                    "--standalone",
                    f"--nproc_per_node={n}",
                    "-m",
                    "rwm_gym.cli",
                ]
            )
            checkpoint = out / f"train_{n}.safetensors"
            checkpoint.unlink(missing_ok=True)
            runs.setdefault(f"train x{n}", []).append(
                timed(
                    [
                        *launcher,
                        "train",
                        "--data",
                        data,
                        "--out",
                        str(checkpoint),
                        "--iterations",
                        str(options.iterations),
                        "--batch-size",
                        str(options.batch_size),
                        "--val-every",
                        str(options.iterations),
                        "--device",
                        options.device,
                        "--quiet",
                    ]
                )
            )
    same = (out / "collect_1.h5").read_bytes() == (out / f"collect_{options.processes}.h5").read_bytes()
    result = {"options": asdict(options), "cpu_count": os.cpu_count(), "identical_collections": same, "runs": runs}
    (out / "scaling.json").write_text(json.dumps(result, indent=2))
    print(f"{'run':12s} {'best wall s':>11s} {'rate':>14s} {'speed-up':>8s} {'loop s':>7s} {'load before':>11s}")
    for name, entries in runs.items():
        best = min(entries, key=lambda e: e["wall_s"])
        kind, n = name.split(" x")
        base = min(e["wall_s"] for e in runs[f"{kind} x1"])
        amount, unit = (options.episodes, "ep/s") if kind == "collect" else (options.iterations, "it/s")
        loop = f"{best['loop_s']:7.1f}" if "loop_s" in best else f"{'-':>7s}"
        print(
            f"{name:12s} {best['wall_s']:11.1f} {amount / best['wall_s']:9.2f} {unit} {base / best['wall_s']:8.2f} "
            f"{loop} {best['loadavg_before']:11.2f}"
        )
    print(f"collections byte-identical: {same}")
    return result


if __name__ == "__main__":
    main()

"""`rwm-gym evaluate` with its defaults against `rwm-gym train --iterations 20` on the same data, in one run.

    python benchmarks/evaluate_speed.py [--episodes 4] [--demos] [--previous] [--out results/evaluate_speed]

Collects `--episodes` episodes of the trot (`rwm-gym collect`), trains the default world model on them for 20
iterations (`rwm-gym train --iterations 20`) and evaluates that checkpoint on the same file with evaluate's defaults
(on its held-out validation episodes). Each command runs as a process of its own and is timed in wall-clock seconds
and CPU seconds (the process's user + system time), with the load average (`os.getloadavg`, the figures `uptime`
prints) read before and after it. `--demos` also evaluates the shipped checkpoint on the shipped demonstrations
(`assets/checkpoints/anymal_d_demos.h5`) with the defaults; `--previous` evaluates the 4-episode checkpoint again as
the defaults were before the slow extras were made options (`--max-horizon 368 --noise 0.1 0.2 0.4 0.8
--max-windows 512`). Writes `<out>.json` and `<out>.md`.
"""

from __future__ import annotations

import argparse
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from rwm_gym.atomic import write_json, write_text
from rwm_gym.resources import assets_dir

RWM_GYM = [sys.executable, "-m", "rwm_gym.cli"]
PREVIOUS = ["--max-horizon", "368", "--noise", "0.1", "0.2", "0.4", "0.8", "--max-windows", "512"]
"""The defaults `rwm-gym evaluate` had while the longest horizon and the robustness test ran unasked."""


def timed(name: str, args: list[str]) -> dict:
    """Run `rwm-gym ARGS` to its end; its wall-clock and CPU seconds and the load average around it."""
    before, load = resource.getrusage(resource.RUSAGE_CHILDREN), os.getloadavg()
    start = time.perf_counter()
    subprocess.run([*RWM_GYM, *args], check=True, stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    row = {"name": name, "command": "rwm-gym " + " ".join(args), "wall_s": wall, "cpu_s": cpu}
    row |= {"load_before": list(load), "load_after": list(os.getloadavg())}
    print(f"{name}: {wall:.1f} s wall, {cpu:.1f} s CPU (load {load[0]:.2f} -> {row['load_after'][0]:.2f})")
    return row


def markdown(rows: list[dict]) -> str:
    """The table: each command's times, against the training run's."""
    train = next(r for r in rows if r["name"] == "train")
    lines = [
        "| run | wall s | CPU s | wall / train's | CPU / train's | load average (1 min) before -> after |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['name']} | {r['wall_s']:.1f} | {r['cpu_s']:.1f} | {r['wall_s'] / train['wall_s']:.2f} | "
            f"{r['cpu_s'] / train['cpu_s']:.2f} | {r['load_before'][0]:.2f} -> {r['load_after'][0]:.2f} |"
        )
    return "\n".join(lines) + "\n\n" + "\n".join(f"- {r['name']}: `{r['command']}`" for r in rows) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=int, default=4)
    parser.add_argument("--demos", action="store_true", help="also evaluate the shipped checkpoint on the demos")
    parser.add_argument("--previous", action="store_true", help="also evaluate with the previous defaults")
    parser.add_argument("--out", default="results/evaluate_speed")
    options = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        data, model = Path(folder) / "data.h5", Path(folder) / "model.safetensors"
        collect = ["collect", "--episodes", str(options.episodes), "--num-envs", str(options.episodes)]
        subprocess.run([*RWM_GYM, *collect, "--out", str(data)], check=True, stdout=subprocess.DEVNULL)
        rows = [timed("train", ["train", "--data", str(data), "--iterations", "20", "--out", str(model), "--quiet"])]
        evaluate = ["evaluate", "--checkpoint", str(model), "--data", str(data), "--quiet"]
        rows.append(timed("evaluate", evaluate))
        if options.previous:
            rows.append(timed("evaluate, previous defaults", [*evaluate, *PREVIOUS]))
        if options.demos:
            shipped = assets_dir() / "checkpoints"
            demos = ["--checkpoint", str(shipped / "anymal_d_rwm.safetensors")]
            demos += ["--data", str(shipped / "anymal_d_demos.h5"), "--quiet"]
            rows.append(timed("evaluate, shipped checkpoint on the demos", ["evaluate", *demos]))
    out = Path(options.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    machine = {"cpus": os.cpu_count(), "processor": platform.processor() or platform.machine()}
    write_json(out.with_suffix(".json"), {"episodes": options.episodes, "machine": machine, "runs": rows})
    write_text(out.with_suffix(".md"), markdown(rows))
    print(markdown(rows))


if __name__ == "__main__":
    main()

"""Several `benchmarks/trainer.py` runs on one plot: validation error against CPU minutes of every arm they trained.

Each run's new arm is labelled by its setting (segments x branches, stride, warm-up gradients); the old arm (the
paper's 64 windows of 32 + 8 rows) of each run is drawn too, so the spread between runs of the same setting shows.
Writes `<out>.png` and `<out>.md` (error at 2.5 / 5 / 7.5 / 10 minutes, iterations, windows per second of the run's
throughput rounds where it measured them).

    python benchmarks/trainer_compare.py results/trainer_a results/trainer_b --out benchmarks/figures/trainer
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

sys.path.insert(0, str(Path(__file__).parent))  # the trainer benchmark, a sibling script
from trainer import error_at

from rwm_gym.atomic import save_png, write_text

MARKS = (2.5, 5.0, 7.5, 10.0)


def label(arm: str, config: dict) -> str:
    """The arm's setting, read from the TrainConfig the run stored."""
    if config["branches"] == 1:
        setting = f"{config['batch_size']} windows of {config['history']} + {config['forecast']} rows"
    else:
        setting = (
            f"{config['batch_size'] // config['branches']} x {config['branches']} branches, "
            f"stride {config['branch_stride']}"
        )
    return f"{arm}: {setting}" + ("" if config["warmup_gradients"] else ", no warm-up gradients")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path, help="output folders of benchmarks/trainer.py")
    parser.add_argument("--out", type=Path, required=True, help="path stem of the PNG and the table")
    args = parser.parse_args()
    rows = [
        "| run | arm | " + " | ".join(f"{m:g} min" for m in MARKS) + " | iterations | windows/s, 1 thread |",
        "|---|---|" + "---|" * (len(MARKS) + 2),
    ]
    fig, ax = plt.subplots(figsize=(8, 5))
    for run in args.runs:
        result = json.loads((run / "results.json").read_text())
        rates = next(
            (t["windows_per_s"] for t in result.get("throughput", []) if t["kind"] == "rwm" and t["threads"] == 1), {}
        )
        for arm, curve in result["curves"].items():
            name = label(arm, result["arms"][arm])
            log = curve["log"]
            ax.plot(
                [row["wall_s"] / 60 for row in log],
                [row["val_error"] for row in log],
                ls="--" if arm == "old" else "-",
                label=f"{run.name}, {name}",
            )
            marks = " | ".join("-" if (e := error_at(log, 60 * m)) is None else f"{e:.4f}" for m in MARKS)
            rate = f"{rates[arm]:.0f}" if arm in rates else "-"
            rows.append(f"| {run.name} | {name} | {marks} | {curve['iterations']:,} | {rate} |")
    ax.set_xlabel("CPU minutes (one thread)")
    ax.set_ylabel("validation error (8-step open-loop, relative L1)")
    ax.set_ylim(top=0.5)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    ax.set_title("RWM trainer settings at equal CPU time")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    save_png(fig, args.out.with_suffix(".png"), bbox_inches="tight")
    write_text(args.out.with_suffix(".md"), "\n".join(rows) + "\n")
    print("\n".join(rows))


if __name__ == "__main__":
    main()

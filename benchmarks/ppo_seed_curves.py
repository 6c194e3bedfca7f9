"""Several PPO runs' physics learning curves in one figure: tracking against env steps and against the runs' own wall
time, and falls against env steps, per run.

    python benchmarks/ppo_seed_curves.py --runs runs/a runs/b runs/c --out benchmarks/figures/NAME \
        [--labels "seed 0" ...] [--title "..."] [--trained-in imagination]

Reads each `RUN/curve/curve.csv` written by `benchmarks/ppo_curve.py` (score the snapshots first) and draws the
shipped physics policy's tracking, 0.9 x it and the zero-action floor (from the first run's `curve.json`) beside them.
Wall time is the run's training time at each snapshot as it ran (machine load included). Writes `OUT.png` and `OUT.csv`
(run, timesteps, wall_s, tracking, falls, episodes).
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

from rwm_gym.atomic import atomic_write
from rwm_gym.resources import assets_dir


def read_curve(run: Path) -> list[dict]:
    table = run / "curve" / "curve.csv"
    if not table.is_file():
        raise SystemExit(f"{table}: no such file (run benchmarks/ppo_curve.py --run-dir {run} first)")
    rows = list(csv.DictReader(table.open()))
    return sorted(
        (
            {
                "timesteps": int(r["timesteps"]),
                "wall_s": float(r["wall_s"]),
                "tracking": float(r["tracking"]),
                "falls": int(r["falls"]),
                "episodes": int(r["episodes"]),
            }
            for r in rows
        ),
        key=lambda r: r["timesteps"],
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=Path, nargs="+", required=True, help="run folders with curve/curve.csv")
    parser.add_argument("--out", type=Path, required=True, help="output path without suffix (.png and .csv)")
    parser.add_argument("--labels", nargs="+", help="one per run (default: the run folders' names)")
    parser.add_argument("--title", default="PPO learning curves, scored in physics")
    parser.add_argument("--trained-in", choices=("physics", "imagination"), default="imagination")
    args = parser.parse_args()
    labels = args.labels or [run.name for run in args.runs]
    if len(labels) != len(args.runs):
        parser.error(f"{len(labels)} --labels for {len(args.runs)} --runs")
    curves = {label: read_curve(run) for label, run in zip(labels, args.runs)}
    teacher = json.loads((assets_dir() / "policies" / "anymal_d_ppo_physics.json").read_text())["score"]
    summary = args.runs[0] / "curve" / "curve.json"  # ppo_curve.py scores the zero-action floor once per run
    floor = json.loads(summary.read_text())["floor"]["tracking"] if summary.is_file() else None

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, cx, bx) = plt.subplots(1, 3, figsize=(15, 4.6))
    for name, curve in curves.items():
        x = [r["timesteps"] / 1e6 for r in curve]
        ax.plot(x, [r["tracking"] for r in curve], ".-", label=name)
        cx.plot([r["wall_s"] / 60 for r in curve], [r["tracking"] for r in curve], ".-")
        bx.plot(x, [r["falls"] for r in curve], ".-", label=name)
    for a in (ax, cx):
        a.axhline(teacher["tracking"], color="k", lw=0.8, label=f"physics PPO policy ({teacher['tracking']:.3f})")
        a.axhline(0.9 * teacher["tracking"], color="tab:green", ls=":", label="0.9 x it")
        if floor is not None:
            a.axhline(floor, color="0.5", ls="--", label=f"zero action ({floor:.3f})")
        a.set_ylabel("tracking score in physics")
    cx.set_xlabel("training wall time (min, as run)")
    episodes = next(iter(curves.values()))[0]["episodes"] if next(iter(curves.values())) else 0
    bx.set_ylabel(f"falls in {episodes} physics episodes")
    for a in (ax, bx):
        a.set_xlabel(f"{args.trained_in} env steps (M)")
    handles, labels = ax.get_legend_handles_labels()
    rows = -(-len(handles) // 4)  # below both panels, four to a row: the curves stay uncovered
    fig.legend(handles, labels, fontsize=8, loc="lower center", ncol=4)
    fig.suptitle(args.title, fontsize=10)
    fig.tight_layout(rect=(0, 0.06 * rows, 1, 1))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out.with_suffix(".png"), dpi=100)
    plt.close(fig)

    def write(tmp: str) -> None:
        with open(tmp, "w", newline="") as f:
            w = csv.writer(f)
            columns = ("timesteps", "wall_s", "tracking", "falls", "episodes")
            w.writerow(["run", *columns])
            for name, curve in curves.items():
                w.writerows([name, *(r[c] for c in columns)] for r in curve)

    atomic_write(args.out.with_suffix(".csv"), write)
    print(f"wrote {args.out.with_suffix('.png')} and {args.out.with_suffix('.csv')}")


if __name__ == "__main__":
    main()

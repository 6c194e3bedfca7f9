"""MBPO-PPO runs against model-free PPO: physics tracking and falls against every physics sample behind each policy.

    python benchmarks/mbpo_samples.py --runs runs/mbpo_policy runs/mbpo_random --labels "from a policy" "random data" \
        --prior 1553211 0 --out benchmarks/figures/NAME
    python benchmarks/mbpo_samples.py --runs runs/mbpo_random_more_ppo --labels "more PPO" \
        --earlier benchmarks/figures/mbpo_policy_start_and_random_data.csv "random" --out benchmarks/figures/NAME

`rwm-gym mbpo` counts the rows of its `--data`, of its starting checkpoint's lineage and of what it collects. A run
that starts from a policy made from other physics data (or a run folder from before checkpoints recorded their
lineage) has those rows behind it too: `--prior` adds them, per run, so the x axis is every physics sample the policy
depends on. The model-free curve is the shipped physics PPO policy's
(`assets/policies/anymal_d_ppo_physics_curve.csv`); N_mf is its samples when it first reached tracking 0.80.
Writes OUT.png and OUT.csv (run, iteration, physics_samples, fraction_of_n_mf, tracking, falls). `--earlier CSV RUN`
draws a run whose folder is gone from a CSV this script wrote: the one run whose label contains RUN.
"""

from __future__ import annotations

import argparse
import csv
import io
import json
from pathlib import Path

from rwm_gym.atomic import atomic_write, save_png
from rwm_gym.resources import assets_dir
from rwm_gym.rl.mbpo import TRACKING_TARGET, read_curve

MODEL_FREE = assets_dir() / "policies" / "anymal_d_ppo_physics_curve.csv"


def n_mf(path: Path, max_falls: int = 1) -> int:
    """Model-free PPO's physics samples when it first reaches the target tracking with at most `max_falls` falls
    (N_mf as `benchmarks/ppo_curve.py` defines it: 32.2 M for the shipped teacher)."""
    rows = list(csv.DictReader(path.open()))
    return next(
        int(r["timesteps"]) for r in rows if float(r["tracking"]) >= TRACKING_TARGET and int(r["falls"]) <= max_falls
    )


def rows_of(run: Path, label: str, prior: int, n_model_free: int) -> list[dict]:
    report = run / "mbpo.json"
    if not report.is_file():
        raise SystemExit(f"{report}: no such file (an `rwm-gym mbpo --out {run}` run writes it)")
    log = json.loads(report.read_text())["log"]
    return [
        {
            "run": label,
            "iteration": r["iteration"],
            "physics_samples": prior + r["physics_samples"],
            "fraction_of_n_mf": (prior + r["physics_samples"]) / n_model_free,
            "tracking": r["tracking"],
            "falls": r["falls"],
        }
        for r in log
    ]


def earlier_rows(path: Path, name: str) -> list[dict]:
    """The rows of an earlier run, read back from a CSV this script wrote: those whose `run` contains `name`."""
    if not path.is_file():
        raise SystemExit(f"{path}: no such file (a CSV written by this script)")
    rows = [r for r in csv.DictReader(path.open()) if name in r["run"]]
    if not rows:
        raise SystemExit(f"{path}: no run named like {name!r}")
    if len({r["run"] for r in rows}) > 1:
        raise SystemExit(f"{path}: {name!r} names more than one run ({', '.join(sorted({r['run'] for r in rows}))})")
    return [
        {
            "run": r["run"],
            "iteration": int(r["iteration"]),
            "physics_samples": int(r["physics_samples"]),
            "fraction_of_n_mf": float(r["fraction_of_n_mf"]),
            "tracking": float(r["tracking"]),
            "falls": int(r["falls"]),
        }
        for r in rows
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=Path, nargs="+", required=True, help="rwm-gym mbpo run folders")
    parser.add_argument("--labels", nargs="+", help="one per run (default: the folders' names)")
    parser.add_argument("--prior", type=int, nargs="+", help="physics rows behind each run's start (default 0)")
    parser.add_argument(
        "--earlier",
        nargs=2,
        action="append",
        default=[],
        metavar=("CSV", "RUN"),
        help="also draw a run from a CSV this script wrote (repeatable)",
    )
    parser.add_argument("--out", type=Path, required=True, help="output path without suffix (.png and .csv)")
    args = parser.parse_args()
    labels = args.labels or [run.name for run in args.runs]
    prior = args.prior or [0] * len(args.runs)
    if len(labels) != len(args.runs) or len(prior) != len(args.runs):
        parser.error("--labels and --prior need one value per run")
    model_free = read_curve(MODEL_FREE)
    total = n_mf(MODEL_FREE)
    earlier = [earlier_rows(Path(path), name) for path, name in args.earlier]
    rows = [row for part in earlier for row in part]
    rows += [row for run, label, p in zip(args.runs, labels, prior) for row in rows_of(run, label, p, total)]
    labels = [part[0]["run"] for part in earlier] + labels

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, ax_falls) = plt.subplots(1, 2, figsize=(12, 4))
    ax.plot([s / 1e6 for s, _ in model_free], [t for _, t in model_free], "-", color="grey", label="model-free PPO")
    for label in labels:
        mine = [r for r in rows if r["run"] == label]
        x = [r["physics_samples"] / 1e6 for r in mine]
        ax.plot(x, [r["tracking"] for r in mine], "o-", markersize=3, label=label)
        ax_falls.plot(x, [r["falls"] for r in mine], "o-", markersize=3, label=label)
    for fraction in (0.05, 0.10):
        ax.axvline(fraction * total / 1e6, color="grey", linestyle=":", linewidth=0.8)
        ax.annotate(f"{fraction:.0%} of N_mf", (fraction * total / 1e6, 0.02), fontsize=7, rotation=90)
    ax.axhline(TRACKING_TARGET, color="grey", linestyle="--", linewidth=0.8)
    ax.set(
        xscale="log",
        xlabel="physics samples behind the policy (M, log)",
        ylabel="physics tracking",
        title="MBPO-PPO against model-free PPO",
        ylim=(0, 1),
    )
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(0.0, -0.2))
    ax_falls.set(
        xscale="log", xlabel="physics samples behind the policy (M, log)", ylabel="falls in 54 episodes", title="falls"
    )
    fig.tight_layout()
    png, table = args.out.with_suffix(".png"), args.out.with_suffix(".csv")
    png.parent.mkdir(parents=True, exist_ok=True)
    save_png(fig, png, dpi=110, bbox_inches="tight")
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=list(rows[0]))
    writer.writeheader()
    writer.writerows(rows)
    atomic_write(table, lambda tmp: Path(tmp).write_text(text.getvalue()))
    print(f"N_mf {total:,}; wrote {png} and {table}")
    for label in labels:
        best = max((r for r in rows if r["run"] == label), key=lambda r: r["tracking"])
        print(
            f"{label}: best tracking {best['tracking']:.3f} ({best['falls']} falls) at iteration "
            f"{best['iteration']}, {best['physics_samples']:,} physics samples "
            f"({best['fraction_of_n_mf']:.1%} of N_mf)"
        )


if __name__ == "__main__":
    main()

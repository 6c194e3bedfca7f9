"""The learning curve of a resumable PPO run: the tracking score of every snapshot against env steps and wall time.

    python benchmarks/ppo_curve.py --run-dir runs/ppo_physics [--env Go2-MuJoCo-v0] [--seeds 3] [--threshold 0.8]
                                   [--every N] [--out DIR]
    python benchmarks/ppo_curve.py --run-dir runs/imagC --trained-in imagination --checkpoint CKPT --reset-data H5

Scores each `RUN/snapshots/step_N.zip` in physics on the scoring command set (`rwm-gym score`'s), once: results are
kept in `<out>/curve.csv` and reused when the script runs again (a running training adds snapshots). The zero-action
floor is scored once. Writes `<out>/curve.csv`, `<out>/curve.png` and `<out>/curve.json` with N_mf, the env steps of the
first snapshot at or above `--threshold` with at most `--max-falls` falls. With `--checkpoint` every snapshot is also
scored inside that world model (from `--reset-data`'s histories): where the two curves part, the policy exploits the
model.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
from pathlib import Path

from rwm_gym.atomic import atomic_write, save_png, write_json
from rwm_gym.registration import resolve_spec
from rwm_gym.rl.score import score
from rwm_gym.rl.training_run import TrainingRun

FIELDS = [
    "timesteps",
    "wall_s",
    "tracking",
    "return",
    "falls",
    "episodes",
    "loadavg",
    "imagined_tracking",
    "imagined_falls",
]


def wall_at(run: TrainingRun, timesteps: int) -> float | None:
    """Training wall time (s, summed over restarts) when the run had taken `timesteps` steps, from log.csv."""
    if not run.log_path.is_file():
        return None
    with run.log_path.open() as f:
        rows = [r for r in csv.DictReader(f) if int(r["timesteps"]) <= timesteps]
    return float(rows[-1]["total_wall_s"]) if rows else 0.0


def spaced(snapshots: list[Path], every: int) -> list[Path]:
    """The first snapshot at or past each multiple of `every` env steps (all of them with `every` 0): a curve of a
    long run with frequent snapshots at the cost of a few physics scores."""
    kept, last = [], None
    for snapshot in snapshots:
        bucket = int(snapshot.stem.split("_")[1]) // every if every else snapshot
        if bucket != last:
            kept.append(snapshot)
            last = bucket
    return kept


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run-dir", type=Path, required=True)
    parser.add_argument("--env", default="anymal_d", help="the physics env id or spec the run is scored on")
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--threshold", type=float, default=0.8)
    parser.add_argument("--max-falls", type=int, default=1)
    parser.add_argument("--out", type=Path, default=None, help="default: RUN/curve")
    parser.add_argument(
        "--every",
        type=int,
        default=0,
        help="score only the first snapshot at or past each multiple of this many env steps (0: all)",
    )
    parser.add_argument(
        "--trained-in",
        choices=("physics", "imagination"),
        default="physics",
        help="where the run trained (labels the plot: physics or imagined env steps)",
    )
    parser.add_argument(
        "--checkpoint",
        default=None,
        help="also score every snapshot inside this world model (imagined tracking and falls)",
    )
    parser.add_argument(
        "--reset-data",
        default=None,
        help="with --checkpoint: histories the imagined episodes start from (default: the model's)",
    )
    args = parser.parse_args()
    run = TrainingRun(args.run_dir)
    out = args.out or run.folder / "curve"
    out.mkdir(parents=True, exist_ok=True)
    table = out / "curve.csv"
    rows = list(csv.DictReader(table.open())) if table.is_file() else []
    done = {int(r["timesteps"]): r for r in rows}
    for snapshot in spaced(run.snapshot_files(), args.every):
        steps = int(snapshot.stem.split("_")[1])
        row = done.get(steps)
        if row is None:
            e = score(str(snapshot), seeds=args.seeds, spec=args.env)
            row = {
                "timesteps": steps,
                "wall_s": wall_at(run, steps),
                "tracking": round(e.tracking, 4),
                "return": round(e.episode_return, 3),
                "falls": e.falls,
                "episodes": e.episodes,
                "loadavg": os.getloadavg()[0],
            }
            rows.append(row)
            print(
                f"{snapshot.name}: tracking {e.tracking:.3f}, return {e.episode_return:.2f}, "
                f"falls {e.falls}/{e.episodes}",
                flush=True,
            )
        if args.checkpoint and not row.get("imagined_tracking"):
            e = score(
                str(snapshot), seeds=args.seeds, checkpoint=args.checkpoint, reset_data=args.reset_data, spec=args.env
            )
            row.update(imagined_tracking=round(e.tracking, 4), imagined_falls=e.falls)
            print(
                f"{snapshot.name} in the world model: tracking {e.tracking:.3f}, falls {e.falls}/{e.episodes}",
                flush=True,
            )
        atomic_write(table, lambda tmp: _write_csv(tmp, rows))
    rows.sort(key=lambda r: int(r["timesteps"]))
    floor_path = out / "floor.json"
    if floor_path.is_file():
        floor = json.loads(floor_path.read_text())
    else:
        e = score("zero", seeds=args.seeds, spec=args.env)
        floor = {"tracking": e.tracking, "return": e.episode_return, "falls": e.falls}
        write_json(floor_path, floor)
    reached = [r for r in rows if float(r["tracking"]) >= args.threshold and int(r["falls"]) <= args.max_falls]
    n_mf = int(reached[0]["timesteps"]) if reached else None
    best = max(rows, key=lambda r: float(r["tracking"])) if rows else None
    write_json(
        out / "curve.json",
        {
            "run_dir": str(run.folder),
            "threshold": args.threshold,
            "max_falls": args.max_falls,
            "n_mf": n_mf,
            "floor": floor,
            "best": best,
            "rows": rows,
        },
    )
    _plot(rows, floor, args.threshold, out / "curve.png", args.trained_in, resolve_spec(args.env))
    print(
        f"floor (zero action): tracking {floor['tracking']:.3f}; best snapshot: {best}; "
        f"N_mf (tracking >= {args.threshold}, falls <= {args.max_falls}): {n_mf}"
    )


def _write_csv(path: str, rows: list[dict]) -> None:
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=FIELDS)
        writer.writeheader()
        writer.writerows(rows)


def _plot(rows: list[dict], floor: dict, threshold: float, path: Path, trained_in: str = "physics", task=None) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = [int(r["timesteps"]) / 1e6 for r in rows]
    walls = [float(r["wall_s"] or 0) / 60 for r in rows]
    tracking = [float(r["tracking"]) for r in rows]
    imagined = [(x, float(r["imagined_tracking"])) for x, r in zip(steps, rows) if r.get("imagined_tracking")]
    fig, axes = plt.subplots(1, 2, figsize=(11, 4), sharey=True)
    floor_text = "stands still" if not floor.get("falls") else f"falls {floor['falls']} times"
    steps_label = f"{'imagined' if trained_in == 'imagination' else 'physics'} env steps (M)"
    for ax, x, label in ((axes[0], steps, steps_label), (axes[1], walls, "training wall time (min)")):
        ax.plot(x, tracking, "o-", label="PPO snapshot, in physics (falls in 54 beside it)")
        for xi, yi, r in zip(x, tracking, rows):
            ax.annotate(str(r["falls"]), (xi, yi), textcoords="offset points", xytext=(3, 4), fontsize=7)
        ax.axhline(floor["tracking"], color="0.5", ls="--", label=f"zero action ({floor_text})")
        ax.axhline(threshold, color="tab:green", ls=":", label=f"target {threshold}")
        ax.set_xlabel(label)
    if imagined:
        axes[0].plot(*zip(*imagined), "s--", color="tab:orange", label="the same, inside the world model")
    axes[0].set_ylabel("tracking score (physics unless said)")
    axes[0].legend()
    task = task or resolve_spec("anymal_d")
    fig.suptitle(
        f"PPO from scratch in imagination ({task.imagined_env_id}), scored in MuJoCo physics, {task.name}"
        if trained_in == "imagination"
        else f"model-free PPO in MuJoCo physics ({task.physics_env_id})"
    )
    fig.tight_layout()
    save_png(fig, path, dpi=100)


if __name__ == "__main__":
    main()

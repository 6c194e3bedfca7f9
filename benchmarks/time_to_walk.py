"""Time to walk: physics tracking of a policy learned from scratch in imagination, against training wall-clock minutes.

    python benchmarks/time_to_walk.py --recipe fast [--seeds 0 1 2] [--minutes 8] [--threads 2] [--out DIR]
    python benchmarks/time_to_walk.py --plot            # redraw the figure from every recipe's scored runs

For each seed the script trains a fresh policy with `rwm-gym ppo --run-dir` in the shipped world model with the
recipe's settings for `--minutes` of training wall time (snapshots every few rollouts), then scores the snapshot
nearest each whole minute (`--score-every`) in MuJoCo physics with `rwm-gym score`'s command set, beside the
zero-action floor. Training and scoring run one after the other, so scoring never slows the timed training.

Results go to DIR/<recipe>/seed_<k>/ (the run folder, curve.csv) and DIR/summary.json: per recipe and seed the
minutes and imagined steps of the first snapshot with tracking >= 0.80 and at most 2 of 54 falls (the quick start's
"walks"), with the load average during training; DIR/time_to_walk.png draws tracking against minutes, imagined
steps in the summary, one colour per recipe. The recipes are the `RECIPES` table below; the shipped recipe
(`reference`) is the shipped from-scratch recipe as it was trained; `fast` is what `examples/quickstart.py` runs.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from rwm_gym.atomic import save_png, write_json
from rwm_gym.resources import shipped_file

WALKS = {"tracking": 0.80, "max_falls": 2}
"""A snapshot walks at tracking >= 0.80 with at most 2 falls in the 54 scoring episodes."""

MODEL = "assets/checkpoints/anymal_d_rwm_cover.safetensors"
EPISODES = ["--episode-steps=50", "--torque-halt=0.95"]
PPO_SHARED = [
    *EPISODES,
    "--uncertainty-penalty=10.0",
    "--uncertainty-floor=0.02",
    "--uncertainty-halt=0.06",
    "--positive-reward-only",
    "--log-std-init=-1.0",
]
"""What every PPO recipe shares: the shipped from-scratch recipe's imagined episodes and policy start."""

HISTORY = ["--num-envs=1024", "--fall-tilt=30", "--command-from-history=0.5", "--matmul-precision=bfloat16"]
"""The history recipe's own options: 1024 robots, fall tilt 30, half the restarts commanded by their history."""

RECIPES: dict[str, tuple[str, str, list[str]]] = {
    "reference": ("PPO, 4096 envs, fp32, 1 thread (the shipped recipe)", "ppo", ["--num-envs=4096"]),
    "fast": (
        "PPO, 4096 envs, bf16 products (the quick start)",
        "ppo",
        ["--num-envs=4096", "--matmul-precision=bfloat16"],
    ),
    "envs1024": (
        "PPO, 1024 envs, fall tilt 30, bf16",
        "ppo",
        ["--num-envs=1024", "--fall-tilt=30", "--matmul-precision=bfloat16"],
    ),
    "envs1024_symmetry": (
        "PPO, 1024 envs, fall tilt 30, bf16, mirror augmentation",
        "ppo",
        ["--num-envs=1024", "--fall-tilt=30", "--matmul-precision=bfloat16", "--symmetry"],
    ),
    "envs4096_symmetry": (
        "PPO, 4096 envs, bf16, mirror augmentation",
        "ppo",
        ["--num-envs=4096", "--matmul-precision=bfloat16", "--symmetry"],
    ),
    "envs512": ("PPO, 512 envs, fall tilt 30", "ppo", ["--num-envs=512", "--fall-tilt=30"]),
    "envs256": ("PPO, 256 envs, fall tilt 30", "ppo", ["--num-envs=256", "--fall-tilt=30"]),
    "envs1024_gsde": (
        "PPO, 1024 envs, fall tilt 30, bf16, gSDE exploration",
        "ppo",
        [
            "--num-envs=1024",
            "--fall-tilt=30",
            "--matmul-precision=bfloat16",
            "--use-sde",
            "--log-std-init=-3.3",
            "--target-kl=0.05",
        ],
    ),
    "history": (
        "PPO, 1024 envs, fall tilt 30, half the restarts commanded by their history, bf16 model",
        "ppo",
        HISTORY,
    ),
    "history_bf16_update": (
        "the same with PPO's update in bf16",
        "ppo",
        [
            "--num-envs=1024",
            "--fall-tilt=30",
            "--command-from-history=0.5",
            "--matmul-precision=bfloat16",
            "--update-precision=bfloat16",
        ],
    ),
    "history_ep100": (
        "the history recipe with 2-s imagined episodes",
        "ppo",
        [*HISTORY, "--episode-steps=100"],
    ),
    "history_ep200": (
        "the history recipe with 4-s imagined episodes",
        "ppo",
        [*HISTORY, "--episode-steps=200"],
    ),
    "history_own_data": (
        "the history recipe in the model taught its own policies' physics episodes",
        "ppo",
        HISTORY,
    ),
    "history_taught": (
        "the history recipe in the model taught two rounds of its own policies' episodes (the quick start)",
        "ppo",
        HISTORY,
    ),
    "history_taught_3epochs": (
        "the same with 3 epochs per update instead of 5",
        "ppo",
        [*HISTORY, "--n-epochs=3"],
    ),
    "shac": (
        "SHAC, 1024 envs, horizon 16, fall tilt 30",
        "shac",
        ["--num-envs=1024", "--horizon=16", "--fall-tilt=30"],
    ),
}
"""name -> (what, learner, its options beyond the shared ones)."""

RECIPE_MODELS = {
    "history_own_data": "assets/checkpoints/anymal_d_rwm_cover_history.safetensors",
    "history_taught": "assets/checkpoints/anymal_d_rwm_taught.safetensors",
    "history_taught_3epochs": "assets/checkpoints/anymal_d_rwm_taught.safetensors",
}
"""Recipes trained in another world model than MODEL, each one MBPO data step further
(`examples/make_coverage_model.py`: 32 physics episodes of up to 1000 steps per policy at action noise 0 and 0.26,
then a 600-step fine-tune). `anymal_d_rwm_cover_history`: `MODEL` taught four policies of the history recipes (seed 0
of `history` at 14.0 M steps, seeds 0 / 1 / 2 of `history_ep100` at 10.3 / 13.5 / 11.3 M). `anymal_d_rwm_taught`: that
model taught four policies of `history_own_data` (seed 0 at 9.3 M, seed 1 at 10.3 and 11.3 M, seed 2 at 10.3 M)."""


def train(recipe: str, seed: int, minutes: float, threads: int, run_dir: Path, snapshot_every: int) -> None:
    """One resumable training run of `minutes` of wall time (a killed run continues where it stopped)."""
    _, learner, options = RECIPES[recipe]
    shared = [*PPO_SHARED, "--in", "imagination", "--no-eval"] if learner == "ppo" else EPISODES
    command = [
        sys.executable,
        "-m",
        "rwm_gym.cli",
        learner,
        "--checkpoint",
        str(shipped_file(RECIPE_MODELS.get(recipe, MODEL))),
        *shared,
        *options,
        "--timesteps",
        str(10**9),
        "--minutes",
        str(minutes),
        "--run-dir",
        str(run_dir),
        "--save-every",
        str(snapshot_every),
        "--snapshot-every",
        str(snapshot_every),
        "--threads",
        str(threads),
        "--seed",
        str(seed),
        "--out",
        str(run_dir / "policy.zip"),
    ]
    env = {**os.environ, "OMP_NUM_THREADS": str(threads)}
    subprocess.run(command, check=True, env=env)


def log_rows(run_dir: Path) -> list[dict]:
    with (run_dir / "log.csv").open() as f:
        return list(csv.DictReader(f))


def snapshots_by_minute(run_dir: Path, every: float) -> list[tuple[float, int, Path]]:
    """(training minutes, imagined steps, snapshot) of the last snapshot at or before each multiple of `every`
    minutes, and the final one."""
    wall = {int(r["timesteps"]): float(r["total_wall_s"]) / 60 for r in log_rows(run_dir)}
    snaps = sorted(
        (
            (wall.get(int(p.stem.split("_")[1]), 0.0), int(p.stem.split("_")[1]), p)
            for p in (run_dir / "snapshots").glob("step_*.zip")
        ),
        key=lambda t: t[1],
    )
    if not snaps:
        return []
    marks = [every * k for k in range(1, int(snaps[-1][0] // every) + 1)]
    picked = {max((s for s in snaps if s[0] <= mark), key=lambda s: s[1], default=None) for mark in marks}
    return sorted((s for s in picked | {snaps[-1]} if s is not None), key=lambda s: s[1])


def score_run(run_dir: Path, every: float, seeds: int) -> list[dict]:
    """Physics scores of the picked snapshots, kept in RUN/curve.csv and reused."""
    from rwm_gym.rl.score import score

    table = run_dir / "curve.csv"
    rows = {int(r["timesteps"]): r for r in csv.DictReader(table.open())} if table.is_file() else {}
    for minute, steps, path in snapshots_by_minute(run_dir, every):
        if steps not in rows:
            result = score(str(path), seeds=seeds)
            rows[steps] = {
                "minutes": round(minute, 3),
                "timesteps": steps,
                "tracking": round(result.tracking, 4),
                "falls": result.falls,
                "episodes": result.episodes,
            }
            print(
                f"{run_dir.name} {minute:5.2f} min {steps / 1e6:6.2f} M steps: tracking {result.tracking:.3f}, "
                f"falls {result.falls}/{result.episodes}",
                flush=True,
            )
            with table.open("w", newline="") as f:
                writer = csv.DictWriter(f, fieldnames=["minutes", "timesteps", "tracking", "falls", "episodes"])
                writer.writeheader()
                writer.writerows(sorted(rows.values(), key=lambda r: int(r["timesteps"])))
    return sorted(rows.values(), key=lambda r: int(r["timesteps"]))


def first_walking(rows: list[dict]) -> dict | None:
    return next(
        (r for r in rows if float(r["tracking"]) >= WALKS["tracking"] and int(r["falls"]) <= WALKS["max_falls"]), None
    )


def summarize(out: Path) -> dict:
    """Every scored run under `out`: its curve, the first walking snapshot, the training load average."""
    summary: dict = {"walks": WALKS, "recipes": {}}
    for recipe_dir in sorted(p for p in out.iterdir() if p.is_dir() and p.name in RECIPES):
        runs = {}
        for run_dir in sorted(recipe_dir.glob("seed_*")):
            table = run_dir / "curve.csv"
            if not table.is_file():
                continue
            rows = list(csv.DictReader(table.open()))
            meta = (
                json.loads((run_dir / "benchmark.json").read_text()) if (run_dir / "benchmark.json").is_file() else {}
            )
            walking = first_walking(rows)
            runs[run_dir.name] = {
                **meta,
                "curve": rows,
                "walks_at_minutes": None if walking is None else float(walking["minutes"]),
                "walks_at_steps": None if walking is None else int(walking["timesteps"]),
            }
        what, learner, options = RECIPES[recipe_dir.name]
        summary["recipes"][recipe_dir.name] = {"what": what, "learner": learner, "options": options, "seeds": runs}
    return summary


def plot(summary: dict, floor: float | None, path: Path) -> Path:
    """Tracking against training minutes (left) and imagined steps (right), one colour per recipe, one line per
    seed; the right panel also draws the shipped recipe's measured 40 M-step curves (from its JSON)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from rwm_gym.resources import assets_dir

    fig, axes = plt.subplots(1, 2, figsize=(13, 4.8), sharey=True)
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for i, (name, recipe) in enumerate(summary["recipes"].items()):
        for j, run in enumerate(recipe["seeds"].values()):
            rows = run["curve"]
            label = f"{name}: {recipe['what']}" if j == 0 else None
            tracking = [float(r["tracking"]) for r in rows]
            axes[0].plot(
                [float(r["minutes"]) for r in rows],
                tracking,
                "o-",
                color=colours[i % len(colours)],
                alpha=0.8,
                label=label,
            )
            axes[1].plot(
                [int(r["timesteps"]) / 1e6 for r in rows], tracking, "o-", color=colours[i % len(colours)], alpha=0.8
            )
    shipped = json.loads((assets_dir() / "policies" / "anymal_d_ppo_imagination.json").read_text())
    for j, run in enumerate(shipped["seeds"]):
        axes[1].plot(
            [r["timesteps"] / 1e6 for r in run["curve"]],
            [r["tracking"] for r in run["curve"]],
            ":",
            color="0.3",
            label="shipped recipe to 40 M steps (its JSON)" if j == 0 else None,
        )
    for ax in axes:
        if floor is not None:
            ax.axhline(floor, color="0.5", ls="--")
        ax.axhline(WALKS["tracking"], color="tab:green", ls=":")
    axes[0].set_xlabel("training wall time (min; load average in summary.json)")
    axes[1].set_xlabel("imagined env steps (M)")
    axes[0].set_ylabel("tracking score in physics")
    fig.suptitle(
        "Learning from scratch in the shipped world model, scored in MuJoCo (ANYmal D), one line per seed; "
        "dashed: standing still, dotted green: walks"
    )
    fig.legend(fontsize=8, loc="lower center", ncol=3)
    fig.tight_layout(rect=(0, 0.12, 1, 1))
    return save_png(fig, path, dpi=100)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--recipe", choices=sorted(RECIPES), help="what to train (see RECIPES)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--minutes", type=float, default=8.0, help="training wall time per seed")
    parser.add_argument("--threads", type=int, default=2, help="torch threads of the training run")
    parser.add_argument("--snapshot-every", type=int, default=10, help="rollouts between snapshots")
    parser.add_argument("--score-every", type=float, default=1.0, help="minutes between scored snapshots")
    parser.add_argument("--score-seeds", type=int, default=3, help="physics seeds per scoring command")
    parser.add_argument("--out", type=Path, default=Path("runs/time_to_walk"))
    parser.add_argument("--plot", action="store_true", help="only redraw the figure and summary")
    args = parser.parse_args()
    if not args.plot:
        if args.recipe is None:
            parser.error("--recipe is required unless --plot")
        for seed in args.seeds:
            run_dir = args.out / args.recipe / f"seed_{seed}"
            if not (run_dir / "state.json").is_file() or not (run_dir / "benchmark.json").is_file():
                run_dir.mkdir(parents=True, exist_ok=True)
                load_before, started = os.getloadavg()[0], time.monotonic()
                train(args.recipe, seed, args.minutes, args.threads, run_dir, args.snapshot_every)
                write_json(
                    run_dir / "benchmark.json",
                    {
                        "seed": seed,
                        "threads": args.threads,
                        "minutes_budget": args.minutes,
                        "process_s": round(time.monotonic() - started, 1),
                        "loadavg_before": load_before,
                        "loadavg_after": os.getloadavg()[0],
                        "cpu": _cpu_name(),
                    },
                )
            score_run(run_dir, args.score_every, args.score_seeds)
    summary = summarize(args.out)
    floor_path = args.out / "floor.json"
    if not floor_path.is_file():
        from rwm_gym.rl.score import score, zero_policy

        write_json(floor_path, {"tracking": score(zero_policy, seeds=args.score_seeds).tracking})
    floor = json.loads(floor_path.read_text())["tracking"]
    summary["floor"] = floor
    write_json(args.out / "summary.json", summary)
    figure = plot(summary, floor, args.out / "time_to_walk.png")
    for name, recipe in summary["recipes"].items():
        times = [run["walks_at_minutes"] for run in recipe["seeds"].values()]
        print(
            f"{name:10s} {recipe['what']}: walks at "
            + ", ".join("not within the budget" if t is None else f"{t:.1f} min" for t in times)
        )
    print(f"wrote {args.out / 'summary.json'} and {figure}")
    return 0


def _cpu_name() -> str:
    try:
        return next(line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name"))
    except (OSError, StopIteration):
        return "unknown"


if __name__ == "__main__":
    sys.exit(main())

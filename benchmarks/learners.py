"""The learner table: PPO, SHAC and a Dreamer-style actor-critic, each from scratch in the same world model, at equal
imagined steps and equal wall time, scored in physics, and where each breaks.

    python benchmarks/learners.py --out runs/learners --seeds 0 1 2 --imagined-steps 11796480 --minutes 12 --threads 1
    python benchmarks/learners.py --out runs/learners --plot          # the table and figure from the runs so far

Each (learner, seed) trains with its own command (`rwm-gym ppo --in imagination`, `rwm-gym shac`, `rwm-gym dreamer`)
in OUT/<learner>_s<seed>, all with the same imagined episodes (1 s from real histories, a fall at 30 degrees of tilt,
the torque halt, step rewards clipped at 0, initial log std -1) and the same budget: it stops at `--imagined-steps`
or at `--minutes` of training, whichever comes first (the runs resume: the same command continues them). Each final
policy is then scored twice on the tracking score's episodes: in physics (MuJoCo) and inside the world model it
learned in. Where each breaks:

- *gradient norms*: the actor's gradient norm per update (SHAC and the Dreamer-style learner log it; SB3's PPO clips
  its gradients without logging them, so its approximate KL per rollout stands in);
- *imagined against physics*: the same policy's return and tracking in the model and in physics;
- *exploited states*: the scoring commands on which the policy falls in physics but not in the model (it learned to
  walk where the model is wrong).

Writes OUT/learners.json (every run, its scores and statistics), OUT/learners.md (one table) and OUT/learners.png
(one figure: physics against in-model tracking, and the actor's gradient norm against imagined steps).
"""

from __future__ import annotations

import argparse
import csv
import json
import statistics
import sys
import time
from pathlib import Path

LEARNERS = ("ppo", "shac", "dreamer")
"""The learners compared, each by its `rwm-gym` command."""

SHARED = ["--episode-steps=50", "--fall-tilt=30", "--torque-halt=0.95"]
"""Imagined episodes every learner trains in (the options all three steppers implement)."""

DEFAULT_CHECKPOINT = "assets/checkpoints/anymal_d_rwm_taught.safetensors"
"""The quick start's world model."""


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, required=True, help="folder of the runs and the table")
    parser.add_argument("--learners", nargs="+", choices=LEARNERS, default=list(LEARNERS))
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--imagined-steps", type=int, default=11_796_480, help="each run's budget in imagined steps")
    parser.add_argument("--minutes", type=float, default=12.0, help="each run's budget in minutes of training")
    parser.add_argument("--checkpoint", default=DEFAULT_CHECKPOINT, help="the world model every learner trains in")
    parser.add_argument("--num-envs", type=int, default=1024, help="imagined robots of every learner")
    parser.add_argument("--horizon", type=int, default=16, help="SHAC's and the Dreamer-style learner's horizon")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--score-seeds", type=int, default=3, help="episodes per scoring command (3: the score)")
    parser.add_argument("--score-steps", type=int, default=None, help="policy steps per episode (default 20 s)")
    parser.add_argument("--plot", action="store_true", help="only write the table and figure from the runs so far")
    args = parser.parse_args(argv)
    if args.imagined_steps < 1 or args.minutes <= 0 or args.num_envs < 1 or args.score_seeds < 1:
        parser.error("--imagined-steps, --minutes, --num-envs and --score-seeds must be positive")
    return args


def checkpoint_path(name: str) -> str:
    """A repository path ("assets/...") wherever the data folders live, else the path as given."""
    from rwm_gym.resources import shipped_file

    return str(shipped_file(name)) if name.startswith("assets/") else name


def command(learner: str, seed: int, args: argparse.Namespace, run_dir: Path) -> list[str]:
    """The `rwm-gym` argv that trains one run."""
    budget = ["--timesteps", str(args.imagined_steps), "--minutes", str(args.minutes)]
    common = [*SHARED, f"--num-envs={args.num_envs}", "--checkpoint", checkpoint_path(args.checkpoint), *budget]
    common += ["--run-dir", str(run_dir), "--seed", str(seed), "--threads", str(args.threads)]
    common += ["--out", str(run_dir / "policy.zip")]
    if learner == "ppo":
        return ["ppo", "--in", "imagination", *common, "--positive-reward-only", "--log-std-init=-1.0", "--no-eval"]
    if learner == "shac":
        return ["shac", *common, f"--horizon={args.horizon}"]
    return ["dreamer", *common, f"--horizon={args.horizon}", "--score-seeds=0"]


def train_and_score(learner: str, seed: int, args: argparse.Namespace) -> dict:
    """One run: trained (or continued), then its final policy scored in physics and in the model (cached)."""
    from rwm_gym.cli import main as cli

    run_dir = args.out / f"{learner}_s{seed}"
    started = time.monotonic()
    code = cli(command(learner, seed, args, run_dir))
    if code:
        raise SystemExit(f"{learner} seed {seed}: rwm-gym exited with {code}")
    scores = run_dir / "scores.json"
    state = json.loads((run_dir / "state.json").read_text())
    if not scores.is_file() or json.loads(scores.read_text())["timesteps"] != state["timesteps"]:
        from rwm_gym.atomic import write_json

        write_json(scores, {"timesteps": state["timesteps"], **score_both(run_dir / "policy.zip", args)})
    print(f"{learner} seed {seed}: {state['timesteps']:,} steps, {time.monotonic() - started:.0f} s in this call")
    return summarize_run(learner, seed, run_dir)


def score_both(policy: Path, args: argparse.Namespace) -> dict:
    """The policy's tracking episodes in physics and in the world model, and the commands it exploits."""
    from rwm_gym.model.checkpoint import read_meta
    from rwm_gym.rl.score import score

    checkpoint = checkpoint_path(args.checkpoint)
    spec = read_meta(checkpoint).spec
    physics = score(str(policy), seeds=args.score_seeds, steps=args.score_steps, spec=spec)
    model = score(str(policy), seeds=args.score_seeds, steps=args.score_steps, spec=spec, checkpoint=checkpoint)
    exploited = [
        list(p.command) for p, m in zip(physics.commands, model.commands, strict=True) if p.falls and not m.falls
    ]
    return {"physics": brief(physics), "model": brief(model), "exploited_commands": exploited}


def brief(evaluation) -> dict:
    return {
        "tracking": evaluation.tracking,
        "return": evaluation.episode_return,
        "falls": evaluation.falls,
        "episodes": evaluation.episodes,
    }


def log_rows(run_dir: Path) -> list[dict]:
    path = run_dir / "log.csv"
    return list(csv.DictReader(path.open())) if path.is_file() else []


def summarize_run(learner: str, seed: int, run_dir: Path) -> dict:
    """A run's row of the table: budget used, scores, and where it breaks."""
    state = json.loads((run_dir / "state.json").read_text())
    scores = json.loads((run_dir / "scores.json").read_text())
    rows = log_rows(run_dir)
    grads = [float(r["actor_grad_norm"]) for r in rows if r.get("actor_grad_norm")]
    kl = [float(r["approx_kl"]) for r in rows if r.get("approx_kl") not in (None, "")]
    return {
        "learner": learner,
        "seed": seed,
        "imagined_steps": int(state["timesteps"]),
        "wall_min": float(state.get("wall_s", 0.0)) / 60,
        **scores,
        "actor_grad_norm": None if not grads else {"median": statistics.median(grads), "max": max(grads)},
        "grad_curve": [[int(r["timesteps"]), float(r["actor_grad_norm"])] for r in rows if r.get("actor_grad_norm")],
        "approx_kl_median": statistics.median(kl) if kl else None,
    }


def markdown(runs: list[dict]) -> str:
    """One table: a row per run."""
    head = (
        "| learner | seed | imagined steps | training min | physics tracking (falls) | in-model tracking (falls) "
        "| physics / in-model return | exploited commands | actor grad norm, median / max |\n"
        "|---|---|---|---|---|---|---|---|---|\n"
    )
    lines = []
    for r in runs:
        p, m, g = r["physics"], r["model"], r["actor_grad_norm"]
        grad = f"{g['median']:.3g} / {g['max']:.3g}" if g else f"- (PPO: KL {r['approx_kl_median'] or 0:.3g})"
        lines.append(
            f"| {r['learner']} | {r['seed']} | {r['imagined_steps'] / 1e6:.2f} M | {r['wall_min']:.1f} "
            f"| {p['tracking']:.3f} ({p['falls']}/{p['episodes']}) "
            f"| {m['tracking']:.3f} ({m['falls']}/{m['episodes']}) "
            f"| {p['return']:.2f} / {m['return']:.2f} | {len(r['exploited_commands'])} | {grad} |"
        )
    return head + "\n".join(lines) + "\n"


def plot(runs: list[dict], path: Path) -> None:
    """Physics against in-model tracking per run (below the diagonal: the model exploited), and the actor's gradient
    norm against imagined steps."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from rwm_gym.atomic import save_png

    colours = dict(zip(LEARNERS, ("tab:blue", "tab:orange", "tab:green"), strict=True))
    markers = dict(zip(LEARNERS, ("o", "s", "^"), strict=True))  # distinct shapes: runs that stand overlap
    fig, (left, right) = plt.subplots(1, 2, figsize=(12, 4.5))
    for learner in LEARNERS:
        mine = [r for r in runs if r["learner"] == learner]
        if not mine:
            continue
        left.scatter(
            [r["model"]["tracking"] for r in mine],
            [r["physics"]["tracking"] for r in mine],
            color=colours[learner],
            marker=markers[learner],
            s=70 - 20 * LEARNERS.index(learner),
            alpha=0.8,
            label=learner,
        )
        for r in mine:
            if r["grad_curve"]:
                steps, norms = zip(*r["grad_curve"], strict=True)
                right.plot([s / 1e6 for s in steps], norms, color=colours[learner], alpha=0.7, lw=0.8)
    left.plot([0, 1], [0, 1], color="0.6", ls="--", lw=0.8)
    left.set_xlabel("tracking inside the world model")
    left.set_ylabel("tracking in physics")
    left.set_title("the same policy in the model and in physics")
    left.legend()
    right.set_yscale("log")
    right.set_xlabel("imagined steps (M)")
    right.set_ylabel("actor gradient norm (before clipping)")
    right.set_title("SHAC (orange) and Dreamer-style (green) gradients")
    fig.tight_layout()
    save_png(fig, path, dpi=100)


def write_outputs(out: Path) -> list[dict]:
    """learners.json, .md and .png from every finished run in `out`."""
    from rwm_gym.atomic import write_json

    runs = []
    for run_dir in sorted(out.glob("*_s*")):
        learner, _, seed = run_dir.name.rpartition("_s")
        if learner in LEARNERS and (run_dir / "scores.json").is_file():
            runs.append(summarize_run(learner, int(seed), run_dir))
    if not runs:
        raise SystemExit(f"{out}: no scored run yet")
    write_json(out / "learners.json", {"runs": runs, "python": sys.version.split()[0]})
    (out / "learners.md").write_text(markdown(runs))
    plot(runs, out / "learners.png")
    return runs


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    if not args.plot:
        for seed in args.seeds:
            for learner in args.learners:
                train_and_score(learner, seed, args)
    runs = write_outputs(args.out)
    print(markdown(runs))
    print(f"wrote {args.out / 'learners.json'}, {args.out / 'learners.md'}, {args.out / 'learners.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Quick start: a policy learned from scratch inside the shipped world model, then judged in physics.

    pip install . && python examples/quickstart.py

1. PPO (`rwm-gym ppo`) trains a fresh policy in the world model `anymal_d_rwm_taught` with the recipe of
   `assets/policies/anymal_d_ppo_quickstart.json`: 1024 imagined ANYmal D robots stepped in one forward pass, 1 s
   episodes restarted from real histories (half of them commanded at the velocity their history moves at), a fall at
   30 degrees of tilt, the ensemble-disagreement penalty and halt, the torque halt; the world model's products in
   bfloat16 where the CPU has native bf16, on both cores. No physics sample is used.
2. The policy is scored in MuJoCo with `rwm-gym score`'s tracking score (18 commands x 3 seeds x 20 s; a fall scores 0
   for the rest of its episode), beside the standing-still floor and the shipped policies.
3. `curve.png` places this run on the recipe's measured seeds, and `walk.gif` shows the policy walking (needs offscreen
   GL, `MUJOCO_GL=egl`).

The recipe walks (tracking >= 0.80 with at most 2 falls in 54) at its default 15.9 M imagined steps on its three
measured seeds; `--recipe anymal_d_ppo_imagination` runs the 40 M-step recipe of the shipped 4096-robot policy instead.
`--robot go2` runs the same recipe in the Go2's shipped world model (`go2_ppo_quickstart.json`: its measured seeds,
the default the seed of its shipped policy).
`--checkpoint CKPT` trains in another world model of the task, e.g. an MLP one (`rwm-gym train --model mlp
--ensemble-size 5`: the recipe's penalty reads five heads; its products stay float32).
docs/results/time-to-walk.md has the measured times. Run the command again after an interruption to continue.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

ROBOT = "anymal_d"
"""The robot of the default recipe, assets/policies/ROBOT_ppo_quickstart.json: its settings, shipped policy and
measured seeds; the robot's physics teacher is ROBOT_ppo_physics.json beside it."""

WALKS = (0.80, 2)
"""(tracking, falls in 54): the policy walks at tracking >= 0.80 with at most 2 falls (the zero-action floor stands
at 0.23 with none)."""


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument(
        "--robot",
        default=ROBOT,
        help=f"the robot whose quick-start recipe runs, assets/policies/ROBOT_ppo_quickstart.json (default {ROBOT})",
    )
    parser.add_argument(
        "--recipe",
        default=None,
        help="a recipe JSON in assets/policies in place of --robot's (anymal_d_ppo_imagination: the 40 M-step one)",
    )
    parser.add_argument(
        "--timesteps", type=int, default=None, help="PPO budget in imagined steps (default: the recipe's)"
    )
    parser.add_argument("--seed", type=int, default=None, help="PPO's seed (default: the recipe's shipped policy's)")
    parser.add_argument(
        "--checkpoint",
        type=Path,
        default=None,
        help="another world model to train in, e.g. an MLP one (`rwm-gym train --model mlp`; default: the recipe's)",
    )
    parser.add_argument("--num-envs", type=int, default=None, help="imagined robots (default: the recipe's)")
    parser.add_argument("--score-seeds", type=int, default=3, help="physics episodes per scoring command")
    parser.add_argument("--score-steps", type=int, default=None, help="policy steps per scoring episode (default 20 s)")
    parser.add_argument("--device", default="cpu", help="where PPO and the world model run (cuda on a GPU)")
    parser.add_argument("--threads", default="2", help="torch CPU threads (1 on a machine busy with other jobs)")
    parser.add_argument(
        "--precision",
        choices=("bfloat16", "float32"),
        default=None,
        help="the world model's products (default: bfloat16 where the CPU has it, else float32)",
    )
    parser.add_argument("--out", type=Path, default=Path("quickstart"))
    parser.add_argument(
        "--video",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="write walk.gif (skipped with a note where offscreen GL is missing)",
    )
    args = parser.parse_args()
    os.environ.setdefault("OMP_NUM_THREADS", args.threads)  # before torch is imported
    import time

    from rwm_gym.cli import main as cli
    from rwm_gym.model.checkpoint import read_meta
    from rwm_gym.model.lineage import physics_rows, share_text
    from rwm_gym.resources import assets_dir, shipped_file
    from rwm_gym.rl.score import record_walk, score

    policies = assets_dir() / "policies"
    recipe_file = policies / f"{Path(args.recipe or f'{args.robot}_ppo_quickstart').stem}.json"
    if not recipe_file.is_file() or not from_scratch(recipe := json.loads(recipe_file.read_text())):
        known = sorted(p.stem for p in policies.glob("*.json") if from_scratch(json.loads(p.read_text())))
        given = f"--recipe {args.recipe}" if args.recipe else f"--robot {args.robot}"
        parser.error(f"{given}: no from-scratch recipe in {policies} (known: {', '.join(known)})")
    timesteps = args.timesteps or recipe["imagined_steps"]
    seed = recipe.get("seed", 0) if args.seed is None else args.seed
    num_envs = args.num_envs or recipe["ppo"]["num_envs"]
    checkpoint = args.checkpoint or shipped_file(recipe["world_model"]["checkpoint"])
    precision = args.precision or default_precision(args.device, read_meta(checkpoint).model_config.kind)
    print(
        f"PPO from scratch in {checkpoint.stem}: {num_envs} imagined "
        f"robots, {timesteps:,} steps, seed {seed}, {args.threads} threads, {precision} products"
    )
    started = time.monotonic()
    code = cli(
        [
            "ppo",
            "--in",
            "imagination",
            *ppo_options(recipe, checkpoint),
            f"--num-envs={num_envs}",
            "--matmul-precision",
            precision,
            "--timesteps",
            str(timesteps),
            "--run-dir",
            str(args.out / "run"),
            "--save-every",
            "5",
            "--snapshot-every",
            "24",
            "--device",
            args.device,
            "--threads",
            args.threads,
            "--seed",
            str(seed),
            "--no-eval",
            "--out",
            str(args.out / "policy.zip"),
        ]
    )
    if code:
        return code
    trained = time.monotonic() - started
    policy = args.out / "policy.zip"
    steps = json.loads((args.out / "run" / "state.json").read_text())["timesteps"]
    task = read_meta(checkpoint).spec
    result = score(str(policy), seeds=args.score_seeds, steps=args.score_steps, spec=task)
    robot = recipe_file.stem.rsplit("_ppo_", 1)[0]
    floor, teacher = recipe["score"]["floor"], json.loads((policies / f"{robot}_ppo_physics.json").read_text())
    print(f"this policy, in physics:  {score_text(result.tracking, result.falls, result.episodes)}")
    print(f"standing still (floor):   {score_text(floor['tracking'], floor['falls'], recipe['score']['episodes'])}")
    print(
        f"this recipe at {recipe['imagined_steps'] / 1e6:.0f} M steps: "
        f"{score_text(recipe['score']['tracking'], recipe['score']['falls'], recipe['score']['episodes'])} "
        f"(shipped: {policies / recipe['policy']})"
    )
    print(f"physics-trained teacher:  {score_text(teacher['score']['tracking'], teacher['score']['falls'], 54)}")
    rows, _ = physics_rows(checkpoint)
    print(
        f"physics samples behind the policy: {share_text(rows, task.physics_env_id)}; the policy saw none, its world "
        "model's lineage"
    )
    files = [policy, plot_curve(recipe, steps, result.tracking, floor["tracking"], args.out / "curve.png", task.name)]
    if args.video:
        try:
            files.append(record_walk(str(policy), args.out / "walk.gif", args.out / "walk.png", spec=task)[0])
        except Exception as error:  # no offscreen GL here: the score above still stands
            print(f"no video ({type(error).__name__}); set MUJOCO_GL=egl where libEGL is installed")
    print("files: " + ", ".join(str(f) for f in files))
    walks = walking(result.tracking, result.falls)
    print(
        ("VERDICT: it walks" if walks else "VERDICT: it does not walk yet")
        + f" after {steps / 1e6:.1f} M imagined steps in {trained / 60:.1f} min (walking: tracking >= {WALKS[0]}"
        f" with <= {WALKS[1]} falls)"
        + ("" if walks else "; a larger --timesteps continues this run (curve.png: the recipe's seeds)")
    )
    return 0


def walking(tracking: float, falls: int) -> bool:
    """Whether a policy's physics score walks (`WALKS`)."""
    return tracking >= WALKS[0] and falls <= WALKS[1]


def from_scratch(recipe: dict) -> bool:
    """Whether a shipped policy's JSON is a recipe the quick start runs: PPO in imagination with measured seeds."""
    return recipe.get("env", {}).get("where") == "imagination" and "seeds" in recipe and "ppo" in recipe


def default_precision(device: str, kind: str = "rwm") -> str:
    """bfloat16 where its products are fast (a CUDA device, or a CPU with AVX512-BF16 or AMX) for an RWM model (the
    only kind with bf16 products), else float32."""
    if kind != "rwm":
        return "float32"
    if device.startswith("cuda"):
        return "bfloat16"
    try:
        flags = next(line for line in open("/proc/cpuinfo") if line.startswith("flags")).split()
    except (OSError, StopIteration):
        return "float32"
    return "bfloat16" if {"avx512_bf16", "amx_bf16"} & set(flags) else "float32"


def score_text(tracking: float, falls: int, episodes: int) -> str:
    return f"tracking {tracking:.3f}, falls {falls}/{episodes}"


def ppo_options(recipe: dict, checkpoint: Path | None = None) -> list[str]:
    """`rwm-gym ppo` options of the recipe, read from its JSON (its numbers live there once), in `checkpoint`
    (default: the recipe's world model)."""
    from rwm_gym.resources import shipped_file

    options = ["--checkpoint", str(checkpoint or shipped_file(recipe["world_model"]["checkpoint"]))]
    for name, value in recipe["env"]["imagination"].items():
        if value is not None:  # reset_data None: the windows the checkpoint names
            options.append(f"--{name.replace('_', '-')}={value}")
    for name, value in recipe["ppo"].items():
        flag = f"--{name.replace('_', '-')}"
        if name == "num_envs":  # the quick start's --num-envs decides
            continue
        if isinstance(value, bool):
            options.append(flag if value else f"--no-{flag[2:]}")
        elif isinstance(value, list):
            options += [flag, *map(str, value)]
        else:
            options.append(f"{flag}={value}")
    return options


def plot_curve(recipe: dict, timesteps: int, tracking: float, floor: float, path: Path, robot: str) -> Path:
    """This run's point on the recipe's measured physics tracking against imagined steps (one line per seed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from rwm_gym.atomic import save_png

    fig, ax = plt.subplots(figsize=(8, 4.5))
    for run in recipe["seeds"]:
        ax.plot(
            [r["timesteps"] / 1e6 for r in run["curve"]],
            [r["tracking"] for r in run["curve"]],
            ".-",
            alpha=0.7,
            label=f"the recipe, seed {run['seed']}",
        )
    ax.plot([timesteps / 1e6], [tracking], "r*", markersize=14, label="this run")
    ax.axhline(floor, color="0.5", ls="--", label="standing still")
    ax.axhline(WALKS[0], color="tab:green", ls=":", label=f"walks ({WALKS[0]}, <= {WALKS[1]} falls)")
    ax.set_xlabel("imagined env steps (M)")
    ax.set_ylabel("tracking score in physics")
    ax.set_title(f"PPO from scratch in the shipped world model, scored in MuJoCo ({robot})")
    ax.legend(fontsize=8, loc="upper left")
    fig.tight_layout()
    save_png(fig, path, dpi=100)
    return path


if __name__ == "__main__":
    sys.exit(main())

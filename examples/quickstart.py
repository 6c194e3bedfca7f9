"""Quick start: a policy learned from scratch inside a shipped world model, then judged in physics.

    pip install . && python examples/quickstart.py

1. PPO (Stable-Baselines3 with RWM's settings: 128-128-128 ELU actor and critic, lr 1e-3 with a KL target) trains a
   fresh policy in the shipped coverage world model (`assets/checkpoints/anymal_d_rwm_cover.safetensors`: the default
   model fine-tuned by 25 MBPO iterations, then on the physics episodes of four policies trained from scratch in it,
   `examples/make_coverage_model.py`): 4096 imagined robots stepped in one forward pass, 1 s episodes that each restart
   from a real history, the RWM-U uncertainty penalty, step rewards clipped at 0 (`--positive-reward-only`: with
   negative steps PPO learns to end its episodes), episodes ended where a predicted joint torque reaches 95 % of the
   effort limit (`--torque-halt 0.95`: states the model's data barely covers) and an initial action std of 0.37. No
   cloning, no physics sample beyond the world model's own dataset. The run lives in `--out`/run: stop it at any time
   and run the same command again to continue; a larger `--timesteps` continues a finished run.
2. The policy is scored in physics (MuJoCo, `AnymalD-MuJoCo-v0`) with `rwm-gym score`'s tracking score (18 commands x
   3 seeds x 20 s, a fall scores 0 for the rest of its episode), beside the zero-action floor (standing still) and the
   shipped physics PPO policy's score.
3. The measured curve of the same recipe (three seeds to 40 M imagined steps, from the shipped policy's JSON; then the
   settings measured beside it, all in the MBPO model before its coverage fine-tune: dotted: the same recipe; dashed:
   without the torque halt; dash-dotted: 1024 envs; sparse dots: 1024 envs with `--fall-tilt 30`; dash-dot-dot:
   `--torque-halt 0.9`; dash-dash-dot: `--lr-anneal-fraction 0.25`) with this run's point on it (`curve.png`), the
   budget at which those seeds reached tracking 0.7, a GIF of the policy walking (`--video`, needs offscreen GL:
   `MUJOCO_GL=egl`) and a one-line verdict.

Written to `--out` (default `quickstart/`): run/ (resume point, snapshots, log.csv), policy.zip, curve.png, walk.gif
and walk.png. The default 2 M steps fit in 10 minutes on 2 CPU cores and only learn to stand (the recipe stands to about
12 M steps); the budget that walks is `--timesteps 40000000` (README: about 2 h on one CPU thread, 12 min on a GPU
with `--device cuda`).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

WALKING = 0.7
"""Tracking score a policy must reach to be called walking (the zero-action floor is 0.23, the scripted trot 0.63)."""


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--timesteps", type=int, default=2_000_000,
                        help="PPO budget in imagined env steps (2 M fits 10 min on 2 CPU cores; 40 M walks: README)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--num-envs", type=int, default=None,
                        help="imagined robots stepped together (default: the recipe's, from the shipped policy's JSON)")
    parser.add_argument("--device", default="cpu", help="where PPO and the world model run (cuda on a GPU)")
    parser.add_argument("--score-seeds", type=int, default=3, help="physics episodes per scoring command")
    parser.add_argument("--score-steps", type=int, default=None, help="policy steps per scoring episode (default 20 s)")
    parser.add_argument("--threads", default="1", help="torch CPU threads (default 1: fastest on a small shared CPU)")
    parser.add_argument("--out", type=Path, default=Path("quickstart"))
    parser.add_argument("--video", action=argparse.BooleanOptionalAction, default=True,
                        help="write walk.gif (skipped with a note where offscreen GL is missing)")
    args = parser.parse_args()
    os.environ.setdefault("OMP_NUM_THREADS", args.threads)  # before torch is imported
    from rwm_gym.cli import main as cli
    from rwm_gym.resources import assets_dir
    from rwm_gym.rl.score import record_walk, score, summary_line, zero_policy

    policies = assets_dir() / "policies"
    scratch = json.loads((policies / "anymal_d_ppo_imagination.json").read_text())
    num_envs = args.num_envs or scratch["ppo"]["num_envs"]
    code = cli(["ppo", "--in", "imagination", *recipe(scratch), "--num-envs", str(num_envs),
                "--timesteps", str(args.timesteps), "--run-dir", str(args.out / "run"),
                "--save-every", "5", "--snapshot-every", "20", "--device", args.device, "--threads", args.threads,
                "--seed", str(args.seed), "--no-eval", "--out", str(args.out / "policy.zip")])
    if code:
        return code
    policy = args.out / "policy.zip"
    options = dict(seeds=args.score_seeds, steps=args.score_steps)
    result, floor = score(str(policy), **options), score(zero_policy, **options)
    shipped = json.loads((policies / "anymal_d_ppo_physics.json").read_text())["score"]
    steps = json.loads((args.out / "run" / "state.json").read_text())["timesteps"]  # whole rollouts: >= --timesteps
    print(summary_line(f"this policy (PPO in imagination, {steps:,} imagined steps)", result))
    print(summary_line("zero-action floor (stands still)", floor))
    print(f"shipped physics PPO policy (36 M physics steps): {json_score(shipped)}")
    mbpo = json.loads((policies / "anymal_d_mbpo_ppo.json").read_text())
    rows = mbpo["physics_samples"]
    print(f"shipped MBPO-PPO policy (trained in imagination, {rows['counted']:,} physics samples: {rows['loop']:,} in "
          f"its loop, {rows['before_the_loop']:,} before it): {json_score(mbpo['score'])}")
    random_start = json.loads((policies / "anymal_d_mbpo_ppo_random_data.json").read_text())
    rows = random_start["physics_samples"]
    print(f"shipped MBPO-PPO policy from random-action data ({rows['counted']:,} physics samples, "
          f"{rows['fraction_of_n_mf']:.1%} of the physics policy's to 0.80): {json_score(random_start['score'])}")
    print(f"shipped policy from scratch in imagination (this recipe, {scratch['imagined_steps']:,} imagined steps, "
          f"seed {scratch['seed']}): {json_score(scratch['score'])}")
    episodes = scratch["score"]["episodes"]
    for setting, seeds in measured_recipes(scratch):
        for run in seeds:
            curve = run["curve"]
            reached = next((r["timesteps"] for r in curve if r["tracking"] >= WALKING), None)
            peak = max(curve, key=lambda r: r["tracking"])
            print(f"  the recipe at {setting}, seed {run['seed']}: tracking {run['tracking']:.3f} with "
                  f"{run['falls']}/{episodes} falls at {run['imagined_steps'] / 1e6:.1f} M steps (best snapshot "
                  f"{peak['tracking']:.3f} at {peak['timesteps'] / 1e6:.1f} M); tracking >= {WALKING} first at "
                  + (f"{reached / 1e6:.1f} M steps" if reached is not None else "no snapshot"))
    curve = plot_curve(scratch, num_envs, steps, result.tracking, floor.tracking, args.out / "curve.png")
    print(f"curve: {curve}")
    if args.video:
        try:
            gif, _ = record_walk(str(policy), args.out / "walk.gif", args.out / "walk.png")
            print(f"video: {gif}")
        except Exception as error:  # no offscreen GL here: the score above still stands
            print(f"no video ({type(error).__name__}: {error}); set MUJOCO_GL=egl where libEGL is installed")
    walks = result.tracking >= WALKING and result.falls <= 1
    ratio = result.tracking / shipped["tracking"]
    print(("VERDICT: it walks" if walks else "VERDICT: it does not walk yet")
          + f": tracking {result.tracking:.3f} ({ratio:.0%} of the physics-trained policy, floor {floor.tracking:.3f}),"
          f" {result.falls}/{result.episodes} falls; walking means >= {WALKING} with at most 1 fall")
    return 0


def json_score(score: dict) -> str:
    """A shipped policy's physics score as its JSON records it (not re-measured here)."""
    return f"tracking {score['tracking']:.3f}, falls {score['falls']}/{score['episodes']} (from its JSON)"


def recipe(scratch: dict) -> list[str]:
    """`rwm-gym ppo` options for the shipped from-scratch policy's world model and settings, read from its JSON (the
    recipe's numbers live there once): the model, its imagined-episode options, the reward clip, the learning-rate
    anneal and the initial std."""
    from rwm_gym.resources import shipped_file

    options = ["--checkpoint", str(shipped_file(scratch["world_model"]["checkpoint"]))]
    for name, value in scratch["env"]["imagination"].items():
        if value is not None:  # reset_data None: the windows the checkpoint names
            options.append(f"--{name.replace('_', '-')}={value}")
    if scratch["ppo"]["positive_reward_only"]:
        options.append("--positive-reward-only")
    if scratch["ppo"].get("lr_anneal_fraction"):  # absent from the JSONs of recipes older than the anneal
        options.append(f"--lr-anneal-fraction={scratch['ppo']['lr_anneal_fraction']}")
    return options + [f"--log-std-init={scratch['ppo']['log_std_init']}"]


def measured_recipes(scratch: dict) -> list[tuple[str, list[dict]]]:
    """(setting, seeds with their physics curves) of the shipped recipe first, then of the other settings measured
    beside it (the JSON's `other_recipes`); a setting names the imagined envs, the fall tilt, torque halt and
    learning-rate anneal where one was set, and the world model where it is not the shipped recipe's."""
    model = scratch["world_model"]["checkpoint"]
    shipped = {"num_envs": scratch["ppo"]["num_envs"], **scratch["env"]["imagination"], "seeds": scratch["seeds"],
               "lr_anneal_fraction": scratch["ppo"].get("lr_anneal_fraction"), "world_model": model}

    def setting(recipe: dict) -> str:
        tilt, halt, anneal = recipe.get("fall_tilt"), recipe.get("torque_halt"), recipe.get("lr_anneal_fraction")
        trained_in = recipe.get("world_model", model)
        parts = [f"{recipe['num_envs']} envs", tilt and f"fall tilt {tilt:g} deg", halt and f"torque halt {halt:g}",
                 anneal and f"lr annealed over the last {anneal:.0%}",
                 trained_in != model and f"in {Path(trained_in).stem}"]
        return ", ".join(part for part in parts if part)

    return [(setting(recipe), recipe["seeds"]) for recipe in [shipped, *scratch.get("other_recipes", [])]]


LINE_STYLES = ("-", ":", "--", "-.", (0, (1, 4)), (0, (5, 1, 1, 1, 1, 1)), (0, (5, 1, 5, 1, 1, 1)))
"""One per measured setting, in the JSON's order: the shipped recipe first, then `other_recipes`."""


def plot_curve(scratch: dict, num_envs: int, timesteps: int, tracking: float, floor: float, path: Path) -> Path:
    """The recipe's measured physics tracking against imagined steps (one line per seed), with this run's point; the
    legend names each curve's setting and this run's imagined envs, so a point from another setting is not read as the
    recipe's."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from rwm_gym.atomic import save_png

    fig, ax = plt.subplots(figsize=(11, 4.5))
    for i, (setting, seeds) in enumerate(measured_recipes(scratch)):
        for run in seeds:
            ax.plot([r["timesteps"] / 1e6 for r in run["curve"]], [r["tracking"] for r in run["curve"]],
                    marker="" if i else ".", linestyle=LINE_STYLES[min(i, len(LINE_STYLES) - 1)],
                    label=f"seed {run['seed']}, {setting}" + ("" if i else " (shipped recipe)"))
    ax.plot([timesteps / 1e6], [tracking], "r*", markersize=14, label=f"this run ({num_envs} envs)")
    ax.axhline(floor, color="0.5", ls="--", label="zero action (stands still)")
    ax.axhline(WALKING, color="tab:green", ls=":", label=f"walking ({WALKING})")
    ax.set_xlabel("imagined env steps (M)")
    ax.set_ylabel("tracking score in physics")
    ax.set_title(f"PPO from scratch in {Path(scratch['world_model']['checkpoint']).stem} (shipped), ANYmal D")
    ax.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.01, 0.5))  # beside the axes: the curves stay clear
    fig.tight_layout()
    save_png(fig, path, dpi=100)
    return path


if __name__ == "__main__":
    sys.exit(main())

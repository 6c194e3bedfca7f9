"""Reproduce the ANYmal D world model shipped in `assets/checkpoints/` (the default of `RWM-AnymalD-v0`).

The shipped model is made in five stages, on one CPU thread of the shared 2-core machine (the model of stages 1-3 alone
was the default before the last two: `git show f0dc796:assets/checkpoints/anymal_d_rwm.safetensors`):

1. Trained from scratch on the physics PPO teacher's experience (95 min, 6,707 iterations x 256 windows):

       rwm-gym ppo --in physics --num-envs 4096 --n-steps 24 --timesteps 60000000 --run-dir runs/ppo_physics \
           --save-every 4 --snapshot-every 8 --record-every 32 --threads 1 --seed 0       # the teacher (~75 min)
       python examples/make_teacher_data.py --run-dir runs/ppo_physics --out data/teacher
       python examples/make_default_checkpoint.py --out runs/wm_default --data data/teacher/experience.h5 \
           --batch-size 256 --branches 4 --branch-stride 8 --unit-gravity --joint-limits --minutes 95 --iterations 0

2. Fine-tuned in six iterations of the MBPO loop (`rwm-gym mbpo` with 192 physics
   episodes of up to 400 steps and 300 model steps per iteration, `--iterations 6`, from stage 1's model;
   `data/base/mix.h5` is its 208 k-row physics mix): `model_6`.

3. Fine-tuned on that mix with 32-step forecasts (80 min, 1,409 iterations x 256 windows; `--init` trains on the
   `--data` files alone and keeps the model's config):

       python examples/make_default_checkpoint.py --out runs/wm_f32 --init runs/mbpoM/model_6.safetensors \
           --data data/base/mix.h5 --forecast 32 --lr 3e-4 --batch-size 256 --branches 4 --branch-stride 8 \
           --minutes 80 --iterations 0
       cp runs/wm_f32/anymal_d_rwm.safetensors runs/wm_f32/anymal_d_reset.h5 assets/checkpoints/

4. Fine-tuned on the same mix with the Gaussian nll state loss, the std freed first (40 min, 5,000 iterations x 64
   segments x 4 branches; under the mse loss the std sat at 0.34 normalised units on every channel):

       python examples/make_default_checkpoint.py --out runs/wm_nll32 --init runs/wm_f32/anymal_d_rwm.safetensors \
           --data data/base/mix.h5 --loss nll --reset-std-band --forecast 32 --lr 3e-4 --batch-size 64 \
           --branches 4 --branch-stride 8 --no-warmup-gradients --minutes 40 --iterations 0

5. The same loss on 100-step forecasts (35 min, 1,518 iterations x 64 segments x 4 branches 16 rows apart):

       python examples/make_default_checkpoint.py --out runs/wm_nll100 --init runs/wm_nll32/anymal_d_rwm.safetensors \
           --data data/base/mix.h5 --loss nll --forecast 100 --lr 3e-4 --batch-size 64 --branches 4 \
           --branch-stride 16 --no-warmup-gradients --minutes 35 --iterations 0
       cp runs/wm_nll100/anymal_d_rwm.safetensors assets/checkpoints/   # the reset data of stage 3 stays

Collects physics data with fixed seeds (correlated random actions, and the scripted trot with two levels of action
noise under random commands), adds any `--data` files of the same task (the physics PPO teacher's experience: 4,798
episodes from its first to its last iteration, so falling, standing and walking), trains RWM (2 x 256 GRUs, 5
ensemble heads, history 32, forecast 8; here 64 segments x 4 forecast branches 8 rows apart per step) for a number of
iterations and/or minutes (resumable: run the same command again), and writes the checkpoint plus a small reset
dataset (real 32-step histories the imagined env starts from, drawn from the scripted trot and the `--data` files).
The command line is stored in the checkpoint's `extras["made_by"]`.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

from rwm_gym.data.collect import collect
from rwm_gym.data.dataset import merge_datasets
from rwm_gym.imagination.reset_data import make_reset_data
from rwm_gym.model.checkpoint import load_checkpoint, read_meta, save_checkpoint
from rwm_gym.model.config import TrainConfig
from rwm_gym.model.factory import model_config_for
from rwm_gym.model.train import train
from rwm_gym.spec import load_spec

# (policy, episodes, max steps, action noise, seed): the data mix of the shipped model.
DATA_MIX = (
    ("random", 200, 300, 0.0, 100),
    ("gait", 160, 500, 0.1, 1000),
    ("gait", 60, 500, 0.3, 5000),
)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("assets/checkpoints"))
    parser.add_argument(
        "--data-dir",
        type=Path,
        default=Path("data/default_checkpoint"),
        help="folder for the collected data and the merged mix",
    )
    parser.add_argument(
        "--data", type=Path, nargs="*", default=[], help="more datasets of the task to train on (merged into the mix)"
    )
    parser.add_argument("--iterations", type=int, default=2000, help="gradient steps (0: only --minutes)")
    parser.add_argument("--minutes", type=float, default=0.0, help="wall-clock budget (0: only --iterations)")
    parser.add_argument("--batch-size", type=int, default=64, help="forecast windows per gradient step")
    parser.add_argument("--branches", type=int, default=1, help="forecast branches per segment (1: paper windows)")
    parser.add_argument("--branch-stride", type=int, default=1, help="rows between the starts of a segment's branches")
    parser.add_argument("--ensemble", type=int, default=5, help="state heads")
    parser.add_argument("--unit-gravity", action="store_true", help="ModelConfig.unit_gravity")
    parser.add_argument("--joint-limits", action="store_true", help="ModelConfig.joint_limits")
    parser.add_argument(
        "--init",
        type=Path,
        default=None,
        metavar="CKPT",
        help="fine-tune this checkpoint on the --data files alone (no collected mix)",
    )
    parser.add_argument("--forecast", type=int, default=8, help="forecast steps per training window")
    parser.add_argument("--lr", type=float, default=1e-3, help="Adam learning rate at the start of the schedule")
    parser.add_argument(
        "--warmup-gradients",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="backpropagate through the teacher-forced warm-up (TrainConfig.warmup_gradients)",
    )
    parser.add_argument("--loss", choices=("mse", "nll"), default="mse", help="state loss (TrainConfig.loss)")
    parser.add_argument(
        "--reset-std-band",
        action="store_true",
        help="with --init: free the std of an mse-trained model first (TrainConfig.reset_std_band)",
    )
    parser.add_argument("--threads", type=int, default=1, help="torch threads (1 is fastest on a busy 2-core CPU)")
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()
    for extra in args.data + ([args.init] if args.init else []):
        if not extra.exists():
            parser.error(f"{extra}: no such file")
    if args.init and not args.data:
        parser.error("--init fine-tunes on the --data files: give at least one")
    if args.reset_std_band and not args.init:
        parser.error("--reset-std-band resets the model given with --init")
    torch.set_num_threads(args.threads)

    parts, mix = [], () if args.init else DATA_MIX
    for policy, episodes, steps, noise, seed in mix:
        path = args.data_dir / f"{policy}_noise{noise}_seed{seed}.h5"
        if not path.exists():
            collect(
                "AnymalD-MuJoCo-v0", policy, episodes, path, seed=seed, num_envs=16, action_noise=noise, max_steps=steps
            )
        parts.append(path)
    name = ("finetune" if args.init else "anymal_d_mix") + "".join(f"+{extra.stem}" for extra in args.data)
    data = args.data[0] if args.init and len(args.data) == 1 else args.data_dir / f"{name}.h5"
    if not data.exists():
        merge_datasets(parts + list(args.data), data)

    spec = load_spec("anymal_d")
    checkpoint = args.out / "anymal_d_rwm.safetensors"
    config = TrainConfig(
        iterations=args.iterations,
        minutes=args.minutes,
        batch_size=args.batch_size,
        branches=args.branches,
        branch_stride=args.branch_stride,
        forecast=args.forecast,
        lr=args.lr,
        warmup_gradients=args.warmup_gradients,
        loss=args.loss,
        reset_std_band=args.reset_std_band,
        device=args.device,
        seed=0,
        val_every=250,
        checkpoint_every=250,
    )
    if args.init:
        model_config = read_meta(args.init).model_config
    else:
        model_config = model_config_for(
            "rwm", spec, ensemble_size=args.ensemble, unit_gravity=args.unit_gravity, joint_limits=args.joint_limits
        )
    train(data, model_config, config, checkpoint, resume=True, init=args.init)

    reset_sources = [*parts[1:2], *args.data]
    if len(reset_sources) > 1:
        if not (args.data_dir / f"reset_sources_{name}.h5").exists():
            merge_datasets(reset_sources, args.data_dir / f"reset_sources_{name}.h5")
        reset_sources = [args.data_dir / f"reset_sources_{name}.h5"]
    reset = make_reset_data(reset_sources[0], args.out / "anymal_d_reset.h5", episodes=24, rows=160, seed=0)
    model, meta = load_checkpoint(checkpoint)
    extras = {
        "reset_data": reset.name,
        "made_by": "python examples/make_default_checkpoint.py " + " ".join(sys.argv[1:]),
        "data_mix": [dict(zip(("policy", "episodes", "max_steps", "action_noise", "seed"), m)) for m in mix]
        + [{"file": str(extra)} for extra in args.data],
    }
    save_checkpoint(
        checkpoint,
        model,
        meta.spec,
        train_config=meta.train_config,
        provenance=meta.provenance,
        stats=meta.stats,
        extras=extras,
    )
    print(f"wrote {checkpoint} and {reset}")


if __name__ == "__main__":
    main()

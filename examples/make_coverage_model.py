"""Teach a world model the states its own policies exploit: their physics episodes, then a fine-tune.

    python examples/make_base_mix.py --out runs/cover/base
    python examples/make_coverage_model.py --base runs/cover/base/mix.h5 --out runs/cover/model \\
        --policies runs/anneal0/policy.zip runs/anneal1/policy.zip runs/anneal2/policy.zip \\
                   assets/policies/anymal_d_ppo_imagination.zip

A second step continues from the first: `--checkpoint runs/cover/model/model.safetensors --base
runs/cover/model/buffer.h5` with the new policies, so the model keeps the earlier policies' episodes too.

Policies trained from scratch inside a model find where it is wrong: an annealed from-scratch policy fell three times
on the fastest diagonal command, where the shipped MBPO model predicts it upright with no fall 25 steps out. The cause
is data coverage, so this collects each policy's own physics episodes in the start model's robot (`--episodes` per
action-noise level, from consecutive seeds), merges them after the base mix (the task's ordinary motions, so the
model keeps what it knew) and fine-tunes the model on the merge with the model's own training settings (only the
budget, learning rate and seed change, as in the MBPO loop). It is one MBPO data step, taken with policies that were
themselves trained from scratch.

Writes OUT/own/part_<i>.h5 (one per policy and noise level), OUT/buffer.h5 (the base, then the parts),
OUT/train.safetensors (the fine-tune with its optimizer state: the same command resumes it) and OUT/model.safetensors:
the weights alone, naming the start model's reset data (found beside it or among the shipped checkpoints, as for the
shipped model), with the physics rows behind its whole lineage in its provenance (`rwm_gym.model.lineage`; each
source once) and their parts in `extras`. Torch's thread count changes the float sums, so the
same `--threads` gives the same model.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import torch

from rwm_gym.data.collect import collect, finished_collection
from rwm_gym.data.dataset import Dataset, DatasetError, merge_datasets
from rwm_gym.data.lineage import total_rows
from rwm_gym.model.checkpoint import load_checkpoint, read_meta, save_checkpoint
from rwm_gym.model.lineage import checkpoint_lineage
from rwm_gym.model.train import train
from rwm_gym.resources import assets_dir

SHIPPED = assets_dir() / "checkpoints" / "anymal_d_rwm_mbpo.safetensors"


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "--policies",
        nargs="+",
        required=True,
        help="SB3 zips (or 'random', 'zero', 'gait') whose physics episodes the model learns",
    )
    parser.add_argument("--base", type=Path, required=True, help="the base mix (examples/make_base_mix.py)")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument(
        "--checkpoint", type=Path, default=SHIPPED, help="the model to fine-tune (default: the shipped MBPO model)"
    )
    parser.add_argument("--episodes", type=int, default=32, help="episodes per policy and noise level")
    parser.add_argument("--max-steps", type=int, default=400, help="cap on an episode's policy steps")
    parser.add_argument(
        "--noise",
        type=float,
        nargs="+",
        default=[0.0, 0.26],
        help="action-noise std levels (0.26: the from-scratch policies' own std at 40 M steps)",
    )
    parser.add_argument("--first-seed", type=int, default=80_000, help="part i's episodes start from seed + 100 i")
    parser.add_argument("--iterations", type=int, default=600, help="fine-tuning steps")
    parser.add_argument("--lr", type=float, default=3e-4, help="fine-tuning learning rate (cosine schedule)")
    parser.add_argument("--seed", type=int, default=27, help="the fine-tune's seed (windows, validation split)")
    parser.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    parser.add_argument(
        "--mirror", action="store_true", help="fine-tune on mirrored windows too (TrainConfig.mirror; else the start's)"
    )
    args = parser.parse_args(argv)
    for given in (args.base, args.checkpoint):
        if not given.is_file():
            parser.error(f"{given}: no such file")
    if not 1 <= args.episodes <= 100 or args.iterations < 1 or args.first_seed < 0:
        parser.error(
            "--episodes must be 1-100 (part i's seeds start at --first-seed + 100 i), --iterations >= 1 and "
            "--first-seed >= 0"
        )
    return args


def collect_parts(args: argparse.Namespace, robot: str) -> list[Path]:
    """One file per (policy, noise level) in `robot`'s physics (an env id); a part already complete with its seed is
    kept (the command resumes)."""
    parts = []
    for i, (policy, noise) in enumerate((p, n) for p in args.policies for n in args.noise):
        part, seed = args.out / "own" / f"part_{i}.h5", args.first_seed + 100 * i
        try:
            finished = finished_collection(part, episodes=args.episodes, seed=seed, what=f"part {i} of this command")
        except DatasetError as error:
            raise SystemExit(str(error)) from None
        if not finished:
            collect(
                robot,
                policy,
                args.episodes,
                part,
                seed=seed,
                num_envs=16,
                action_noise=noise,
                max_steps=args.max_steps,
                overwrite=True,
                progress=not args.quiet,
            )
        parts.append(part)
    return parts


def main(argv: list[str] | None = None) -> Path:
    args = parse_args(argv)
    torch.set_num_threads(args.threads)
    (args.out / "own").mkdir(parents=True, exist_ok=True)
    start = read_meta(args.checkpoint)
    parts = collect_parts(args, start.spec.physics_env_id)  # the start model's robot
    buffer = args.out / "buffer.h5"
    if not buffer.exists():  # merged once (atomic writes): a resumed fine-tune finds the file it started on
        merge_datasets([args.base, *parts], buffer)

    config = replace(
        start.train_config,
        iterations=args.iterations,
        minutes=0.0,
        seed=args.seed,
        lr=args.lr,
        val_every=max(1, args.iterations // 4),
        checkpoint_every=100,
        device="cpu",
        mirror=args.mirror or start.train_config.mirror,
    )
    fine_tune = train(
        buffer,
        start.model_config,
        config,
        args.out / "train.safetensors",
        resume=True,
        init=args.checkpoint,
        progress=not args.quiet,
    )

    model, meta = load_checkpoint(fine_tune.path)
    rows = {
        # the start model's whole lineage; the total is the lineage train() recorded: the start model's united with
        # the buffer's sources, so a base the start model was trained on is not counted twice
        "start_model": total_rows(checkpoint_lineage(start)) or None,
        "base": Dataset.load(args.base).num_steps,
        "own": sum(Dataset.load(part).num_steps for part in parts),
    }
    command = " ".join(argv if argv is not None else sys.argv[1:])
    extras = {
        "reset_data": start.extras.get("reset_data"),
        "made_by": f"python examples/make_coverage_model.py {command}",
        "policies": list(args.policies),
        "physics_rows": {**rows, "total": meta.provenance["physics_rows"]},
    }
    extras = {key: value for key, value in extras.items() if value is not None}
    out = save_checkpoint(
        args.out / "model.safetensors",
        model,
        meta.spec,
        train_config=meta.train_config,
        provenance=meta.provenance,
        stats=meta.stats,
        extras=extras,
    )
    print(f"wrote {out}: val error {meta.stats['val_error']:.4f}; physics rows behind it {extras['physics_rows']}")
    return out


if __name__ == "__main__":
    main()

"""`rwm-gym collect`: collect episodes from a physics env into an HDF5 dataset (`rwm_gym.data.collect`)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import rwm_gym
from rwm_gym.data.collect import collect
from rwm_gym.data.dataset import Dataset, DatasetError
from rwm_gym.options import non_negative_float
from rwm_gym.workers import RayMissing, add_worker_arguments


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `rwm-gym collect`."""
    parser.add_argument(
        "--env", default="AnymalD-MuJoCo-v0", help="registered physics env id, or the path of a task spec (.toml)"
    )
    parser.add_argument(
        "--policy", default="gait", help="'random', 'zero' (stand still), 'gait' or the path of an SB3 .zip"
    )
    parser.add_argument("--episodes", type=int, default=64, help="episodes to collect (default 64)")
    parser.add_argument("--out", required=True, type=Path, help="HDF5 file to write")
    parser.add_argument("--seed", type=int, default=0, help="episode k starts from seed + k (default 0)")
    parser.add_argument("--num-envs", type=int, default=8, help="simulations stepped together (default 8)")
    add_worker_arguments(parser, "the episodes")
    parser.add_argument(
        "--action-noise", type=non_negative_float, default=0.0, help="Gaussian std added to the policy's actions"
    )
    parser.add_argument(
        "--max-steps",
        type=int,
        default=None,
        help="cap on episode length in policy steps (default: the task's episode length)",
    )
    parser.add_argument("--xml-file", type=Path, default=None, help="another MJCF of the robot")
    parser.add_argument(
        "--physics", default=None, help="JSON dict of physics parameters (see PhysicsParams; default: the MJCF's)"
    )
    parser.add_argument("--overwrite", action="store_true", help="replace an existing --out")


def _no_constant(name: str):
    raise ValueError(f"--physics: {name} is not a physics value (give finite numbers)")


def run(args: argparse.Namespace) -> int:
    """`rwm-gym collect`: 2 with a one-line error on bad input, 130 on Ctrl-C (finished episodes are kept)."""
    import json

    env_kwargs: dict[str, object] = {}
    replacing = args.out.exists()  # an interrupted --overwrite run leaves the old file as it was
    if args.xml_file:
        env_kwargs["xml_file"] = str(args.xml_file)
    try:
        if args.physics:
            try:
                env_kwargs["physics"] = json.loads(args.physics, parse_constant=_no_constant)
            except json.JSONDecodeError as err:
                raise ValueError(f"--physics is not valid JSON ({err})") from None
        path = collect(
            args.env,
            args.policy,
            args.episodes,
            args.out,
            seed=args.seed,
            num_envs=args.num_envs,
            action_noise=args.action_noise,
            max_steps=args.max_steps,
            env_kwargs=env_kwargs,
            overwrite=args.overwrite,
            workers=args.workers,
            backend=args.backend,
        )
    except KeyboardInterrupt:
        kept = f"{args.out} is unchanged" if replacing else f"the finished episodes are in {args.out} (complete=false)"
        print(f"rwm-gym collect: interrupted; {kept}", file=sys.stderr)
        return 130
    except (ValueError, TypeError, OSError, DatasetError, RayMissing) as err:
        print(f"rwm-gym collect: {' '.join(str(err).split())}", file=sys.stderr)
        return 2
    ds = Dataset.load(path)
    falls = int(ds["terminated"].sum())
    print(
        f"wrote {path}: {ds.num_episodes} episodes, {ds.num_steps} rows, {falls} terminated "
        f"(rwm-gym {rwm_gym.__version__})"
    )
    return 0

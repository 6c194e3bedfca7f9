"""`rwm-gym collect`: collect episodes from a physics env into an HDF5 dataset (`rwm_gym.data.collect`)."""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path

import rwm_gym
from rwm_gym.commands._options import OverwriteOption, PhysicsEnvOptions, WorkerOptions, add_group, parse_physics
from rwm_gym.data.collect import collect, diverged_episodes
from rwm_gym.data.dataset import Dataset, DatasetError
from rwm_gym.options import option
from rwm_gym.workers import RayMissing


@dataclass(frozen=True)
class CollectOptions:
    """What is collected, how, and where it is written."""

    out: Path
    """HDF5 file to write"""
    policy: str = "gait"
    """'random', 'zero' (stand still), 'gait' (a legged robot's trot), 'reach' (an arm's reach toward its target;
    --action-noise makes it hover and miss) or the path of an SB3 .zip"""
    episodes: int = option(64, ge=1)
    """episodes to collect"""
    seed: int = 0
    """episode k starts from seed + k"""
    num_envs: int = option(8, ge=1)
    """simulations stepped together"""
    action_noise: float = option(0.0, ge=0)
    """Gaussian std added to the policy's actions ('reach': correlated, with an aim offset of 0.1 m per unit)"""
    max_steps: int | None = option(None, ge=1)
    """cap on episode length in policy steps (default: the task's episode length)"""
    physics: str | None = None
    """JSON dict of physics parameters (see PhysicsParams), or a JSON file of one (default: the MJCF's). The physics
    is solved with the MJCF's own solver settings (ANYmal D: 4 iterations, pyramidal cone, fast for PPO), as `rwm-gym
    gap` re-simulates by default; {"solver": {"iterations": 100}} solves each step to convergence"""


OPTIONS = (PhysicsEnvOptions, CollectOptions, WorkerOptions, OverwriteOption)
"""The dataclasses the flags of `rwm-gym collect` come from."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `rwm-gym collect`."""
    for group in OPTIONS:
        add_group(parser, group)


def run(args: argparse.Namespace) -> int:
    """`rwm-gym collect`: 2 with a one-line error on bad input, 130 on Ctrl-C (finished episodes are kept)."""
    env_kwargs: dict[str, object] = {}
    replacing = args.out.exists()  # an interrupted --overwrite run leaves the old file as it was
    if args.xml_file:
        env_kwargs["xml_file"] = str(args.xml_file)
    try:
        if args.physics:
            env_kwargs["physics"] = parse_physics(args.physics)
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
    blown = len(diverged_episodes(ds))
    if blown:
        print(
            f"rwm-gym collect: the physics blew up in {blown} of {ds.num_episodes} episodes (MuJoCo reset the "
            'simulation); each ends at the last state before it. {"solver": {"iterations": 100}} in --physics '
            "solves each step to convergence",
            file=sys.stderr,
        )
    return 0

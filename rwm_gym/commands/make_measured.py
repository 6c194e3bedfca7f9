"""`rwm-gym make-measured`: 'measured' data from a simulator with a hidden physical effect (`rwm_gym.gap.measured`)."""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path

from rwm_gym.commands._options import OverwriteOption, PhysicsEnvOptions, add_group, parse_physics
from rwm_gym.data.collect import make_physics_core
from rwm_gym.data.dataset import Dataset
from rwm_gym.gap.effects import parse_effects
from rwm_gym.gap.measured import (
    SensorNoise,
    make_measured,
    solver_option,
)
from rwm_gym.options import option
from rwm_gym.physics.params import CONVERGED_SOLVER


@dataclass(frozen=True, kw_only=True)
class MeasuredOptions:
    """The hidden effects, what drives the robot, and the file written (the nominal simulator: `PhysicsEnvOptions`)."""

    effect: tuple[str, ...] = option((), append=True)
    """effect of the vocabulary to hide (repeatable; default: none, the nominal simulator)"""
    magnitude: tuple[str, ...] = option((), append=True)
    """its parameter value(s), e.g. 2.0 or 0.7,1.2 (one per --effect; default: realistic); negative ones with a
    comma after an equals sign: --magnitude=-5,0.1"""
    physics: str | None = None
    """JSON dict of further PhysicsParams to hide (per-joint ok), or a JSON file of one"""
    policy: str = "excitation"
    """what drives the robot: excitation (made for identification), gait, random, or the path of an SB3 .zip (an
    ordinary walking policy, as in a real robot's log)"""
    episodes: int = option(16, ge=1)
    max_steps: int = option(250, ge=1)
    """policy steps per episode"""
    noise_scale: float = option(1.0, ge=0)
    """multiplier on the default sensor noise (0: none); `rwm-gym gap` assumes the default and checks it against
    the data"""
    solver_iterations: int = option(CONVERGED_SOLVER.iterations, ge=0)
    """MuJoCo solver iterations per physics step of the hidden robot: the robot stands in for a real one, so by
    default each step is solved to convergence (100), not with the fast MJCF's settings that `rwm-gym gap`
    re-simulates with (0: the MJCF's own)"""
    seed: int = 0
    out: Path


OPTIONS = (MeasuredOptions, PhysicsEnvOptions, OverwriteOption)
"""The dataclasses the flags of `rwm-gym make-measured` come from."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `rwm-gym make-measured`."""
    for group in OPTIONS:
        add_group(parser, group)


def run(args: argparse.Namespace) -> int:
    """`rwm-gym make-measured`: 0, or 2 with one line on stderr on bad input."""
    env_kwargs = {"xml_file": str(args.xml_file)} if args.xml_file else {}
    spec = make_physics_core(args.env, 1, **env_kwargs).spec
    try:
        from rwm_gym.output_guard import check_output

        check_output(
            args.out,
            overwrite=args.overwrite,
            inputs=[
                args.policy if args.policy.endswith(".zip") else None,
                args.xml_file,
                args.env if args.env.endswith(".toml") else None,
            ],
        )
        effects = parse_effects(spec, args.effect, args.magnitude)
        extra_physics = parse_physics(args.physics) if args.physics else {}
        path = make_measured(
            effects,
            args.episodes,
            args.out,
            env_id=args.env,
            env_kwargs=env_kwargs,
            extra_physics=extra_physics or None,
            seed=args.seed,
            max_steps=args.max_steps,
            noise=SensorNoise(scale=args.noise_scale),
            policy=args.policy,
            solver=solver_option(args.solver_iterations),
            overwrite=args.overwrite,
        )
    except (ValueError, FileNotFoundError, FileExistsError) as err:
        print(f"rwm-gym make-measured: {err}", file=sys.stderr)
        return 2
    ds = Dataset.load(path)
    hidden = [*args.effect, *extra_physics]
    print(f"wrote {path}: {ds.num_episodes} episodes, {ds.num_steps} rows (hidden: {', '.join(hidden) or 'nothing'})")
    return 0

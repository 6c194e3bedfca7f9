"""`rwm-gym gap`: find, name and correct the gap between a simulator and measured data (`rwm_gym.gap.workflow`)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from rwm_gym.gap.fit import FitConfig
from rwm_gym.gap.measured import SensorNoise, solver_option
from rwm_gym.gap.report import world_model_table
from rwm_gym.gap.scope import SCOPES
from rwm_gym.gap.workflow import (
    GapConfig,
    resolve_world_model,
    run_gap,
)
from rwm_gym.gap.world_model import WorldModelGapConfig
from rwm_gym.physics.params import CONVERGED_SOLVER


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `rwm-gym gap`."""
    parser.add_argument("--sim", default="AnymalD-MuJoCo-v0", help="registered physics env id of the nominal simulator")
    parser.add_argument("--sim-kwargs", default=None, help='JSON env kwargs, e.g. {"xml_file": "my_robot.xml"}')
    parser.add_argument("--measured", type=Path, required=True, help="measured dataset (HDF5, rwm-gym format)")
    parser.add_argument("--out", type=Path, required=True, help="report folder")
    parser.add_argument("--val-fraction", type=float, default=GapConfig.val_fraction, help="held-out episode share")
    parser.add_argument(
        "--scopes",
        default=",".join(FitConfig.scopes),
        help=f"joint-group scopes tried for the best joint effect, comma-separated from "
        f"{', '.join(SCOPES[1:])} (none: global only; each kept only if held-out data pays)",
    )
    parser.add_argument(
        "--max-effects",
        type=int,
        default=FitConfig.max_effects,
        help="forward selection names at most this many effects",
    )
    parser.add_argument(
        "--joint-candidates",
        type=int,
        default=FitConfig.joint_candidates,
        help="at later selection steps, the best candidates also refitted together with the named "
        "effects (0: each fitted on top of them, frozen)",
    )
    parser.add_argument(
        "--learned-correction",
        action=argparse.BooleanOptionalAction,
        default=GapConfig.learned_correction,
        help="learn a residual joint torque when a gap above the noise floor remains",
    )
    parser.add_argument(
        "--sensor-noise",
        default=None,
        help='JSON SensorNoise of the measured data (SI units, e.g. {"joint_vel": 0.05}); default: make-measured\'s',
    )
    parser.add_argument(
        "--solver-iterations",
        type=int,
        default=CONVERGED_SOLVER.iterations,
        help="MuJoCo solver iterations per physics step of the re-simulations (0: the MJCF's own)",
    )
    parser.add_argument(
        "--world-model",
        default="auto",
        help="checkpoint of the nominal-sim world model for the world-model rows; auto: the shipped "
        "one for AnymalD-MuJoCo-v0 (else none); none: skip them",
    )
    parser.add_argument(
        "--finetune-iterations",
        type=int,
        default=WorldModelGapConfig.iterations,
        help="fine-tuning budget (gradient steps) of the world model after correction",
    )
    parser.add_argument(
        "--regenerate-episodes",
        type=int,
        default=WorldModelGapConfig.episodes,
        help="episodes regenerated from the corrected simulator for the fine-tuning",
    )
    parser.add_argument(
        "--device",
        default=WorldModelGapConfig.device,
        help="torch device of the world-model rows (fine-tuning and evaluation): cpu or cuda",
    )


def run(args: argparse.Namespace) -> int:
    """`rwm-gym gap`: 0, or 2 with one line on stderr on bad input."""
    wm_config = WorldModelGapConfig(
        iterations=args.finetune_iterations, episodes=args.regenerate_episodes, device=args.device
    )
    try:
        sim_kwargs = json.loads(args.sim_kwargs) if args.sim_kwargs else {}
        noise = SensorNoise(**json.loads(args.sensor_noise)) if args.sensor_noise else SensorNoise()
        scopes = tuple(s for s in args.scopes.split(",") if s and s != "none")
        unknown = sorted(set(scopes) - set(SCOPES[1:]))
        if unknown:
            raise ValueError(f"--scopes: unknown scope(s) {unknown}; choose from {', '.join(SCOPES[1:])}")
        if args.joint_candidates < 0:
            raise ValueError(f"--joint-candidates: {args.joint_candidates} is negative (0 turns joint refits off)")
        from rwm_gym.output_guard import check_output

        check_output(
            args.out,
            inputs=[args.measured, args.world_model if args.world_model not in ("auto", "none") else None],
            overwrite=True,
            folder=True,
        )
        report = run_gap(
            args.sim,
            args.measured,
            args.out,
            sim_kwargs=sim_kwargs,
            config=GapConfig(
                val_fraction=args.val_fraction,
                learned_correction=args.learned_correction,
                solver=solver_option(args.solver_iterations),
            ),
            fit_config=FitConfig(scopes=scopes, max_effects=args.max_effects, joint_candidates=args.joint_candidates),
            sensor_noise=noise,
            world_model=resolve_world_model(args.world_model, args.sim, sim_kwargs),
            wm_config=wm_config,
        )
    except (ValueError, FileNotFoundError, TypeError) as err:  # DatasetError and CheckpointError are ValueErrors
        print(f"rwm-gym gap: {err}", file=sys.stderr)
        return 2
    floor = report["noise_floor"]
    print(
        f"gap {floor['gap']:.4g} vs sensor-noise floor {floor['floor']:.4g} (ratio {floor['ratio']:.2f}, "
        f"p={floor['p_value']:.2g})"
    )
    print(f"effect: {report['effect']} ({report['reason']})")
    for item in report["effects"]:
        print(f"  {item['effect']} ({item['scope']}), {item['share_of_explained_gap']:.0%} of the explained gap")
        for name, value in item["parameters"].items():
            print(f"    {name} = {value:.4g} ± {item['uncertainty'][name]:.2g} {item['units'][name]}")
    print(
        f"gap before {report['gap_before']:.4g}, after {report['gap_after']:.4g} "
        f"(explained {report['explained_fraction']:.1%}); report: {Path(args.out) / 'report.md'}"
    )
    learned = report["learned_correction"]
    if learned and learned["status"] == "ok":
        print(
            f"learned residual torque (not a named effect): gap {learned['gap_before']:.4g} -> "
            f"{learned['gap_after']:.4g} (explained {learned['explained_fraction']:.1%})"
        )
    if "world_model" in report:
        print(world_model_table(report["world_model"]))
    return 0

"""`rwm-gym gap`: find, name and correct the gap between a simulator and measured data (`rwm_gym.gap.workflow`)."""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path

from rwm_gym.commands._options import OverwriteOption, add_group
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
from rwm_gym.options import Range, dataclass_from_args, number, option, torch_device


@dataclass(frozen=True, kw_only=True)
class GapOptions:
    """The simulator, the measured data, the report folder and the inputs given as text (JSON, a solver's
    iterations); the workflow's settings are fields of its configs."""

    sim: str = "AnymalD-MuJoCo-v0"
    """registered physics env id of the nominal simulator"""
    sim_kwargs: str | None = None
    """JSON env kwargs, e.g. {"xml_file": "my_robot.xml"}"""
    measured: Path
    """measured dataset (HDF5, rwm-gym format)"""
    out: Path
    """report folder"""
    sensor_noise: str | None = None
    """JSON SensorNoise of the measured data (SI units, e.g. {"joint_vel": 0.05}); default: make-measured's"""
    solver_iterations: int = option(0, ge=0)
    """MuJoCo solver iterations per physics step of the re-simulations (0: the sim env's own, so the gap is that
    of the simulator as it runs, unless --solver-check finds a converged solve reproduces the data materially
    better; 100: each step solved to convergence)"""
    world_model: str = "auto"
    """checkpoint of the nominal-sim world model for the world-model rows; auto: the shipped one for
    AnymalD-MuJoCo-v0 (else none); none: skip them"""


def json_flag(text: str, flag: str) -> dict:
    """A JSON object given as a flag's text; a one-line ValueError naming the flag otherwise."""
    try:
        value = json.loads(text)
    except json.JSONDecodeError as err:
        raise ValueError(f"{flag} is not valid JSON ({err})") from None
    except RecursionError:
        raise ValueError(f"{flag} is nested too deeply") from None
    if not isinstance(value, dict):
        raise ValueError(f"{flag} must be a JSON object, got {type(value).__name__}")
    return value


def scope_list(text: str) -> tuple[str, ...]:
    """An argparse type: comma-separated joint-group scopes of `FitConfig.scopes` ('none': the global forms only)."""
    scopes = tuple(s for s in text.split(",") if s and s != "none")
    if unknown := sorted(set(scopes) - set(SCOPES[1:])):
        raise argparse.ArgumentTypeError(f"unknown scope(s) {unknown}; choose from {', '.join(SCOPES[1:])}")
    return scopes


OPTIONS = (GapOptions, OverwriteOption, GapConfig, FitConfig, WorldModelGapConfig)
"""The dataclasses the flags of `rwm-gym gap` come from."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `rwm-gym gap`: its inputs, then the fields of the workflow's configs it exposes."""
    add_group(parser, GapOptions)
    add_group(parser, OverwriteOption)
    add_group(
        parser,
        GapConfig,
        "workflow",
        only={"val_fraction", "learned_correction", "solver_check", "bootstrap"},
    )
    add_group(
        parser,
        FitConfig,
        "fit",
        only={"scopes", "max_effects", "joint_candidates"},
        types={"scopes": scope_list},
    )
    add_group(
        parser,
        WorldModelGapConfig,
        "world model",
        only={"iterations", "episodes", "device"},
        flags={"iterations": ["--finetune-iterations"], "episodes": ["--regenerate-episodes"]},
        types={"device": torch_device, "iterations": number(int, Range(ge=0)), "episodes": number(int, Range(ge=1))},
    )


def run(args: argparse.Namespace) -> int:
    """`rwm-gym gap`: 0, or 2 with one line on stderr on bad input."""
    wm_config = dataclass_from_args(WorldModelGapConfig, args)
    try:
        sim_kwargs = json_flag(args.sim_kwargs, "--sim-kwargs") if args.sim_kwargs else {}
        noise = SensorNoise(**json_flag(args.sensor_noise, "--sensor-noise")) if args.sensor_noise else SensorNoise()
        from rwm_gym.output_guard import check_folder, no_empty_folder

        world_model = resolve_world_model(args.world_model, args.sim, sim_kwargs)
        if world_model is not None and not world_model.is_file():
            raise FileNotFoundError(f"--world-model {world_model} not found")
        check_folder(
            args.out,
            inputs=[args.measured, args.world_model if args.world_model not in ("auto", "none") else None],
            overwrite=args.overwrite,
        )
        with no_empty_folder(args.out):  # run_gap makes the folder: a refused run leaves none
            report = run_gap(
                args.sim,
                args.measured,
                args.out,
                sim_kwargs=sim_kwargs,
                config=dataclass_from_args(GapConfig, args, solver=solver_option(args.solver_iterations)),
                fit_config=dataclass_from_args(FitConfig, args),
                sensor_noise=noise,
                world_model=world_model,
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
            spread = item.get("bootstrap", {}).get(name)
            interval = " (bootstrap 95 %: {:.4g} to {:.4g})".format(*spread["interval"]) if spread else ""
            print(f"    {name} = {value:.4g} ± {item['uncertainty'][name]:.2g} {item['units'][name]}{interval}")
    chosen = report["gap_measure"]
    print(
        f"gap ({chosen['measure']}) before {chosen['gap_before']:.4g}, after {chosen['gap_after']:.4g} "
        f"(explained {chosen['explained_fraction']:.1%}); report: {Path(args.out) / 'report.md'}"
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

"""`rwm-gym gap`: find where a simulator and measured data disagree, name the missing effect, correct, show the gap.

Steps: split the measured episodes into fitting and held-out ones; re-simulate held-out windows with the nominal
simulator and rank channels and conditions (`diagnose`); fit every effect of the vocabulary on the fitting episodes
and judge it on the held-out ones (`fit`); write the corrected simulator (`correct`); with a world model, regenerate
data from the corrected simulator, fine-tune the world model on it plus the measured fitting episodes and compare the
four predictors on the held-out episodes (`world_model`); write the report (`report`).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rwm_gym import atomic
from rwm_gym.data.collect import make_physics_core
from rwm_gym.data.dataset import Dataset
from rwm_gym.gap.correct import write_corrected
from rwm_gym.gap.diagnose import where
from rwm_gym.gap.effects import vocabulary
from rwm_gym.gap.fit import GAP_HORIZONS, FitConfig, decide, fit_all
from rwm_gym.gap.report import markdown, plot_channels, plot_rollout, world_model_table, write_json
from rwm_gym.gap.resim import Resimulator, make_windows, normalised_residual
from rwm_gym.gap.scope import per_leg_candidate
from rwm_gym.gap.world_model import WorldModelGapConfig, compare, config_dict, fine_tune, regenerate
from rwm_gym.model.evaluate import plot_curves
from rwm_gym.resources import assets_dir

SHIPPED_WORLD_MODELS = {"AnymalD-MuJoCo-v0": "checkpoints/anymal_d_rwm.safetensors"}
"""Nominal-sim world model used by `rwm-gym gap` when `--world-model` is not given (path under `assets/`)."""


@dataclass(frozen=True)
class GapConfig:
    """Data handling of the workflow (the fit's own options are `FitConfig`)."""

    val_fraction: float = 0.34
    """Share of measured episodes held out (never fitted); at least one."""
    split_seed: int = 0
    fit_stride: int = 8
    """Rows between the starts of fitting windows."""
    eval_stride: int = 5
    """Rows between the starts of held-out windows."""
    warmup: int = 2
    """Measured steps replayed before each window (fills the actuator delay buffer)."""
    per_leg: bool = True
    """Refit a named joint effect with one value per leg; kept only if the held-out gap pays for it (`gap.scope`)."""


def run_gap(sim: str, measured: str | Path, out: str | Path, *, sim_kwargs: dict | None = None,
            config: GapConfig = GapConfig(), fit_config: FitConfig = FitConfig(), progress: bool = True,
            world_model: str | Path | None = None, wm_config: WorldModelGapConfig = WorldModelGapConfig()) -> dict:
    """Run the workflow and write `out/report.json` (+ md, plots, corrected model); returns the report dict.

    world_model: checkpoint of the world model trained on nominal-sim data; adds the `world_model` section (None: skip).
    """
    if world_model is not None and not Path(world_model).is_file():
        raise FileNotFoundError(f"world model {world_model} not found (--world-model)")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    sim_kwargs = dict(sim_kwargs or {})
    core = make_physics_core(sim, 1, **sim_kwargs)
    spec, base = core.spec, core.params
    data = Dataset.load(measured)
    if data.spec().state_columns != spec.state_columns:
        raise ValueError(f"{measured}: field 'state': columns differ from the simulator {sim}'s task spec")
    train_ids, held_ids = data.split_episodes(config.val_fraction, config.split_seed)
    horizon = max(GAP_HORIZONS)
    train = make_windows(data, train_ids, fit_config.fit_horizon, config.fit_stride, config.warmup)
    held = make_windows(data, held_ids, horizon, config.eval_stride, config.warmup)
    resim = Resimulator(spec, sim_kwargs.get("xml_file"))
    effects = vocabulary(spec, sim_kwargs.get("xml_file"))

    fits, before = fit_all(effects, resim, train, held, base, fit_config, progress)
    leg = (per_leg_candidate(fits, effects, spec, resim, train, held, base, before, fit_config) if config.per_leg
           else None)
    if leg is not None:
        fits.append(leg[1])
    verdict = decide(fits, effects, fit_config)
    named = verdict.winner and (leg[0] if verdict.winner.scope == "leg" else effects[verdict.effect])
    corrected_params = named.physics(verdict.winner.values, base) if verdict.winner else base
    nominal_sim = resim.rollout(held, base)
    corrected_sim = resim.rollout(held, corrected_params) if verdict.winner else nominal_sim
    after = before if verdict.winner is None else np.stack(
        [(normalised_residual(spec, corrected_sim[:, h - 1], held.target[:, h - 1]) ** 2).mean(-1)
         for h in GAP_HORIZONS], axis=1)

    plots = {"channels": str(out / "residual_channels.png"), "rollout": str(out / "rollout_overlay.png")}
    h5 = min(5, horizon) - 1
    per_channel = [(normalised_residual(spec, s[:, h5], held.target[:, h5]) ** 2).mean(0)
                   for s in (nominal_sim, corrected_sim)]
    plot_channels(spec, *per_channel, Path(plots["channels"]), 5)
    top = [c["channel"] for c in where(spec, nominal_sim, held)["channels_h5"][:3]]
    worst = int(np.argmax(before.mean(1)))
    plot_rollout(spec, held.target[worst], nominal_sim[worst], corrected_sim[worst], top, Path(plots["rollout"]))
    winner = verdict.winner
    report = {
        "effect": verdict.effect,
        "reason": verdict.reason,
        "scope": winner.scope if winner else None,
        "parameters": dict(zip(winner.names, winner.values)) if winner else {},
        "units": dict(zip(winner.names, winner.units)) if winner else {},
        "uncertainty": dict(zip(winner.names, winner.uncertainty)) if winner else {},
        "explained_fraction": float(1.0 - after.mean() / before.mean()),
        "gap_before": float(before.mean()),
        "gap_after": float(after.mean()),
        "gap_before_per_horizon": {str(h): float(v) for h, v in zip(GAP_HORIZONS, before.mean(0))},
        "gap_after_per_horizon": {str(h): float(v) for h, v in zip(GAP_HORIZONS, after.mean(0))},
        "gap_metric": "normalised state MSE ((sim - measured) / spec state std)^2 at each horizon, held-out windows",
        "where": where(spec, nominal_sim, held),
        "candidates": [dataclasses.asdict(f) for f in sorted(fits, key=lambda f: f.score, reverse=True)],
        "held_out_episodes": [int(e) for e in held_ids],
        "fit_episodes": [int(e) for e in train_ids],
        "corrected_physics": corrected_params.to_dict(),
        "corrected": write_corrected(spec, corrected_params, out, sim_kwargs.get("xml_file"), sim_kwargs),
        "plots": plots,
        "sim": sim,
        "measured": str(measured),
        "config": {"gap": dataclasses.asdict(config), "fit": dataclasses.asdict(fit_config)},
    }
    if world_model is not None:
        report["world_model"] = world_model_rows(sim, sim_kwargs, data, train_ids, held_ids, resim, base,
                                                 corrected_params, Path(world_model), out, wm_config, config.warmup,
                                                 progress)
        report["plots"]["world_model"] = report["world_model"]["plot"]
    write_json(out / "report.json", report)
    atomic.write_text(out / "report.md", markdown(report))
    return report


def world_model_rows(sim: str, sim_kwargs: dict, data: Dataset, train_ids: np.ndarray, held_ids: np.ndarray,
                     resim: Resimulator, base, corrected, checkpoint: Path, out: Path, config: WorldModelGapConfig,
                     warmup: int, progress: bool) -> dict:
    """Regenerate, fine-tune and compare (see `gap.world_model`); the report's `world_model` section."""
    checkpoints: dict[str, Path] = {"world_model_nominal": checkpoint}
    control = config.control and corrected != base  # with nothing corrected the control is the same run
    runs = [("world_model_corrected", corrected)] + ([("world_model_control", base)] if control else [])
    for name, params in runs:
        sim_data = regenerate(sim, sim_kwargs, params, config, out / f"{name}_sim_data.h5")
        checkpoints[name] = fine_tune(checkpoint, sim_data, data, train_ids, out / f"{name}.safetensors", config,
                                      progress)
        sim_data.unlink()
    result = compare(resim, data, held_ids, base, corrected, checkpoints, config, warmup)
    if not result["error"]:
        raise ValueError(f"{data.path}: field 'episode_lengths': no held-out episode has {config.history} + "
                         f"{min(config.horizons)} rows, needed for the world-model rows")
    plot = out / "world_model_error.png"
    plot_curves(result.pop("curve"), plot, title="held-out measured episodes: relative error vs open-loop steps")
    return {**result, "checkpoints": {k: str(v) for k, v in checkpoints.items()}, "plot": str(plot),
            "metric": "relative error sum|pred - true| / sum|true| of the normalised state, mean over the first N "
                      "rows (rwm_gym.model.evaluate); sims re-simulated open loop from the measured state",
            "config": config_dict(config)}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--sim", default="AnymalD-MuJoCo-v0", help="registered physics env id of the nominal simulator")
    parser.add_argument("--sim-kwargs", default=None, help='JSON env kwargs, e.g. {"xml_file": "my_robot.xml"}')
    parser.add_argument("--measured", type=Path, required=True, help="measured dataset (HDF5, rwm-gym format)")
    parser.add_argument("--out", type=Path, required=True, help="report folder")
    parser.add_argument("--val-fraction", type=float, default=GapConfig.val_fraction, help="held-out episode share")
    parser.add_argument("--per-leg", action=argparse.BooleanOptionalAction, default=GapConfig.per_leg,
                        help="try one value per leg for a named joint effect (kept only if held-out data pays for it)")
    parser.add_argument("--world-model", default="auto",
                        help="checkpoint of the nominal-sim world model for the world-model rows; auto: the shipped "
                             "one for AnymalD-MuJoCo-v0 (else none); none: skip them")
    parser.add_argument("--finetune-iterations", type=int, default=WorldModelGapConfig.iterations,
                        help="fine-tuning budget (gradient steps) of the world model after correction")
    parser.add_argument("--regenerate-episodes", type=int, default=WorldModelGapConfig.episodes,
                        help="episodes regenerated from the corrected simulator for the fine-tuning")
    parser.add_argument("--device", default=WorldModelGapConfig.device,
                        help="torch device of the world-model rows (fine-tuning and evaluation): cpu or cuda")


def resolve_world_model(choice: str, sim: str, sim_kwargs: dict) -> Path | None:
    """The --world-model checkpoint: a path, `none`, or `auto` (the shipped one for a stock shipped simulator)."""
    if choice == "none":
        return None
    if choice == "auto":
        shipped = SHIPPED_WORLD_MODELS.get(sim)
        return assets_dir() / shipped if shipped and not sim_kwargs.get("xml_file") else None
    return Path(choice)


def run(args: argparse.Namespace) -> int:
    sim_kwargs = json.loads(args.sim_kwargs) if args.sim_kwargs else {}
    wm_config = WorldModelGapConfig(iterations=args.finetune_iterations, episodes=args.regenerate_episodes,
                                    device=args.device)
    try:
        report = run_gap(args.sim, args.measured, args.out, sim_kwargs=sim_kwargs,
                         config=GapConfig(val_fraction=args.val_fraction, per_leg=args.per_leg),
                         world_model=resolve_world_model(args.world_model, args.sim, sim_kwargs), wm_config=wm_config)
    except (ValueError, FileNotFoundError) as err:  # DatasetError and CheckpointError are ValueErrors
        print(f"rwm-gym gap: {err}", file=sys.stderr)
        return 2
    scope = f", {report['scope']}" if report["scope"] else ""
    print(f"effect: {report['effect']}{scope} ({report['reason']})")
    for name, value in report["parameters"].items():
        print(f"  {name} = {value:.4g} ± {report['uncertainty'][name]:.2g} {report['units'][name]}")
    print(f"gap before {report['gap_before']:.4g}, after {report['gap_after']:.4g} "
          f"(explained {report['explained_fraction']:.1%}); report: {Path(args.out) / 'report.md'}")
    if "world_model" in report:
        print(world_model_table(report["world_model"]))
    return 0

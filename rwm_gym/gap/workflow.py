"""`rwm-gym gap`: find where a simulator and measured data disagree, name the missing effects, correct, show the gap.

Steps: split the measured episodes into fitting and held-out ones; re-simulate held-out windows with the nominal
simulator, rank channels and conditions (`diagnose`), compute the sensor-noise floor of the gap (`noise_floor`) and
which effects these data can reveal (`identifiability`); if the gap is above the floor, name effects by forward
selection over the vocabulary and its scopes (`select`, `fit`, `scope`); if a gap remains above the corrected
simulator's own noise floor, learn a residual torque for it (`learned`); write the corrected simulator (`correct`);
with a world model, regenerate data from the corrected simulator, fine-tune the world model on it plus the measured
fitting episodes and compare the predictors on the held-out episodes (`world_model`); write the report (`report`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rwm_gym import atomic
from rwm_gym.atomic import write_json
from rwm_gym.data.collect import make_physics_core
from rwm_gym.data.dataset import Dataset
from rwm_gym.gap.bootstrap import bootstrap
from rwm_gym.gap.correct import write_corrected
from rwm_gym.gap.cross_fit import CrossFit
from rwm_gym.gap.diagnose import locate_gap
from rwm_gym.gap.distribution import distribution_gap, headline
from rwm_gym.gap.effects import vocabulary
from rwm_gym.gap.fit import GAP_HORIZONS, FitConfig, gap_ceiling, gap_horizons, gap_per_window
from rwm_gym.gap.identifiability import identifiability
from rwm_gym.gap.learned import LearnedCorrectionConfig, fit_learned_correction, save_correction
from rwm_gym.gap.measured import SensorNoise
from rwm_gym.gap.noise_estimate import (
    DIFFERENCE_ORDER,
    MATERIAL_RATIO,
    channels,
    estimate_noise,
    measured_noise,
    noise_for_floor,
    quantity_noise,
)
from rwm_gym.gap.noise_floor import FloorConfig, compare_with_floor, noise_floor
from rwm_gym.gap.report import markdown, plot_channels, plot_rollout
from rwm_gym.gap.resim import WARMUP, Resimulator, SimulationDiverged, Windows, make_windows, normalised_residual
from rwm_gym.gap.select import Selection, select_effects
from rwm_gym.gap.significance import paired_p_value
from rwm_gym.gap.solver_check import (
    SolverChoice,
    choose_solver,
    corrected_solver,
    lost_in_reselection,
    named_only_under_converged,
    recheck_with_named,
    solver_settings,
)
from rwm_gym.gap.world_model import WorldModelGapConfig, compare_predictors, config_dict, fine_tune, regenerate
from rwm_gym.model.evaluate import plot_curves
from rwm_gym.options import check_ranges, option
from rwm_gym.physics.params import PhysicsParams, SolverSettings
from rwm_gym.physics.robot import RobotLayout
from rwm_gym.resources import assets_dir
from rwm_gym.spec import shipped_spec


@dataclass(frozen=True)
class GapConfig:
    """Data handling of the workflow (the fit's own options are `FitConfig`, the floor's `FloorConfig`)."""

    val_fraction: float = option(0.34, gt=0, lt=1)
    """Share of measured episodes held out (never fitted); at least one."""
    split_seed: int = 0
    fit_stride: int = option(8, ge=1)
    """Rows between the starts of fitting windows."""
    eval_stride: int = option(5, ge=1)
    """Rows between the starts of held-out windows."""
    warmup: int = option(WARMUP, ge=0)
    """Measured steps replayed before each window (fills the actuator delay buffer and the solver's warm start)."""
    learned_correction: bool = True
    """Learn a residual torque when a gap above the noise floor remains (`gap.learned`)."""
    solver: SolverSettings | None = None
    """MuJoCo solver settings of every re-simulation, on top of the sim env's (None: the sim env's own, its `solver`
    kwarg or its MJCF's, so the gap is that of the simulator as it runs; `CONVERGED_SOLVER`: each step solved to
    convergence). A solver too coarse for the data is the `contact_solver` effect."""
    solver_check: bool = True
    """Fit the first selection step under a converged solve too, and re-simulate with it where it reproduces the data
    materially better than the sim env's own solver (`gap.solver_check`; a no-op where that is converged)."""
    bootstrap: int = option(0, ge=0)
    """Resamples of the fitting episodes (drawn with replacement) on which the named effects are refitted, for the
    bootstrap std and 95 % interval of each fitted value in the report (`gap.bootstrap`; 0: none). Each costs about
    one local fit."""

    def __post_init__(self) -> None:
        check_ranges(self)


@dataclass
class _Selected:
    """What the workflow found under one solver: the vocabulary, the nominal re-simulation and its gap, the sensor
    noise check, the floor and its test, and the selection."""

    effects: dict
    nominal_sim: np.ndarray
    before: np.ndarray
    noise_check: dict
    floor_noise: SensorNoise
    floor: np.ndarray
    floor_test: dict
    floor_of: Callable[[PhysicsParams], np.ndarray]
    selection: Selection


def scored_horizon(data: Dataset, held_ids: np.ndarray, warmup: int) -> int:
    """Steps of the held-out windows: the last of `GAP_HORIZONS`, or, where no held-out episode is long enough for it
    (a robot that falls within a second), as many as the shortest one has, so that every one is scored."""
    lengths = np.asarray(data.episode_lengths)[held_ids] - warmup - 1
    return GAP_HORIZONS[-1] if lengths.max() >= GAP_HORIZONS[-1] else int(max(1, lengths.min()))


def held_out_windows(data: Dataset, config: GapConfig) -> tuple[np.ndarray, np.ndarray, Windows]:
    """The fitting and held-out episodes of `data`, and the held-out windows the gap is scored on."""
    train_ids, held_ids = data.split_episodes(config.val_fraction, config.split_seed)
    horizon = scored_horizon(data, held_ids, config.warmup)
    return train_ids, held_ids, make_windows(data, held_ids, horizon, config.eval_stride, config.warmup)


def run_gap(
    sim: str,
    measured: str | Path,
    out: str | Path,
    *,
    sim_kwargs: dict | None = None,
    config: GapConfig = GapConfig(),
    fit_config: FitConfig = FitConfig(),
    floor_config: FloorConfig = FloorConfig(),
    sensor_noise: SensorNoise = SensorNoise(),
    learned_config: LearnedCorrectionConfig = LearnedCorrectionConfig(),
    progress: bool = True,
    world_model: str | Path | None = None,
    wm_config: WorldModelGapConfig = WorldModelGapConfig(),
) -> dict:
    """Run the workflow and write `out/report.json` (+ md, plots, corrected model); returns the report dict.

    sensor_noise: the measured data's sensor noise (data-sheet values for a real robot), for the noise floor.
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
    train_ids, held_ids, held = held_out_windows(data, config)
    horizon = held.horizon
    train = make_windows(data, train_ids, fit_config.fit_horizon, config.fit_stride, config.warmup)
    resim = Resimulator(spec, sim_kwargs.get("xml_file"), solver=core.solver.then(config.solver))
    held, dropped_held = drop_diverged(resim, held, base, measured)
    held = gap_ceiling(resim, held, base)
    train, dropped_train = drop_diverged(resim, train, base, measured)
    choice = SolverChoice(
        resim, {"checked": False, "taken": "own", "reason": "not asked for (GapConfig.solver_check)"}, None
    )
    if config.solver_check:
        choice = choose_solver(resim, train, held, base, fit_config, progress)

    def select_under(choice: SolverChoice) -> _Selected:
        resim = choice.resim
        effects = vocabulary(spec, sim_kwargs.get("xml_file"), resim.solver)
        nominal_sim = resim.rollout(held, base)
        before = gap_per_window(spec, nominal_sim, held)
        noise_check = sensor_noise_check(resim, data, held, base, sensor_noise)
        floor_noise = noise_check.pop("floor_noise")
        floor = noise_floor(resim, held, base, floor_noise, floor_config)
        floor_test = compare_with_floor(before, floor, held, fit_config.block_rows, floor_config)
        # a step may test its best candidate, or a later step its gap, on every episode, and so may the test of two
        # rivals
        cross = _cross_fit_windows(resim, data, train_ids, held_ids, horizon, base, measured, config, fit_config)
        floor_of = _floor_of(resim, held, floor_noise, floor_config)
        selection = select_effects(
            effects,
            spec,
            resim,
            train,
            held,
            base,
            before,
            floor,
            fit_config,
            floor_config,
            progress,
            cross,
            choice.first_step,
            floor_of=floor_of,
        )
        return _Selected(effects, nominal_sim, before, noise_check, floor_noise, floor, floor_test, floor_of, selection)

    chosen = select_under(choice)
    # an effect named by its spread is the own solver's spread, no least-squares fit to refit under another solve
    if chosen.selection.named and chosen.selection.named[0][1].spread is None:
        rechecked = recheck_with_named(
            choice, chosen.selection.named, train, held, base, chosen.selection.gap_after, fit_config
        )
        if rechecked.resim is not choice.resim:
            again = select_under(rechecked)
            check = lost_in_reselection(rechecked.check, again.selection.gap_after)
            if check["taken"] == "converged":
                chosen, rechecked = again, dataclasses.replace(rechecked, check=check)
            else:
                rechecked = dataclasses.replace(choice, check=check)
        choice = rechecked
    elif not chosen.selection.named and choice.converged is not None and chosen.floor_test["above_floor"]:
        other, memo = choice.converged
        again = select_under(SolverChoice(other, choice.check, memo))
        check = named_only_under_converged(
            choice.check, chosen.selection.gap_after, again.selection.named, again.selection.gap_after, held, fit_config
        )
        if check["taken"] == "converged":
            chosen, choice = again, SolverChoice(other, check, memo)
        else:
            choice = dataclasses.replace(choice, check=check)
    resim, selection, floor = choice.resim, chosen.selection, chosen.floor
    corrected_params, after = selection.params, selection.gap_after
    spread = bootstrap(
        selection.named,
        resim,
        train,
        base,
        fit_config,
        config.bootstrap,
        config.split_seed,
        chosen.floor_of,
    )
    carried = corrected_params.replace(solver=corrected_solver(resim, choice.check))  # what the corrected env runs
    corrected_floor, residual = _residual(held, selection, floor, after, chosen.floor_of, fit_config, floor_config)
    learned = None
    if config.learned_correction and chosen.floor_test["above_floor"] and residual["above_floor"]:
        learned = learned_section(
            resim, train, held, corrected_params, after, corrected_floor, out, learned_config, fit_config, floor_config
        )
    corrected_sim = resim.rollout(held, corrected_params) if selection.named else chosen.nominal_sim

    plots, located = _plots(spec, held, horizon, chosen.nominal_sim, corrected_sim, chosen.before, out)
    numbers = _gap_numbers(chosen.before, after, gap_horizons(horizon))
    distribution = distribution_gap(resim, data, held, base, corrected_params, sensor_noise)
    by_spread = any(fit.spread is not None for _, fit in selection.named)
    report = {
        **named_section(selection, spread),
        "bootstrap": spread,
        **numbers,
        "distribution_gap": distribution,
        "gap_measure": headline(numbers, distribution, by_spread),
        "noise_floor": {
            **chosen.floor_test,
            "sensor_noise": dataclasses.asdict(sensor_noise),
            "floor_sensor_noise": dataclasses.asdict(chosen.floor_noise),
            "noise_check": chosen.noise_check,
            "method": "nominal re-simulation of the held-out windows read through the sensor-noise "
            f"model and re-simulated again, mean of {floor_config.draws} draws",
        },
        "residual": residual,
        "dropped_windows": {"held_out": dropped_held, "fitting": dropped_train},
        "identifiability": identifiability(
            chosen.effects, resim, held, base, chosen.nominal_sim, chosen.floor_test["floor"]
        ),
        "where": located,
        "selection_steps": selection.steps,
        "candidates": selection.steps[0]["candidates"],
        "rejected": rejections(selection),
        "learned_correction": learned,
        "held_out_episodes": [int(e) for e in held_ids],
        "fit_episodes": [int(e) for e in train_ids],
        "corrected_physics": carried.to_dict(),
        "corrected": write_corrected(spec, carried, out, sim_kwargs.get("xml_file"), sim_kwargs),
        "plots": plots,
        "sim": sim,
        "solver": {**solver_settings(resim), "source": solver_source(config), "check": choice.check},
        "measured": str(measured),
        "config": {
            "gap": dataclasses.asdict(config),
            "fit": dataclasses.asdict(fit_config),
            "floor": dataclasses.asdict(floor_config),
        },
    }
    if world_model is not None:
        report["world_model"] = world_model_rows(
            sim,
            sim_kwargs,
            data,
            train_ids,
            held_ids,
            resim,
            base,
            carried,
            Path(world_model),
            out,
            wm_config,
            config.warmup,
            progress,
        )
        report["plots"]["world_model"] = report["world_model"]["plot"]
    write_json(out / "report.json", report)
    atomic.write_text(out / "report.md", markdown(report))
    return report


def _cross_fit_windows(
    resim: Resimulator,
    data: Dataset,
    train_ids: np.ndarray,
    held_ids: np.ndarray,
    horizon: int,
    base: PhysicsParams,
    measured: str | Path,
    config: GapConfig,
    fit_config: FitConfig,
) -> Callable[[], CrossFit]:
    """The swapped windows for 2-fold cross-fitting (fit on the held-out episodes, score on the fitting ones), built
    only if a test needs them (a step's best that fails only its held-out test, a later step's floor test on every
    episode, or what one of two rivals adds on top of the other). Built once."""

    built: list[CrossFit] = []

    def cross() -> CrossFit:
        if not built:
            fit = make_windows(data, held_ids, fit_config.fit_horizon, config.fit_stride, config.warmup)
            score = make_windows(data, train_ids, horizon, config.eval_stride, config.warmup)
            score = gap_ceiling(resim, drop_diverged(resim, score, base, measured)[0], base)
            built.append(CrossFit(drop_diverged(resim, fit, base, measured)[0], score))
        return built[0]

    return cross


def _floor_of(
    resim: Resimulator, held: Windows, noise: SensorNoise, floor_config: FloorConfig
) -> Callable[[PhysicsParams], np.ndarray]:
    """`noise_floor` of a simulator on the held-out windows (or on `windows`, not kept), the last two kept: the
    residual test asks again for the simulator whose floor the last selection step tested (unless a refit changed
    it), and a step that checks its pick against the pick's own floor asks for one more before it."""
    kept: list[tuple[PhysicsParams, np.ndarray]] = []

    def floor_of(params: PhysicsParams, windows: Windows | None = None) -> np.ndarray:
        if windows is not None:
            return noise_floor(resim, windows, params, noise, floor_config)
        for known, floor in kept:
            if known == params:
                return floor
        kept[:] = [*kept[-1:], (params, noise_floor(resim, held, params, noise, floor_config))]
        return kept[-1][1]

    return floor_of


def _residual(
    held: Windows,
    selection: Selection,
    floor: np.ndarray,
    after: np.ndarray,
    floor_of: Callable[[PhysicsParams], np.ndarray],
    fit_config: FitConfig,
    floor_config: FloorConfig,
) -> tuple[np.ndarray, dict]:
    """The floor of the corrected simulator (`floor_of`), and the test of what is left against it."""
    # what is left is judged against the corrected simulator's own floor: a slippery floor or a soft joint carries
    # the same sensor noise further than the nominal simulator does (ground friction 0.3 on walking data: 2.9x)
    corrected_floor = floor_of(selection.params) if selection.named else floor
    residual = {
        **compare_with_floor(after, corrected_floor, held, fit_config.block_rows, floor_config),
        "floor_of": "the corrected simulator" if selection.named else "the nominal simulator",
    }
    return corrected_floor, residual


def _plots(
    spec, held, horizon: int, nominal_sim: np.ndarray, corrected_sim: np.ndarray, before: np.ndarray, out: Path
) -> tuple[dict[str, str], dict]:
    """The residual per channel and the worst window's rollout, as PNGs in `out`; their paths and where the gap
    lives (`locate_gap`)."""
    plots = {"channels": str(out / "residual_channels.png"), "rollout": str(out / "rollout_overlay.png")}
    h5 = min(5, horizon) - 1
    per_channel = [
        (normalised_residual(spec, s[:, h5], held.target[:, h5]) ** 2).mean(0) for s in (nominal_sim, corrected_sim)
    ]
    plot_channels(spec, *per_channel, Path(plots["channels"]), 5)
    located = locate_gap(spec, nominal_sim, held)
    top = [c["channel"] for c in located["channels_h5"][:3]]
    worst = int(np.argmax(before.mean(1)))
    plot_rollout(spec, held.target[worst], nominal_sim[worst], corrected_sim[worst], top, Path(plots["rollout"]))
    return plots, located


def _gap_numbers(before: np.ndarray, after: np.ndarray, horizons) -> dict:
    """The report's gap before and after correction: means, per horizon, and what it measures."""
    return {
        "explained_fraction": float(1.0 - after.mean() / before.mean()),
        "gap_before": float(before.mean()),
        "gap_after": float(after.mean()),
        "gap_horizons": list(horizons),
        "gap_before_per_horizon": {str(h): float(v) for h, v in zip(horizons, before.mean(0))},
        "gap_after_per_horizon": {str(h): float(v) for h, v in zip(horizons, after.mean(0))},
        "gap_metric": "normalised state MSE ((sim - measured) / spec state std)^2 at each horizon, held-out windows",
    }


def sensor_noise_check(
    resim: Resimulator, data: Dataset, held: Windows, base: PhysicsParams, assumed: SensorNoise
) -> dict:
    """The measured data's sensor noise estimated from the data (`noise_estimate`) beside the assumed model, and the
    noise the floor is computed with ("floor_noise", popped by the caller)."""
    layout = RobotLayout.from_model(resim.model(base), resim.spec)
    measured = measured_noise(data, layout, np.arange(data.num_episodes))
    twin = resim.simulate(held, base)
    leak = quantity_noise(channels(layout, twin["qpos"], twin["qvel"], twin["joint_torque"]))
    floor_noise, table = noise_for_floor(assumed, estimate_noise(measured, leak))
    return {
        "floor_noise": floor_noise,
        "quantities": table,
        "method": f"robust std of the order-{DIFFERENCE_ORDER} differences of every measured episode, less (in "
        "variance) that of the nominal re-simulation of the held-out windows (the motion's own leak); the floor takes "
        f"a resolved estimate where it differs from the assumed value by more than {MATERIAL_RATIO}x either way",
    }


def solver_source(config: GapConfig) -> str:
    """Where the solver settings the check started from came from."""
    return "the sim env's own" if config.solver is None else "the sim env's with --solver-iterations on top"


def drop_diverged(resim: Resimulator, windows, params, measured) -> tuple[object, str | None]:
    """The windows without those where the nominal simulator itself blows up (said in the report, never silent);
    a one-line error if it blows up in most of them."""
    try:
        resim.rollout(windows, params)
        return windows, None
    except SimulationDiverged as err:
        if err.windows.mean() > 0.5:
            raise ValueError(
                f"{measured}: the nominal simulator blows up re-simulating the measured data ({err.reason})"
            ) from err
        return windows.subset(~err.windows), f"dropped: the nominal simulator blows up there ({err.reason})"


def named_section(selection: Selection, spread: dict | None = None) -> dict:
    """The report's verdict: `effect` (the first named, `unexplained` or `none`), `effects` in order with their
    share of the explained gap (and, with a bootstrap `spread`, each parameter's), and every named parameter flat in
    `parameters` / `units` / `uncertainty`."""
    boot = (spread or {}).get("parameters", {})
    named = [
        {
            "effect": e.name,
            "scope": f.scope,
            "parameters": dict(zip(f.names, f.values)),
            "units": dict(zip(f.names, f.units)),
            "uncertainty": dict(zip(f.names, f.uncertainty)),
            **({"bootstrap": {n: boot[n] for n in f.names}} if boot else {}),
            "share_of_explained_gap": share,
        }
        for (e, f), share in zip(selection.named, selection.shares)
    ]
    flat = {
        key: {k: v for item in named for k, v in item[key].items()} for key in ("parameters", "units", "uncertainty")
    }
    return {
        "effect": selection.verdict,
        "reason": selection.reason,
        "scope": named[0]["scope"] if named else None,
        "effects": named,
        **flat,
        "joint_refit": selection.joint_refit,
        "simpler_forms": selection.simpler_forms,
        "idle_effects": selection.idle_effects,
    }


def rejections(selection: Selection) -> list[dict]:
    """Every parameter point or candidate rejected because the simulation blew up, with the reason."""
    out = []
    for k, step in enumerate(selection.steps):
        for c in step["candidates"]:
            out += [{"step": k + 1, "effect": c["effect"], "scope": c["scope"], "point": r} for r in c["rejected"]]
            if c["status"] != "ok":
                out.append({"step": k + 1, "effect": c["effect"], "scope": c["scope"], "point": c["status"]})
    return out


def learned_section(
    resim: Resimulator,
    train: Windows,
    held: Windows,
    params,
    after: np.ndarray,
    floor: np.ndarray,
    out: Path,
    config: LearnedCorrectionConfig,
    fit_config: FitConfig,
    floor_config: FloorConfig,
) -> dict:
    """Fit the residual torque on the effects' fitting windows and judge it on the held-out windows."""
    try:
        correction, info = fit_learned_correction(resim, train, params, config)
    except SimulationDiverged as err:
        return {"kind": "learned", "status": f"rejected: {err.reason}", "config": dataclasses.asdict(config)}
    path = out / "learned_correction.safetensors"
    save_correction(correction, path, config, resim.spec)
    try:
        corrected = gap_per_window(resim.spec, resim.rollout(held, params, correction=correction), held)
    except SimulationDiverged as err:
        return {
            "kind": "learned",
            "status": f"rejected: the simulation blows up with it ({err.reason})",
            "path": str(path),
            "training": info,
            "config": dataclasses.asdict(config),
        }
    p_value = paired_p_value(after.mean(1), corrected.mean(1), held, fit_config.block_rows, fit_config.significance)
    return {
        "kind": f"learned residual joint torque (linear in each joint's state, per {config.scope}), not a named effect",
        "status": "ok",
        "gap_before": float(after.mean()),
        "gap_after": float(corrected.mean()),
        "explained_fraction": float(1.0 - corrected.mean() / after.mean()),
        "p_value": p_value,
        "kept": bool(p_value < fit_config.significance and corrected.mean() < after.mean()),
        "residual": compare_with_floor(corrected, floor, held, fit_config.block_rows, floor_config),
        "path": str(path),
        "training": info,
        "config": dataclasses.asdict(config),
        "note": "applied in re-simulation as qfrc_applied; corrected_model.xml and corrected_physics.json do not "
        "hold it",
    }


def world_model_rows(
    sim: str,
    sim_kwargs: dict,
    data: Dataset,
    train_ids: np.ndarray,
    held_ids: np.ndarray,
    resim: Resimulator,
    base,
    corrected,
    checkpoint: Path,
    out: Path,
    config: WorldModelGapConfig,
    warmup: int,
    progress: bool,
) -> dict:
    """Regenerate, fine-tune and compare (see `gap.world_model`); the report's `world_model` section."""
    checkpoints: dict[str, Path] = {"world_model_nominal": checkpoint}
    control = config.control and corrected != base  # with nothing corrected the control is the same run
    runs = [("world_model_corrected", corrected)] + ([("world_model_control", base)] if control else [])
    for name, params in runs:
        sim_data = regenerate(sim, sim_kwargs, params, config, out / f"{name}_sim_data.h5")
        checkpoints[name] = fine_tune(
            checkpoint, sim_data, data, train_ids, out / f"{name}.safetensors", config, progress
        )
        sim_data.unlink()
    result = compare_predictors(resim, data, held_ids, base, corrected, checkpoints, config, warmup)
    if not result["error"]:
        raise ValueError(
            f"{data.path}: field 'episode_lengths': no held-out episode has {config.history} + "
            f"{min(config.horizons)} rows, needed for the world-model rows"
        )
    plot = out / "world_model_error.png"
    plot_curves(result.pop("curve"), plot, title="held-out measured episodes: relative error vs open-loop steps")
    return {
        **result,
        "checkpoints": {k: str(v) for k, v in checkpoints.items()},
        "plot": str(plot),
        "metric": "relative error sum|pred - true| / sum|true| of the normalised state, mean over the first N "
        "rows (rwm_gym.model.evaluate); sims re-simulated open loop from the measured state",
        "config": config_dict(config),
    }


def resolve_world_model(choice: str, sim: str, sim_kwargs: dict) -> Path | None:
    """The --world-model checkpoint: a path, `none`, or `auto` (the shipped one for a stock shipped simulator)."""
    if choice == "none":
        return None
    if choice == "auto":
        spec = shipped_spec(sim)
        shipped = spec.default_checkpoint if spec else ""
        return assets_dir() / shipped if shipped and not sim_kwargs.get("xml_file") else None
    return Path(choice)

"""Error against compute budget: which world model to train for a given number of CPU-minutes, per robot.

For every robot and every row of ROWS (RWM, MLP, RSSM, Transformer, "no change" as the reference; RWM ablations on
request), train from scratch with `rwm_gym.model.train` and `model_config_for(kind, spec)` (TrainConfig's defaults:
history 32, forecast 8, batch 64, Adam 1e-3, cosine to 5 %) to each budget of `--budgets` CPU-minutes, and score the
held-out episodes as `benchmarks/cross_robot.py` does: relative L1 error of open-loop mean forecasts at 8, 32 and
100 steps after 32 true steps.

Budgets. CPU time is `time.process_time()` of this process at one torch thread, so other jobs on the machine do not
count. Each (robot, row) first times `--calibration-iterations` iterations (after two warm-up ones) and converts
every budget to iterations with that rate; the rate is stored with the row's results, so a resumed run trains the
same iterations and ends at the same numbers (`--seconds-per-iteration` fixes the rate instead: exact budgets on any
machine). Beside each budget the CPU time the training loop really took is recorded, and it is the x of the figures.

Incremental. The model at budget b_k is the model at b_{k-1} trained on: weights, Adam moments and RNG states come
from its checkpoint (`OUT/runs/ROBOT/ROW.safetensors`), and the learning rate runs a fresh cosine over the added
iterations (a warm restart, `TrainConfig.schedule_start`). Budgets 4x apart leave the last restart 3/4 of the budget,
close to a run given the whole budget at once; a schedule over the largest budget would leave every smaller one
unannealed, and a constant rate anneals none. A killed run resumes from the last checkpoint to the same result.

Robots: the shipped dm_control domains (random + noisy action mix of `cross_robot.collect_mix`), ANYmal D (the
shipped demonstration file `assets/checkpoints/anymal_d_demos.h5`, scored on its held-out episodes), and any suite
task as DOMAIN-TASK (e.g. fish-swim), whose spec `rwm-gym spec --from-dmc` writes to `OUT/specs/` before the mix is
collected from it.

Writes `results.json`, `results.md` (the winner per robot, budget and horizon, and every row's error at 100 steps),
one `ROBOT.png` per robot (error at 100 and 32 steps against CPU-minutes, log x) and, with `--write-recommendation
PATH`, the table `rwm-gym train --model auto` reads (`rwm_gym.model.choice`).

    python benchmarks/budget_curve.py                                    # every robot, 1 4 16 64 CPU-minutes
    python benchmarks/budget_curve.py --robots DMC-Cheetah-Run-v0 --budgets 0.25 1 --write-recommendation m.json
    python benchmarks/budget_curve.py --rows RWM,RWM-curriculum,RWM-nll --robots AnymalD-MuJoCo-v0   # ablations
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).parent))  # the cross-robot benchmark, a sibling script
from cross_robot import collect_mix, forecast_errors

from rwm_gym.atomic import save_png, write_json, write_text
from rwm_gym.data.dataset import Dataset
from rwm_gym.model import TrainConfig, model_config_for
from rwm_gym.model.checkpoint import read_meta
from rwm_gym.model.choice import Measurement, ModelChoiceTable
from rwm_gym.model.train import train
from rwm_gym.options import option, parse_dataclass_args
from rwm_gym.registration import DMC_SPECS
from rwm_gym.resources import assets_dir

# row -> (model kind, TrainConfig fields, ModelConfig fields) on top of the common recipe
ROWS: dict[str, tuple[str, dict, dict]] = {
    "RWM": ("rwm", {}, {}),
    "MLP": ("mlp", {}, {}),
    "RSSM": ("rssm", {}, {}),
    "Transformer": ("transformer", {}, {}),
    "no-change": ("no_change", {}, {}),
    "RWM-curriculum": ("rwm", {"forecast_curriculum": (8, 32, 100)}, {}),
    "RWM-history16": ("rwm", {"history": 16}, {}),
    "RWM-small": ("rwm", {}, {"hidden_size": 128, "head_hidden": 64}),
    "RWM-lr3e-3": ("rwm", {"lr": 3e-3}, {}),
    "RWM-nll": ("rwm", {"loss": "nll"}, {}),
}
"""The kinds, then RWM ablations (one field each: forecast 8 -> 32 -> 100 in thirds of each budget step, history 16,
half the width, 3x the learning rate, the Gaussian nll loss from the first step instead of mse on samples)."""
ANYMAL = "AnymalD-MuJoCo-v0"
DEFAULT_ROBOTS = (*sorted(DMC_SPECS), ANYMAL, "fish-swim", "ball_in_cup-catch")
EVAL_HISTORY = 32
"""True steps every model warms up on before the scored forecast (whatever history a row trains with)."""


@dataclass(frozen=True)
class Options:
    """World-model error against CPU-minute budgets, per robot and model kind."""

    out: Path = Path("benchmarks/results/budget_curve")
    """Folder for data, specs, per-row checkpoints and results, results.json, results.md and ROBOT.png."""
    robots: str = ",".join(DEFAULT_ROBOTS)
    """Comma-separated robots: dm_control physics ids, AnymalD-MuJoCo-v0, or suite tasks DOMAIN-TASK."""
    rows: str = "RWM,MLP,RSSM,Transformer,no-change"
    """Comma-separated rows of ROWS (the kinds; RWM ablations by name)."""
    budgets: tuple[float, ...] = option((1.0, 4.0, 16.0, 64.0), nargs="+")
    """CPU-minute budgets per model, each continuing the previous one's model."""
    episodes: int = 16
    """Collected episodes per policy (random and noisy) and robot."""
    episode_steps: int = 400
    """Length of each collected episode (policy steps); at least 32 + max(horizons)."""
    horizons: str = "8,32,100"
    """Forecast steps at which the error is reported."""
    eval_windows: int = 256
    """Held-out windows per robot."""
    calibration_iterations: int = 20
    """Iterations timed per (robot, row) to turn CPU-minutes into iterations."""
    seconds_per_iteration: float = 0.0
    """If > 0: this many CPU seconds per iteration for every row instead of the timed calibration (exact budgets)."""
    write_recommendation: Path | None = None
    """Also write the table `rwm-gym train --model auto` reads (error at 100 steps of the kinds) to this path."""
    seed: int = 0


def hardware() -> dict:
    """CPU model, cores, load average and commit, for the provenance of the numbers."""
    cpu = next(
        (
            line.split(":", 1)[1].strip()
            for line in Path("/proc/cpuinfo").read_text().splitlines()
            if "model name" in line
        ),
        "unknown",
    )
    try:
        commit = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=Path(__file__).parent
        ).stdout.strip()
    except OSError:
        commit = ""
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "loadavg": Path("/proc/loadavg").read_text().split()[:3],
        "commit": commit,
    }


def robot_data(robot: str, options: Options) -> Path:
    """The robot's dataset: the ANYmal D demonstrations, or the random + noisy mix of a dm_control domain or of a
    suite task's generated spec (collected once into OUT/data)."""
    if robot == ANYMAL:
        return assets_dir() / "checkpoints" / "anymal_d_demos.h5"
    folder = options.out / "data"
    folder.mkdir(parents=True, exist_ok=True)
    if robot in DMC_SPECS:
        return collect_mix(robot, folder, options.episodes, options.episode_steps, options.seed)
    spec = options.out / "specs" / f"{robot}.toml"
    if not spec.exists():
        from rwm_gym.cli import main as rwm_gym

        spec.parent.mkdir(parents=True, exist_ok=True)
        if rwm_gym(["spec", "--from-dmc", robot, "--out", str(spec), "--seed", str(options.seed)]) != 0:
            raise ValueError(f"rwm-gym spec --from-dmc {robot} failed (its message is above)")
    return collect_mix(str(spec), folder, options.episodes, options.episode_steps, options.seed, name=robot)


def check_robot(robot: str) -> str | None:
    """Why `robot` is not one this benchmark can run, or None."""
    if robot in DMC_SPECS or robot == ANYMAL:
        return None
    domain, _, task = robot.partition("-")
    from dm_control import suite

    if (domain, task) in suite.ALL_TASKS:
        return None
    return f"unknown robot {robot!r} (a dm_control id such as {next(iter(DMC_SPECS))}, {ANYMAL}, or DOMAIN-TASK)"


def row_configs(row: str, dataset: Dataset, seed: int):
    kind, train_fields, model_fields = ROWS[row]
    config = TrainConfig(**{"seed": seed, **train_fields})
    return model_config_for(kind, dataset.spec(), **model_fields), config


def seconds_per_iteration(dataset: Dataset, model_config, config: TrainConfig, iterations: int) -> float:
    """CPU seconds per training iteration of `config`, timed over `iterations` after two warm-up ones (with a
    curriculum: the mean over its forecast lengths, each trained for an equal share)."""
    rates = []
    for forecast in config.forecasts:
        marks: dict[int, float] = {}
        timed = replace(config.stage_of(forecast), iterations=iterations + 2, val_every=10**9, checkpoint_every=10**9)
        train(
            dataset,
            model_config,
            timed,
            progress=False,
            clock=time.process_time,
            callback=lambda i, stats, marks=marks: marks.__setitem__(i, stats["wall_s"]),
        )
        rates.append((marks[iterations + 2] - marks[2]) / iterations)
    return float(np.mean(rates))


def budget_key(minutes: float) -> str:
    return f"{minutes:g}"


def run_row(robot: str, row: str, dataset: Dataset, options: Options, bar: tqdm) -> dict:
    """The row's curve on the robot: {"seconds_per_iteration", "budgets": {minutes: {iterations, cpu_s, errors}}},
    continued from OUT/runs/ROBOT/ROW.{json,safetensors} where a run left it."""
    folder = options.out / "runs" / robot
    record_path, checkpoint = folder / f"{row}.json", folder / f"{row}.safetensors"
    model_config, config = row_configs(row, dataset, options.seed)
    horizons = [int(h) for h in options.horizons.split(",")]
    settings = {
        "row": [model_config.to_dict(), config.to_dict()],
        "data": dataset.file_hash(),
        **{k: str(getattr(options, k)) for k in ("horizons", "eval_windows", "seed", "calibration_iterations")},
    }
    settings = json.loads(json.dumps(settings))  # as the file holds them (tuples become lists)
    record = json.loads(record_path.read_text()) if record_path.exists() else {"settings": settings, "budgets": {}}
    if record["settings"] != settings:
        raise ValueError(f"{record_path}: made with other settings or data; remove it or choose another --out")
    done = [float(b) for b in record["budgets"]]
    budgets = sorted(options.budgets)
    if done and any(b < max(done) and budget_key(b) not in record["budgets"] for b in budgets):
        raise ValueError(f"{record_path}: budgets {budgets} add one below the finished {max(done):g} CPU-minutes")
    _, val_ids = dataset.split_episodes(config.val_fraction, config.seed)
    trains = model_config.kind != "no_change"
    if trains and "seconds_per_iteration" not in record:
        record["seconds_per_iteration"] = options.seconds_per_iteration or seconds_per_iteration(
            dataset, model_config, config, options.calibration_iterations
        )
        write_json(record_path, record)
    previous_minutes, previous_iterations = 0.0, 0
    for minutes in budgets:
        key = budget_key(minutes)
        if key not in record["budgets"]:
            bar.set_postfix_str(f"{robot} {row} {key} CPU-min")
            iterations = 0
            if trains:
                iterations = max(previous_iterations + 1, round(60 * minutes / record["seconds_per_iteration"]))
                if checkpoint.exists() and read_meta(checkpoint).stats.get("iterations", 0) > iterations:
                    raise ValueError(f"{checkpoint}: trained past {iterations} iterations; remove it to start over")
                step = replace(
                    config,
                    iterations=iterations,
                    schedule_start=previous_iterations,
                    val_every=iterations,
                    checkpoint_every=max(1, (iterations - previous_iterations) // 4),
                )
                result = train(dataset, model_config, step, checkpoint, resume=True, progress=False,
                               clock=time.process_time)  # fmt: skip
            else:
                result = train(dataset, model_config, config, progress=False)
            errors = forecast_errors(
                result.model, dataset, val_ids, EVAL_HISTORY, max(horizons), options.eval_windows, options.seed, "cpu"
            )
            record["budgets"][key] = {
                "iterations": int(result.stats["iterations"]),
                "cpu_s": float(result.stats["wall_s"]) if trains else 0.0,
                "errors": {str(h): float(errors[h - 1]) for h in horizons},
            }
            write_json(record_path, record)
        if trains:
            bar.update(minutes - previous_minutes)
        previous_minutes, previous_iterations = minutes, record["budgets"][key]["iterations"]
    return {**record, "budgets": {budget_key(b): record["budgets"][budget_key(b)] for b in budgets}}


def winners_markdown(results: dict, options: Options) -> str:
    horizons = options.horizons.split(",")
    lines = [
        "Lowest held-out relative L1 error (open-loop mean forecasts after 32 true steps) per robot, CPU-minute budget "
        "and horizon; every row trained from scratch at one torch thread, each budget continuing the previous one.",
        "",
        "| robot | CPU-min | " + " | ".join(f"h={h}" for h in horizons) + " |",
        "|---|---|" + "---|" * len(horizons),
    ]
    for robot, entry in results.items():
        for key in map(budget_key, sorted(options.budgets)):
            cells = []
            for h in horizons:
                error, row = min((r["budgets"][key]["errors"][h], row) for row, r in entry["rows"].items())
                cells.append(f"{row} {error:.3f}")
            lines.append(f"| {robot} | {key} | " + " | ".join(cells) + " |")
    rows = list(next(iter(results.values()))["rows"])
    lines += ["", "Error at 100 steps (iterations):", "", "| robot | CPU-min | " + " | ".join(rows) + " |"]
    lines.append("|---|---|" + "---|" * len(rows))
    horizon = str(max(int(h) for h in horizons))
    for robot, entry in results.items():
        for key in map(budget_key, sorted(options.budgets)):
            cells = [entry["rows"][row]["budgets"][key] for row in rows]
            text = [f"{c['errors'][horizon]:.3f} ({c['iterations']})" for c in cells]
            lines.append(f"| {robot} | {key} | " + " | ".join(text) + " |")
    return "\n".join(lines) + "\n"


def plot_robot(robot: str, entry: dict, options: Options, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    shown = [h for h in ("100", "32") if h in options.horizons.split(",")]
    fig, axes = plt.subplots(1, len(shown), figsize=(5.5 * len(shown), 4), squeeze=False)
    for ax, h in zip(axes.flat, shown):
        for row, record in entry["rows"].items():
            points = list(record["budgets"].values())
            errors = [p["errors"][h] for p in points]
            if ROWS[row][0] == "no_change":
                ax.axhline(errors[0], color="k", linestyle="--", label=row)
                continue
            ax.plot([p["cpu_s"] / 60 for p in points], errors, marker="o", label=row)
        ax.set(title=f"{robot}: error at {h} steps", xlabel="CPU-minutes (process time)", ylabel="relative L1 error")
        ax.set_xscale("log")
    axes.flat[0].legend(fontsize=7)
    fig.tight_layout()
    save_png(fig, path)


def recommendation(results: dict, options: Options, machine: dict) -> ModelChoiceTable:
    """The `--model auto` table: per robot and budget, the kinds' error at 100 steps (rows that are a plain kind)."""
    run = next(iter(results.values()))["rows"]
    plain = {row: ROWS[row][0] for row in run if not ROWS[row][1] and not ROWS[row][2]}
    measurements = []
    for robot, entry in results.items():
        for key in map(budget_key, sorted(options.budgets)):
            cells = {plain[row]: entry["rows"][row]["budgets"][key] for row in plain}
            measurements.append(
                Measurement(
                    robot,
                    entry["rows_of_data"],
                    float(key),
                    {kind: c["errors"]["100"] for kind, c in cells.items()},
                    {kind: c["iterations"] for kind, c in cells.items() if kind != "no_change"},
                )
            )
    provenance = {
        "command": "python benchmarks/budget_curve.py " + " ".join(sys.argv[1:]),
        "budgets_cpu_minutes": sorted(options.budgets),
        "robots": list(results),
        "threads": 1,
        "clock": "time.process_time",
        **machine,
    }
    return ModelChoiceTable(tuple(measurements), 100, provenance)


def run_all(robots: list[str], rows: list[str], options: Options) -> dict[str, dict]:
    """Every robot's data and every row's curve on it, under one progress bar of the training CPU-minutes (the
    calibration and the scoring are not counted)."""
    trained = [r for r in rows if ROWS[r][0] != "no_change"]
    total = len(robots) * len(trained) * max(options.budgets)
    results: dict[str, dict] = {}
    with tqdm(total=total, desc="budget curve", unit="CPU-min", bar_format="{l_bar}{bar}| {n:.2f}/{total:.2f} "
              "CPU-min [{elapsed}<{remaining}{postfix}]") as bar:  # fmt: skip
        for robot in robots:
            dataset = Dataset.load(robot_data(robot, options))
            entry = {"rows_of_data": int(dataset.num_steps), "state_dim": dataset.spec().state_dim, "rows": {}}
            for row in rows:
                entry["rows"][row] = run_row(robot, row, dataset, options, bar)
            results[robot] = entry
    return results


def main(argv: list[str] | None = None) -> int:
    options = parse_dataclass_args(Options, argv)
    torch.set_num_threads(1)
    robots, rows = options.robots.split(","), options.rows.split(",")
    for problem in [check_robot(r) for r in robots] + [
        f"unknown row {r!r} (choose from {', '.join(ROWS)})" for r in rows if r not in ROWS
    ]:
        if problem:
            print(f"budget_curve: {problem}", file=sys.stderr)
            return 2
    if options.write_recommendation and "100" not in options.horizons.split(","):
        print("budget_curve: --write-recommendation needs 100 in --horizons", file=sys.stderr)
        return 2
    machine = {"hardware_start": hardware()}
    try:
        results = run_all(robots, rows, options)
    except ValueError as err:
        print(f"budget_curve: {err}", file=sys.stderr)
        return 2
    machine["hardware_end"] = hardware()
    write_json(options.out / "results.json", {"options": {k: str(v) for k, v in asdict(options).items()},
                                              **machine, "robots": results})  # fmt: skip
    table = winners_markdown(results, options)
    write_text(options.out / "results.md", table)
    for robot, entry in results.items():
        plot_robot(robot, entry, options, options.out / f"{robot}.png")
    if options.write_recommendation:
        recommendation(results, options, machine).save(options.write_recommendation)
    print(table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Forecast branches against the paper's windows: forecast windows trained per second and validation error per minute.

Two trainer settings ("arms") on the same data, model and seed: `old`, the paper's recipe (batch 64 windows of H + F
rows, one forecast each) and `new` (segments carrying `branches` forecasts, `TrainConfig.branches`).

1. Throughput, in one process: for 1 and 2 torch threads, rounds that alternate old and new (so load from other jobs
   on a shared machine falls on both), each timing a few optimiser steps; forecast windows per second (wall clock)
   and the new/old ratio per round.
2. Validation error against minutes: each arm trains for the same budget of this process's CPU minutes
   (`train(clock=time.process_time)`: other jobs' load does not count; 1 thread), validating every `val_every`
   iterations on the same held-out windows (the trainer's own metric: 8-step open-loop mean forecasts after 32 true
   rows). The learning-rate schedule spans each arm's budget.

Writes results.json, results.md and val_vs_minutes.png to --out.

    OMP_NUM_THREADS=1 python benchmarks/trainer.py --data data/anymal/mix_train.h5 --minutes 10
"""

from __future__ import annotations

import statistics
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import torch

from rwm_gym.atomic import atomic_write, save_png, write_json
from rwm_gym.data.dataset import Dataset
from rwm_gym.model import TrainConfig, build_model, model_config_for
from rwm_gym.model.factory import train_config_for
from rwm_gym.model.losses import SegmentLoss
from rwm_gym.model.normalization import Normalizer
from rwm_gym.model.train import sample_batch, train, train_step
from rwm_gym.model.windows import WindowData
from rwm_gym.options import parse_dataclass_args


@dataclass(frozen=True)
class Options:
    """Forecast-branch trainer vs the paper's windows: windows/s (1 and 2 threads) and validation error per minute."""

    data: str = "data/anymal/mix_train.h5"
    """Dataset to train on (its validation episodes are held out by the trainer)."""
    out: str = "benchmarks/results/trainer"
    """Folder for results.json, results.md and val_vs_minutes.png."""
    kinds: str = "rwm"
    """Comma-separated model kinds for the throughput part (the learning curves use the first)."""
    ensemble_size: int = 1
    """State heads of the model."""
    new_batch: int = 256
    """Forecast windows per step of the new arm."""
    new_branches: int = 32
    """Branches per segment of the new arm."""
    new_stride: int = 1
    """Rows between branch starts of the new arm."""
    new_lr: float = 1e-3
    """Learning rate of the new arm (the old arm keeps the paper's 1e-3)."""
    new_warmup_gradients: bool = True
    """Backpropagate the new arm through its teacher-forced warm-up (off: through its forecasts only)."""
    curve_arms: str = "old,new"
    """Comma-separated arms whose validation curves are trained."""
    threads: str = "1,2"
    """Comma-separated torch thread counts for the throughput part (empty: skip it)."""
    rounds: int = 3
    """Alternating old/new rounds per thread count."""
    steps: int = 4
    """Timed optimiser steps per arm and round (after one untimed step)."""
    minutes: float = 10.0
    """CPU minutes of training per arm for the validation curves (0: skip them)."""
    val_every: int = 25
    """Iterations between validations in the curves."""
    seed: int = 0


def arms(options: Options) -> dict[str, TrainConfig]:
    base = TrainConfig(
        seed=options.seed,
        iterations=0,
        minutes=max(options.minutes, 1e-3),
        val_every=options.val_every,
        checkpoint_every=10**9,
    )
    return {
        "old": base,
        "new": TrainConfig(
            **{
                **base.to_dict(),
                "batch_size": options.new_batch,
                "branches": options.new_branches,
                "branch_stride": options.new_stride,
                "lr": options.new_lr,
                "warmup_gradients": options.new_warmup_gradients,
            }
        ),
    }


def throughput(data: Dataset, kind: str, configs: dict[str, TrainConfig], options: Options, threads: int) -> dict:
    """Windows per second of each arm, rounds alternating the arms; and the new/old ratio of each round."""
    torch.set_num_threads(threads)
    spec = data.spec()
    windows = WindowData(data, Normalizer.from_spec(spec))
    train_ids, _ = data.split_episodes(0.1, options.seed)
    setups = {}
    for name, config in configs.items():
        config = train_config_for(kind, config)  # rssm keeps its warm-up gradients
        torch.manual_seed(options.seed)
        model = build_model(model_config_for(kind, spec, ensemble_size=options.ensemble_size)).train()
        params = list(model.parameters())
        starts = windows.window_starts(train_ids, config.history + config.forecast)
        setups[name] = (SegmentLoss(model, config, 1.0), torch.optim.Adam(params, lr=1e-4), params, starts, config)
    rates: dict[str, list[float]] = {name: [] for name in configs}
    for _ in range(options.rounds):
        for name, (loss_fn, optimizer, params, starts, config) in setups.items():
            batches = [sample_batch(windows, starts, config, options.ensemble_size) for _ in range(options.steps + 1)]
            train_step(loss_fn, optimizer, params, batches[0], 1.0)
            tic = time.perf_counter()
            for batch in batches[1:]:
                train_step(loss_fn, optimizer, params, batch, 1.0)
            rates[name].append(options.steps * config.batch_size / (time.perf_counter() - tic))
    ratios = [n / o for n, o in zip(rates["new"], rates["old"])]
    return {
        "windows_per_s": {k: statistics.median(v) for k, v in rates.items()},
        "rounds": rates,
        "ratio_median": statistics.median(ratios),
        "ratios": ratios,
    }


def curves(data: Dataset, kind: str, configs: dict[str, TrainConfig], options: Options) -> dict:
    """Validation log (CPU seconds, iteration, error) of each arm trained for `minutes` CPU minutes, one thread."""
    torch.set_num_threads(1)
    model_config = model_config_for(kind, data.spec(), ensemble_size=options.ensemble_size)
    out = {}
    for name, config in configs.items():
        if name not in options.curve_arms.split(","):
            continue
        result = train(data, model_config, config, progress=False, clock=time.process_time)
        out[name] = {
            "log": result.stats["log"],
            "iterations": result.stats["iterations"],
            "windows": result.stats["iterations"] * config.batch_size,
            "final_val_error": result.stats["val_error"],
        }
    return out


def error_at(log: list[dict], seconds: float) -> float | None:
    """The last validation error logged at or before `seconds`."""
    seen = [row["val_error"] for row in log if row["wall_s"] <= seconds]
    return seen[-1] if seen else None


def markdown(results: dict, options: Options) -> str:
    configs = results["arms"]
    lines = [
        f"Data {options.data}; old: batch {configs['old']['batch_size']} windows of H + F rows; new: batch "
        f"{configs['new']['batch_size']} = {configs['new']['batch_size'] // configs['new']['branches']} segments x "
        f"{configs['new']['branches']} branches (stride {configs['new']['branch_stride']}). Load average at the "
        f"start {results['loadavg_start']}, at the end {results['loadavg_end']}; new lr {configs['new']['lr']}."
    ]
    if results["throughput"]:
        lines += [
            "",
            "| model | threads | old windows/s | new windows/s | new/old (median of rounds) | per round |",
            "|---|---|---|---|---|---|",
        ]
    for row in results["throughput"]:
        rate = row["windows_per_s"]
        lines.append(
            f"| {row['kind']} | {row['threads']} | {rate['old']:.0f} | {rate['new']:.0f} | "
            f"{row['ratio_median']:.2f}x | {', '.join(f'{r:.2f}' for r in row['ratios'])} |"
        )
    if results.get("curves"):
        budget = 60 * options.minutes
        marks = [budget * f for f in (0.25, 0.5, 0.75, 1.0)]
        lines += [
            "",
            f"Validation error (8-step open-loop, held-out episodes) after CPU minutes, {options.kinds.split(',')[0]}, "
            "1 thread:",
            "",
            "| arm | " + " | ".join(f"{m / 60:.1f} min" for m in marks) + " | iterations | windows |",
            "|---" * (len(marks) + 3) + "|",
        ]
        for name, curve in results["curves"].items():
            cells = [error_at(curve["log"], m) for m in marks]
            lines.append(
                f"| {name} | "
                + " | ".join("-" if c is None else f"{c:.4f}" for c in cells)
                + f" | {curve['iterations']} | {curve['windows']} |"
            )
    return "\n".join(lines) + "\n"


def plot(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for name, curve in results["curves"].items():
        ax.plot(
            [r["wall_s"] / 60 for r in curve["log"]],
            [r["val_error"] for r in curve["log"]],
            marker=".",
            label=f"{name} ({curve['windows']} windows)",
        )
    ax.set(
        xlabel="CPU minutes (one thread)",
        ylabel="validation relative L1 error (8-step forecast)",
        yscale="log",
        title="paper windows (old) vs forecast branches (new)",
    )
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    save_png(fig, path)


def main(argv: list[str] | None = None) -> int:
    options = parse_dataclass_args(Options, argv)
    out = Path(options.out)
    out.mkdir(parents=True, exist_ok=True)
    data = Dataset.load(options.data)
    configs = arms(options)
    results: dict = {
        "options": asdict(options),
        "arms": {k: v.to_dict() for k, v in configs.items()},
        "loadavg_start": Path("/proc/loadavg").read_text().split()[0],
        "throughput": [],
    }
    for kind in options.kinds.split(","):
        for threads in (int(t) for t in options.threads.split(",") if t):
            row = throughput(data, kind, configs, options, threads)
            results["throughput"].append({"kind": kind, "threads": threads, **row})
            print(
                kind,
                threads,
                {k: round(v) for k, v in row["windows_per_s"].items()},
                f"ratio {row['ratio_median']:.2f}",
                flush=True,
            )
    if options.minutes > 0:
        results["curves"] = curves(data, options.kinds.split(",")[0], configs, options)
        plot(results, out / "val_vs_minutes.png")
    results["loadavg_end"] = Path("/proc/loadavg").read_text().split()[0]
    write_json(out / "results.json", results)
    table = markdown(results, options)
    atomic_write(out / "results.md", lambda tmp: Path(tmp).write_text(table))
    print(table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

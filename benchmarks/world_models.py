"""World-model benchmark on ANYmal D, after the RWM paper's long-horizon comparison.

Collects a data mix with `rwm_gym.data.collect` (the scripted trot with Gaussian action noise under the env's random
commands, plus random-action episodes) unless `--data` files are given; trains every model with the same budget,
seed and data: RWM autoregressive (forecast 8), RWM teacher-forced (forecast 1), MLP, RSSM and Transformer (forecast
8), and scores them with `rwm_gym.model.evaluate` on the held-out episodes: 32 true steps, then open-loop mean
predictions with the true actions; relative L1 error at N = 8, 32, 100 and the longest horizon, per state group,
and with noise on the history. The "no change" predictor is the floor any model must beat.

Writes `results.json`, `results.md` and `error_vs_horizon.png` (+ data and checkpoints) to `--out`.

    python benchmarks/world_models.py --device cuda                    # full budget
    python benchmarks/world_models.py --gait-episodes 4 --random-episodes 2 --episode-steps 200 --iterations 20
    torchrun --nproc_per_node=2 benchmarks/world_models.py ...   # data-parallel training (rank 0 collects and scores)
"""

from __future__ import annotations

import argparse
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
from tqdm import tqdm

from rwm_gym.data.collect import collect
from rwm_gym.data.dataset import Dataset, merge_datasets
from rwm_gym.model import TrainConfig, distributed, model_config_for
from rwm_gym.model.config import add_dataclass_options
from rwm_gym.model.evaluate import EvalConfig, atomic_write, evaluate_checkpoint, plot_curves, write_json
from rwm_gym.model.train import train

# name -> (model kind, training forecast steps; 1 = teacher forcing)
MODELS: dict[str, tuple[str, int]] = {
    "RWM": ("rwm", 8), "RWM-TF": ("rwm", 1), "MLP": ("mlp", 8), "RSSM": ("rssm", 8),
    "Transformer": ("transformer", 8), "no-change": ("no_change", 8),
}


@dataclass(frozen=True)
class Options:
    """ANYmal D world-model benchmark: RWM against its baselines at long horizons."""

    out: str = "benchmarks/results/world_models"
    """Folder for data, checkpoints, results.json, results.md and error_vs_horizon.png."""
    data: str = ""
    """Comma-separated dataset files to use instead of collecting (merged)."""
    env: str = "AnymalD-MuJoCo-v0"
    """Physics env to collect from."""
    gait_episodes: int = 256
    """Episodes of the noisy scripted trot under random commands."""
    random_episodes: int = 64
    """Episodes of random actions (short: the robot falls; they teach termination)."""
    action_noise: float = 0.3
    """Gaussian std added to the trot's actions."""
    episode_steps: int = 1000
    """Cap on the length of collected episodes (policy steps)."""
    num_envs: int = 32
    """Simulations stepped together while collecting."""
    workers: int = 1
    """Collection processes (each with num_envs simulations); the data is the same whatever the number."""
    iterations: int = 5000
    """Gradient steps per model (the same for every model)."""
    minutes: float = 0.0
    """Wall-clock cap per model (0: none)."""
    batch_size: int = 64
    """Windows per gradient step."""
    seed: int = 0
    device: str = "cpu"
    """torch device: cpu or cuda."""
    max_windows: int = 256
    """Held-out windows per horizon in the evaluation."""
    threads: int = 1
    """torch CPU threads (1 is fastest on a busy machine: more threads spin-wait on shared cores)."""


def dataset(options: Options) -> Path:
    """The data file: the given ones merged, or a freshly collected trot + random-action mix."""
    out = Path(options.out)
    merged = out / "data" / "anymal_mix.h5"
    if merged.exists():
        return merged
    if options.data:
        parts = [Path(p) for p in options.data.split(",")]
    else:
        parts = [collect(options.env, "gait", options.gait_episodes, out / "data" / "gait.h5", seed=options.seed,
                         num_envs=options.num_envs, action_noise=options.action_noise,
                         max_steps=options.episode_steps, overwrite=True, workers=options.workers),
                 collect(options.env, "random", options.random_episodes, out / "data" / "random.h5",
                         seed=options.seed + 1, num_envs=options.num_envs, max_steps=options.episode_steps,
                         overwrite=True, workers=options.workers)]
    if len(parts) == 1:
        return parts[0]
    merge_datasets(parts, merged)
    return merged


def markdown(results: dict, data: Dataset, options: Options, wall_s: float) -> str:
    first = next(iter(results.values()))
    horizons = [str(h) for h in first["horizons"]]
    ref = "32" if "32" in horizons else horizons[-1]  # horizon of the robustness and per-group columns
    noise, groups = list(first["noise"]), list(first["group_error"][ref])
    lines = [f"ANYmal D, {data.num_episodes} episodes / {data.num_steps} rows ({data.info.policy}); "
             f"{options.iterations} iterations x {options.batch_size} windows per model, seed {options.seed}, "
             f"device {options.device}, total {wall_s / 60:.1f} min. Relative L1 error of open-loop mean predictions "
             f"after {first['history']} true steps on {first['episodes']} held-out episodes (lower is better).", "",
             "| model | " + " | ".join(f"N={h}" for h in horizons) + f" | contact acc N={horizons[0]} | "
             + " | ".join(f"noise {s} N={ref}" for s in noise) + " | train s | eval s |",
             "|---" * (len(horizons) + len(noise) + 4) + "|"]
    for name, r in results.items():
        acc = r["contact_accuracy"][horizons[0]]
        cells = [f"{r['error'][h]:.3f}" for h in horizons] + ["-" if acc is None else f"{acc:.3f}"]
        cells += [f"{r['noise'][s][ref]:.3f}" for s in noise]
        lines.append(f"| {name} | " + " | ".join(cells) + f" | {r['train_wall_s']:.0f} | {r['eval_wall_s']:.0f} |")
    lines += ["", f"Per-group error at N={ref}:", "", "| model | " + " | ".join(groups) + " |",
              "|---" * (1 + len(groups)) + "|"]
    for name, r in results.items():
        lines.append(f"| {name} | " + " | ".join(f"{r['group_error'][ref][g]:.3f}" for g in groups) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=Options.__doc__)
    add_dataclass_options(parser, Options)
    options = Options(**vars(parser.parse_args(argv)))
    torch.set_num_threads(options.threads)
    world = distributed.init_world(options.device)  # under torchrun: rank 0 collects, writes and scores
    out = Path(options.out)
    started = time.perf_counter()
    if world.is_main:
        (out / "data").mkdir(parents=True, exist_ok=True)
        dataset(options)
    distributed.barrier(world)
    data = Dataset.load(dataset(options))
    spec = data.spec()
    evaluation = EvalConfig(max_windows=options.max_windows, seed=options.seed, device=options.device)
    results = {}
    for name, (kind, forecast) in tqdm(MODELS.items(), desc="models", unit="model", disable=not world.is_main):
        config = TrainConfig(forecast=forecast, batch_size=options.batch_size, iterations=options.iterations,
                             minutes=options.minutes, seed=options.seed, device=options.device,
                             val_every=max(1, options.iterations // 10), checkpoint_every=options.iterations)
        tic = time.perf_counter()
        trained = train(data, model_config_for(kind, spec), config, out / f"{name}.safetensors")
        wall, tic = time.perf_counter() - tic, time.perf_counter()
        if not world.is_main:
            continue
        scores = evaluate_checkpoint(trained.path, data, evaluation)
        results[name] = {**scores, "train_wall_s": wall, "eval_wall_s": time.perf_counter() - tic,
                         "iterations": trained.stats["iterations"], "val_error": trained.stats["val_error"],
                         "log": trained.stats["log"]}
    distributed.close_world()
    if not world.is_main:
        return 0
    wall = time.perf_counter() - started
    write_json({"options": asdict(options), "world_size": world.size, "rows": data.num_steps,
                "episodes": data.num_episodes, "wall_s": wall, "models": results}, out / "results.json")
    table = markdown(results, data, options, wall)
    atomic_write(out / "results.md", lambda tmp: Path(tmp).write_text(table))
    plot_curves({name: r["curve"] for name, r in results.items()}, out / "error_vs_horizon.png",
                title="ANYmal D: error vs open-loop horizon")
    print(table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""World-model benchmark on ANYmal D, after the RWM paper's long-horizon comparison.

Collects a data mix with `rwm_gym.data.collect` (the scripted trot with Gaussian action noise under the env's random
commands, plus random-action episodes) unless `--data` files are given; trains every model with the same trainer
(forecast branches, `TrainConfig.branches`), budget, seed and data, and scores them with `rwm_gym.model.evaluate` on
held-out episodes (the training file's validation episodes, or each `--test-data` file as a source of its own): 32
true steps, then open-loop mean predictions with the true actions; relative L1 error at N = 8, 32, 100 and the longest
horizon, per state group, and with noise on the history. "No change" and "predict the mean" are the floors.

The budget is equal iterations (`--iterations`) or equal minutes (`--minutes`, counted in this process's CPU time
with `--cpu-clock`, so other jobs on a shared machine do not count). `--models` picks rows of MODELS, which also holds
the ablations of the trainer and of the state constraints (RWM-branches: 8 segments x 32 branches; RWM+gravity,
RWM+limits,
RWM+physics: `ModelConfig.unit_gravity` / `joint_limits`).

Writes `results.json`, `results.md` and `error_vs_horizon_<source>.png` (+ data and checkpoints) to `--out`.

    python benchmarks/world_models.py --device cuda                    # full budget
    python benchmarks/world_models.py --gait-episodes 4 --random-episodes 2 --episode-steps 200 --iterations 20
    torchrun --nproc_per_node=2 benchmarks/world_models.py ...   # data-parallel training (rank 0 collects and scores)
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
from tqdm import tqdm

from rwm_gym.atomic import atomic_write, write_json
from rwm_gym.data.collect import collect
from rwm_gym.data.dataset import Dataset, merge_datasets
from rwm_gym.model import TrainConfig, distributed, model_config_for
from rwm_gym.model.evaluate import EvalConfig, evaluate_checkpoint, plot_running_mean
from rwm_gym.model.factory import train_config_for
from rwm_gym.model.train import train
from rwm_gym.options import parse_dataclass_args

# name -> (model kind, TrainConfig fields that differ from the common ones, ModelConfig fields)
MODELS: dict[str, tuple[str, dict, dict]] = {
    "RWM": ("rwm", {}, {}),
    "RWM-TF": ("rwm", {"forecast": 1}, {}),
    "MLP": ("mlp", {}, {}),
    "RSSM": ("rssm", {}, {}),
    "Transformer": ("transformer", {}, {}),
    "no-change": ("no_change", {}, {}),
    "RWM-branches": ("rwm", {"batch_size": 256, "branches": 32}, {}),
    "RWM+gravity": ("rwm", {}, {"unit_gravity": True}),
    "RWM+limits": ("rwm", {}, {"joint_limits": True}),
    "RWM+physics": ("rwm", {}, {"unit_gravity": True, "joint_limits": True}),
}
DEFAULT_MODELS = "RWM,RWM-TF,MLP,RSSM,Transformer,no-change"


@dataclass(frozen=True)
class Options:
    """ANYmal D world-model benchmark: RWM against its baselines at long horizons."""

    out: str = "benchmarks/results/world_models"
    """Folder for data, checkpoints, results.json, results.md and error_vs_horizon.png."""
    data: str = ""
    """Comma-separated dataset files to use instead of collecting (merged)."""
    test_data: str = ""
    """Comma-separated held-out dataset files, each scored as a source of its own (default: the validation
    episodes of the training data)."""
    models: str = DEFAULT_MODELS
    """Comma-separated rows of MODELS to train and score."""
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
    """Minutes per model (0: none); the run stops at whichever budget ends first."""
    cpu_clock: bool = False
    """Count `minutes` in this process's CPU time instead of wall-clock time (fair on a shared machine)."""
    batch_size: int = 64
    """Forecast windows per gradient step."""
    branches: int = 1
    """Forecast branches per segment (1: the paper's windows; benchmarks/trainer.py measures the settings)."""
    branch_stride: int = 1
    """Rows between the branch starts of a segment."""
    warmup_gradients: bool = True
    """Backpropagate through the teacher-forced warm-up (off: through the forecasts only; rssm keeps it on, its
    warm-up carries its KL loss)."""
    loss: str = "mse"
    """State loss of every model: mse (of reparameterised samples) or nll (Gaussian; the std then follows the error)."""
    seed: int = 0
    device: str = "cpu"
    """torch device: cpu or cuda."""
    max_windows: int = 256
    """Held-out windows per horizon in the evaluation."""
    noise: str = "0.1,0.2,0.4,0.8"
    """Comma-separated stds of the noise on the history (robustness columns; empty: none)."""
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
        parts = [
            collect(
                options.env,
                "gait",
                options.gait_episodes,
                out / "data" / "gait.h5",
                seed=options.seed,
                num_envs=options.num_envs,
                action_noise=options.action_noise,
                max_steps=options.episode_steps,
                overwrite=True,
                workers=options.workers,
            ),
            collect(
                options.env,
                "random",
                options.random_episodes,
                out / "data" / "random.h5",
                seed=options.seed + 1,
                num_envs=options.num_envs,
                max_steps=options.episode_steps,
                overwrite=True,
                workers=options.workers,
            ),
        ]
    if len(parts) == 1:
        return parts[0]
    merge_datasets(parts, merged)
    return merged


def markdown(results: dict, source: str, data: Dataset, options: Options, wall_s: float) -> str:
    first = next(iter(results.values()))[source]
    horizons = [str(h) for h in first["horizons"]]
    ref = "32" if "32" in horizons else horizons[-1]  # horizon of the robustness and per-group columns
    noise, groups = list(first["noise"]), list(first["group_error"][ref])
    budget = f"{options.iterations} iterations" if options.iterations else ""
    if options.minutes:
        budget += (" or " if budget else "") + f"{options.minutes} {'CPU ' if options.cpu_clock else ''}minutes"
    lines = [
        f"Source {source}: {first['episodes']} held-out episodes ({first['episode_set']}). Trained on "
        f"{data.num_episodes} episodes / {data.num_steps} rows; {budget} per model, batch {options.batch_size} "
        f"windows ({options.branches} branches per segment unless the row says otherwise), {options.loss} state "
        f"loss, seed {options.seed}, "
        f"device {options.device}, total {wall_s / 60:.1f} min. Relative L1 error of open-loop mean predictions "
        f"after {first['history']} true steps (lower is better); floors on the same windows.",
        "",
        "| model | " + " | ".join(f"N={h}" for h in horizons) + f" | max abs pred N={horizons[-1]} | "
        f"contact acc N={horizons[0]} | "
        + " | ".join(f"noise {s} N={ref}" for s in noise)
        + " | iterations | train s | eval s |",
        "|---" * (len(horizons) + len(noise) + 6) + "|",
    ]
    for name, by_source in results.items():
        r = by_source[source]
        acc = r["contact_accuracy"][horizons[0]]
        cells = [f"{r['error'][h]:.3f}" for h in horizons] + [f"{r['max_abs'][horizons[-1]]['prediction']:.1f}"]
        cells += ["-" if acc is None else f"{acc:.3f}"] + [f"{r['noise'][s][ref]:.3f}" for s in noise]
        lines.append(
            f"| {name} | " + " | ".join(cells) + f" | {r['iterations']} | {r['train_wall_s']:.0f} | "
            f"{r['eval_wall_s']:.0f} |"
        )
    for floor, errors in first["floors"].items():
        lines.append(
            f"| *{floor}* | "
            + " | ".join(f"{errors[h]:.3f}" for h in horizons)
            + f" | {first['max_abs'][horizons[-1]]['data']:.1f} (data) |"
            + " |" * (len(noise) + 4)
        )
    lines += [
        "",
        f"Per-group error at N={ref}:",
        "",
        "| model | " + " | ".join(groups) + " |",
        "|---" * (1 + len(groups)) + "|",
    ]
    for name, by_source in results.items():
        r = by_source[source]
        lines.append(f"| {name} | " + " | ".join(f"{r['group_error'][ref][g]:.3f}" for g in groups) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    options = parse_dataclass_args(Options, argv)
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
    evaluation = EvalConfig(
        max_horizon=368,
        max_windows=options.max_windows,
        seed=options.seed,
        device=options.device,
        noise_levels=tuple(float(s) for s in options.noise.split(",") if s),
    )
    sources = options.test_data.split(",") if options.test_data else [str(data.path)]
    clock = time.process_time if options.cpu_clock else time.monotonic
    results: dict[str, dict] = {}
    for name in tqdm(options.models.split(","), desc="models", unit="model", disable=not world.is_main):
        kind, train_fields, model_fields = MODELS[name]
        common = dict(
            batch_size=options.batch_size,
            branches=options.branches,
            branch_stride=options.branch_stride,
            warmup_gradients=options.warmup_gradients,
            loss=options.loss,
            iterations=options.iterations,
            minutes=options.minutes,
            seed=options.seed,
            device=options.device,
            val_every=max(1, options.iterations // 10 or 50),
            checkpoint_every=options.iterations or 10**9,
        )
        config = train_config_for(kind, TrainConfig(**{**common, **train_fields}))  # rssm keeps warm-up gradients
        tic = time.perf_counter()
        trained = train(
            data,
            model_config_for(kind, spec, **model_fields),
            config,
            out / f"{name}.safetensors",
            progress=False,
            overwrite=True,
            clock=clock,
        )
        wall = time.perf_counter() - tic
        if not world.is_main:  # under torchrun every rank trains, rank 0 scores and writes
            continue
        results[name] = {}
        for source in sources:
            tic = time.perf_counter()
            scores = evaluate_checkpoint(trained.path, source, evaluation, progress=False)
            results[name][Path(source).stem] = {
                **scores,
                "train_wall_s": wall,
                "train_budget_s": trained.stats["wall_s"],
                "eval_wall_s": time.perf_counter() - tic,
                "iterations": trained.stats["iterations"],
                "val_error": trained.stats["val_error"],
                "log": trained.stats["log"],
            }
        print(name, {s: [round(r["error"][h], 3) for h in r["error"]] for s, r in results[name].items()}, flush=True)
    distributed.close_world()
    if not world.is_main:
        return 0
    wall = time.perf_counter() - started
    write_json(
        out / "results.json",
        {
            "options": asdict(options),
            "world_size": world.size,
            "rows": data.num_steps,
            "episodes": data.num_episodes,
            "wall_s": wall,
            "loadavg_end": Path("/proc/loadavg").read_text().split()[0],
            "models": results,
        },
    )
    table = "\n".join(markdown(results, Path(s).stem, data, options, wall) for s in sources)
    atomic_write(out / "results.md", lambda tmp: Path(tmp).write_text(table))
    for source in sources:
        stem = Path(source).stem
        plot_running_mean(
            {name: r[stem] for name, r in results.items()},
            out / f"error_vs_horizon_{stem}.png",
            title=f"ANYmal D, {stem}: error against the open-loop horizon",
        )
    print(table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

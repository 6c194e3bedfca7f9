"""Cross-robot benchmark: one world-model recipe on every dm_control suite domain, against the baselines.

For every suite domain's `DMC-*` physics env (the Jaco arm's `DMC-Jaco-ReachSite-v0` and `DMC-Jaco-LiftBrick-v0`
with `--domains`): collect a data mix (correlated random actions plus slow, large, saturating noisy actions; for the
arm, joint velocity commands that wander the workspace: the target and the brick are in every state, though the
random hand seldom meets them, so a reach task's mix adds the scripted reach `rwm_gym.policies.reach` at four noise
levels), then train RWM (autoregressive), RWM teacher-forced, MLP, RSSM and Transformer with
the same budget and hyperparameters, plus the "no change" predictor. The recipe is the one
`benchmarks/world_models.py` uses on ANYmal D: `model_config_for(kind, spec)` (only the sizes come from each task
spec) and `TrainConfig`'s defaults (history 32, forecast 8, batch 64, Adam 1e-3 with a cosine schedule); only the
budget (`--iterations`) differs.
Each is scored on held-out episodes: warm up on `history` true steps, predict `max(horizons)` steps open-loop from
its own mean predictions, and take RWM's relative L1 error (sum |pred - true| / sum |true| over the normalised
state) at steps 8, 32 and 100.

Writes `results.json`, `results.md` (table + mean rank over domains and horizons) and `error_vs_horizon.png` to `--out`.
Each finished domain is also kept in `--out/domains/<env>.json` and reused by a later run with the same settings, so
an interrupted run resumes and disjoint `--domains` sets can run as separate processes before one run assembles the
table. The wall time reported is the sum of the domains' own wall times (collection, training, evaluation).

    python benchmarks/cross_robot.py                       # full budget on CPU (see --help)
    python benchmarks/cross_robot.py --device cuda         # same on a GPU
    python benchmarks/cross_robot.py --iterations 20 --episodes 4 --domains DMC-Cheetah-Run-v0   # smoke test
    python benchmarks/cross_robot.py --domains DMC-Jaco-ReachSite-v0,DMC-Jaco-LiftBrick-v0 --out DIR   # the arm
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from rwm_gym.atomic import save_png, write_json, write_text
from rwm_gym.data.collect import collect
from rwm_gym.data.dataset import Dataset, merge_datasets
from rwm_gym.model import TrainConfig, model_config_for
from rwm_gym.model.losses import relative_error
from rwm_gym.model.normalization import Normalizer
from rwm_gym.model.train import train
from rwm_gym.model.windows import WindowData
from rwm_gym.options import add_dataclass_options
from rwm_gym.policies.base import RandomPolicy
from rwm_gym.registration import DMC_SPECS
from rwm_gym.spec import load_spec

SUITE_IDS = sorted(
    i for i, name in DMC_SPECS.items() if load_spec(name).extra["dm_control"]["domain"] != "manipulation"
)
"""The suite domains, run by default; the Jaco arm's tasks (dm_control.manipulation) join with --domains."""

# name -> (model kind, forecast steps in training; 1 = teacher forcing)
MODELS: dict[str, tuple[str, int | None]] = {
    "RWM": ("rwm", None),
    "RWM-TF": ("rwm", 1),
    "MLP": ("mlp", None),
    "RSSM": ("rssm", None),
    "Transformer": ("transformer", None),
    "no-change": ("no_change", None),
}


@dataclass(frozen=True)
class Options:
    """Cross-robot world-model benchmark on the dm_control suite domains."""

    out: Path = Path("benchmarks/results/cross_robot")
    """Folder for data, results.json, results.md and error_vs_horizon.png."""
    domains: str = ",".join(SUITE_IDS)
    """Comma-separated physics env ids (default: the suite's; any `DMC-*` id, e.g. DMC-Jaco-ReachSite-v0)."""
    models: str = ",".join(MODELS)
    """Comma-separated models to run (default all)."""
    episodes: int = 16
    """Episodes per policy (random and noisy) and domain."""
    episode_steps: int = 400
    """Length of each collected episode (policy steps, at most the task's: 250 for the Jaco tasks); at least
    32 + max(horizons)."""
    iterations: int = 150
    """Gradient steps per model (the same for every model and domain); 150 fits ~45 min on one CPU core."""
    cpu_minutes: float = 0.0
    """If > 0: an equal budget of this process's CPU minutes per model instead (`iterations` then only caps it), so
    models are compared at equal compute, not equal steps, and other jobs on the machine do not count."""
    horizons: str = "8,32,100"
    """Forecast steps at which the error is reported."""
    eval_windows: int = 256
    """Held-out windows per domain."""
    seed: int = 0
    device: str = "cpu"
    """torch device: cpu or cuda."""
    threads: int = 1
    """torch CPU threads (1 is fastest on a busy machine)."""

    @property
    def train_config(self) -> TrainConfig:
        """The shared recipe: TrainConfig's defaults with this budget, seed and device."""
        return TrainConfig(
            iterations=self.iterations,
            minutes=self.cpu_minutes,
            seed=self.seed,
            device=self.device,
            val_every=self.iterations,
            checkpoint_every=self.iterations,
        )


REACH_NOISE = (0.0, 0.1, 0.2, 0.5)
"""Action noise of the scripted reach's episodes in a reach task's mix: clean reaches, hovers, near misses, misses."""


def mix_policies(spec, episodes: int) -> list:
    """The policies of a domain's data mix: random (rho 0.9, sigma 0.5) and noisy (rho 0.98, sigma 1.0: slow, large,
    often saturated) actions; for a reach task (`[manipulation] goal = "reach"`) also the scripted reach at each
    `REACH_NOISE`, so the data hold the states near the target that random actions seldom visit."""
    policies = []
    for rho, sigma in ((0.9, 0.5), (0.98, 1.0)):
        policy = RandomPolicy(spec, episodes, correlation=rho, scale=sigma)
        policy.name = f"random(rho={rho},sigma={sigma})"
        policies.append(policy)
    if spec.extra.get("manipulation", {}).get("goal") == "reach":
        from rwm_gym.policies.reach import ReachPolicy

        for sigma in REACH_NOISE:
            policy = ReachPolicy(spec, episodes, action_noise=sigma)
            policy.name = f"reach(sigma={sigma})"
            policies.append(policy)
    return policies


def collect_mix(
    env_id: str, folder: Path, episodes: int, episode_steps: int, seed: int = 0, name: str | None = None
) -> Path:
    """The episodes of `mix_policies`, `episodes` per policy of `episode_steps` steps, merged:
    `folder/<name or env_id>.h5` (kept if it exists). `env_id` is a dm_control physics id or the path of a task
    spec."""
    out = folder / f"{name or env_id}.h5"
    if out.exists():
        return out
    spec = load_spec(DMC_SPECS.get(env_id, env_id))
    parts = []
    for k, policy in enumerate(mix_policies(spec, episodes)):
        path = folder / f"{name or env_id}.part{k}.h5"
        collect(
            env_id,
            policy,
            episodes,
            path,
            seed=seed + 10_000 * k,
            num_envs=episodes,
            max_steps=episode_steps,
            overwrite=True,
            progress=False,
        )
        parts.append(path)
    merge_datasets(parts, out)
    for path in parts:
        path.unlink()
    return out


def horizon_errors(model, dataset: Dataset, val_ids: np.ndarray, options: Options) -> np.ndarray:
    """Mean relative error at every forecast step 1..max(horizons) over held-out windows, (max_horizon,)."""
    horizon = max(int(h) for h in options.horizons.split(","))
    return forecast_errors(
        model,
        dataset,
        val_ids,
        options.train_config.history,
        horizon,
        options.eval_windows,
        options.seed,
        options.device,
    )


@torch.no_grad()
def forecast_errors(
    model, dataset: Dataset, val_ids: np.ndarray, history: int, horizon: int, windows: int, seed: int, device: str
) -> np.ndarray:
    """Mean relative error at every forecast step 1..horizon, (horizon,): open-loop mean forecasts from the true
    actions after `history` true steps, on `windows` held-out windows drawn with `seed` from the episodes `val_ids`."""
    rows = history + horizon
    data = WindowData(dataset, Normalizer.from_spec(dataset.spec()), device)
    starts = data.window_starts(val_ids, rows)
    if len(starts) == 0:
        raise ValueError(f"{dataset.path}: no held-out episode has {rows} rows; raise --episode-steps")
    pick = torch.randperm(len(starts), generator=torch.Generator().manual_seed(seed))[:windows]
    batch = data.gather(starts[pick.to(starts.device)], rows)
    model.eval()
    prediction, _ = model.forecast(batch.states[:, :history], batch.actions[:, : rows - 1], horizon, sample=False)
    return relative_error(prediction.state_mean, batch.states[:, history:]).mean(0).cpu().numpy()


SETTINGS = (
    "episodes",
    "episode_steps",
    "iterations",
    "cpu_minutes",
    "horizons",
    "eval_windows",
    "seed",
    "device",
    "models",
)
"""Options a saved domain result must share with the current run to be reused."""


def run_domain(env_id: str, options: Options, bar: tqdm) -> dict:
    path = options.out / "domains" / f"{env_id}.json"
    settings = {k: str(getattr(options, k)) for k in SETTINGS}
    if path.exists():
        saved = json.loads(path.read_text())
        if saved.get("settings") == settings:
            bar.update(len(saved["models"]))
            return saved
    start_domain = start = time.perf_counter()
    dataset = Dataset.load(
        collect_mix(env_id, options.out / "data", options.episodes, options.episode_steps, options.seed)
    )
    spec = dataset.spec()
    base = options.train_config
    _, val_ids = dataset.split_episodes(base.val_fraction, base.seed)
    results = {
        "state_dim": spec.state_dim,
        "action_dim": spec.action_dim,
        "rows": dataset.num_steps,
        "collect_wall_s": time.perf_counter() - start,
        "models": {},
    }
    for name in options.models.split(","):
        kind, forecast = MODELS[name]
        bar.set_postfix_str(f"{env_id} {name}")
        config = replace(base, forecast=forecast or base.forecast)
        model_config = model_config_for(kind, spec)
        start = time.perf_counter()
        trained = train(dataset, model_config, config, progress=False, clock=time.process_time)
        wall = time.perf_counter() - start
        errors = horizon_errors(trained.model, dataset, val_ids, options)
        results["models"][name] = {
            "errors": errors.tolist(),
            "train_wall_s": wall,
            "kind": kind,
            "forecast": config.forecast,
            "iterations": trained.stats["iterations"],
        }
        bar.update(1)
    results.update(settings=settings, wall_s=time.perf_counter() - start_domain)
    write_json(path, results)
    return results


def mean_ranks(results: dict, horizons: list[int]) -> dict[str, float]:
    """Rank of each model (1 = lowest error) per domain and horizon, averaged."""
    names = list(next(iter(results.values()))["models"])
    ranks: dict[str, list[float]] = {name: [] for name in names}
    for domain in results.values():
        for h in horizons:
            errors = np.array([domain["models"][name]["errors"][h - 1] for name in names])
            for name, rank in zip(names, errors.argsort().argsort() + 1):
                ranks[name].append(float(rank))
    return {name: float(np.mean(r)) for name, r in ranks.items()}


def markdown(results: dict, horizons: list[int], ranks: dict[str, float], wall_s: float, options: Options) -> str:
    config = options.train_config
    collect_s = sum(domain["collect_wall_s"] for domain in results.values())
    head = "| domain | model | " + " | ".join(f"h={h}" for h in horizons) + " | iterations | train s |"
    budget = (
        f"{options.cpu_minutes:g} CPU-minutes (at most {options.iterations} iterations)"
        if options.cpu_minutes
        else f"{options.iterations} iterations"
    )
    lines = [
        (
            f"Relative L1 error of open-loop mean forecasts after {config.history} true steps on held-out episodes "
            f"(lower is better). One recipe for every domain: {budget} x "
            f"{config.batch_size} windows per model, forecast {config.forecast} (RWM-TF: 1), seed {options.seed}, "
            f"device {options.device}, {options.threads} thread(s). Data per domain: {options.episodes} "
            f"episodes per policy x {options.episode_steps} steps (random + noisy actions; a reach task also the "
            f"scripted reach at noise {', '.join(map(str, REACH_NOISE))}). Total wall time "
            f"{wall_s / 60:.1f} min (data collection {collect_s / 60:.1f} min)."
        ),
        "",
        head,
        "|" + "---|" * (len(horizons) + 4),
    ]
    for env_id, domain in results.items():
        for name, r in domain["models"].items():
            cells = " | ".join(f"{r['errors'][h - 1]:.3f}" for h in horizons)
            lines.append(
                f"| {env_id} (S={domain['state_dim']}) | {name} | {cells} | {r['iterations']} "
                f"| {r['train_wall_s']:.0f} |"
            )
    lines += [
        "",
        f"Mean rank over {len(results)} domains x {len(horizons)} horizons (1 = lowest error):",
        "",
        "| model | mean rank |",
        "|---|---|",
    ]
    lines += [f"| {name} | {rank:.2f} |" for name, rank in sorted(ranks.items(), key=lambda item: item[1])]
    return "\n".join(lines) + "\n"


def plot(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(results)
    cols = min(3, n)
    fig, axes = plt.subplots(
        (n + cols - 1) // cols, cols, figsize=(4.5 * cols, 3.5 * ((n + cols - 1) // cols)), squeeze=False
    )
    for ax, (env_id, domain) in zip(axes.flat, results.items()):
        for name, r in domain["models"].items():
            ax.plot(np.arange(1, len(r["errors"]) + 1), r["errors"], label=name)
        ax.set(title=env_id, xlabel="forecast step", ylabel="relative L1 error", yscale="log")
    for ax in list(axes.flat)[n:]:
        ax.axis("off")
    axes.flat[0].legend(fontsize=7)
    fig.tight_layout()
    save_png(fig, path)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=Options.__doc__)
    add_dataclass_options(parser, Options)
    options = Options(**vars(parser.parse_args(argv)))
    torch.set_num_threads(options.threads)
    (options.out / "data").mkdir(parents=True, exist_ok=True)
    env_ids = options.domains.split(",")
    horizons = [int(h) for h in options.horizons.split(",")]
    start, results = time.perf_counter(), {}
    unknown = sorted(set(options.models.split(",")) - set(MODELS))
    if unknown:
        parser.error(f"--models: unknown model {unknown[0]!r} (choose from {', '.join(MODELS)})")
    unknown = sorted(set(env_ids) - set(DMC_SPECS))
    if unknown:
        parser.error(f"--domains: unknown env {unknown[0]!r} (choose from {', '.join(DMC_SPECS)})")
    with tqdm(total=len(env_ids) * len(options.models.split(",")), desc="cross-robot", unit="model") as bar:
        for env_id in env_ids:
            results[env_id] = run_domain(env_id, options, bar)
    elapsed = time.perf_counter() - start
    wall = sum(domain["wall_s"] for domain in results.values())
    ranks = mean_ranks(results, horizons)
    summary = {
        "options": {k: str(v) for k, v in asdict(options).items()},
        "wall_s": wall,
        "elapsed_s": elapsed,
        "mean_rank": ranks,
        "domains": results,
    }
    write_json(options.out / "results.json", summary)
    table = markdown(results, horizons, ranks, wall, options)
    write_text(options.out / "results.md", table)
    plot(results, options.out / "error_vs_horizon.png")
    print(table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

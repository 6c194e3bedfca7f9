"""Long-horizon prediction error of a world model, as in the RWM paper (`rwm-gym evaluate`).

Windows from held-out episodes: H true rows of history (warm-up), then open-loop prediction of N rows feeding back the
mean predictions, with the true actions (causal: state[t], action[t] -> state[t+1]). Error of a predicted row =
sum |pred - true| / sum |true| over the normalised state dims; the error at horizon N is its mean over the N rows and
all windows. Reported for N = 8, 32, 100 (and the longest the episodes allow, where that is shorter), per state group
of the spec, with contact accuracy. Two extras cost more passes and are asked for: a longer cap (`max_horizon`: the
paper's 368 steps take about three times the rest together) and the robustness test (`noise_levels`: each level is
one more pass over every horizon, with Gaussian noise added to the history's states and actions).

Two floors come with every table, on the same windows and without training anything: "no change" (the last history
row predicted for ever) and "predict the mean" (the mean normalised state of the evaluated file, a constant). The
largest |predicted| and |true| normalised value per horizon say whether rollouts stay in the data's range.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from rwm_gym.atomic import save_png
from rwm_gym.data.dataset import Dataset
from rwm_gym.model.base import WorldModel
from rwm_gym.model.checkpoint import load_checkpoint
from rwm_gym.model.normalization import Normalizer
from rwm_gym.model.windows import WindowData
from rwm_gym.options import check_ranges, option, torch_device
from rwm_gym.spec import TaskSpec


@dataclass(frozen=True)
class EvalConfig:
    """How a checkpoint's long-horizon error is measured: warm-up, horizons, noise levels, windows."""

    history: int = option(32, ge=1)
    """H: true rows the model warms up on."""
    horizons: tuple[int, ...] = option((8, 32, 100), ge=1)
    """N: open-loop rows to report (plus the longest the episodes allow, up to `max_horizon`)."""
    max_horizon: int | None = option(None, ge=1)
    """Cap of the longest horizon the episodes allow, reported beside `horizons` (default: the largest of
    `horizons`; the paper's 368 costs about three times the default horizons together)."""
    noise_levels: tuple[float, ...] = option((), ge=0)
    """Stds of the Gaussian noise added to the normalised history states and actions in the robustness test (default
    none: no such test; the paper's levels are 0.1 0.2 0.4 0.8, each one more pass over every horizon)."""
    max_windows: int = option(256, ge=1)
    """Windows per horizon (a seeded subset when more fit)."""
    batch_size: int = option(512, ge=1)
    """Windows per forward pass."""
    seed: int = 0
    """Seed of the window choice and the noise."""
    device: str = option("cpu", parse=torch_device)
    """torch device of the model."""

    def __post_init__(self) -> None:
        check_ranges(self, "{field}")
        if not self.horizons or min(self.horizons) < 1:
            raise ValueError(f"horizons must be >= 1, got {list(self.horizons)}")


@torch.no_grad()
def _rollout(
    model: WorldModel,
    windows: WindowData,
    starts: torch.Tensor,
    config: EvalConfig,
    horizon: int,
    noise: float,
    generator: torch.Generator,
    data_mean: torch.Tensor,
) -> dict[str, torch.Tensor]:
    """Per-window, per-step errors (W, N, S) of |pred - true|, |true|, and contact hits (W, N, C); without noise
    also the floors' |pred - true| and the largest |pred| and |true|."""
    h = config.history
    out: dict[str, list] = {
        "abs_error": [],
        "abs_true": [],
        "contact_hit": [],
        "no_change": [],
        "mean": [],
        "max_prediction": [],
        "max_true": [],
    }
    for chunk in starts.split(config.batch_size):
        batch = windows.gather(chunk, h + horizon)
        states, actions = batch.states[:, :h], batch.actions[:, : h + horizon - 1]
        if noise > 0:
            states = states + noise * torch.randn(states.shape, generator=generator).to(states.device)
            history_noise = noise * torch.randn(actions[:, :h].shape, generator=generator).to(states.device)
            actions = torch.cat([actions[:, :h] + history_noise, actions[:, h:]], dim=1)
        prediction, _ = model.forecast(states, actions, horizon, sample=False)
        true = batch.states[:, h:]
        out["abs_error"].append((prediction.state_mean - true).abs().cpu())
        out["abs_true"].append(true.abs().cpu())
        out["contact_hit"].append(((prediction.contact_logits > 0) == (batch.contacts[:, h:] > 0.5)).cpu())
        if noise == 0:
            out["no_change"].append((batch.states[:, h - 1 : h] - true).abs().cpu())
            out["mean"].append((data_mean.to(true.device) - true).abs().cpu())
            out["max_prediction"].append(prediction.state_mean.abs().max().reshape(1).cpu())
            out["max_true"].append(true.abs().max().reshape(1).cpu())
    return {k: torch.cat(v) for k, v in out.items() if v}


def _ratio(abs_error: torch.Tensor, abs_true: torch.Tensor) -> torch.Tensor:
    """Relative error per window and step: (W, N, S') -> (W, N)."""
    return abs_error.sum(-1) / abs_true.sum(-1).clamp(min=1e-8)


def evaluate(
    model: WorldModel,
    dataset: Dataset,
    normalizer: Normalizer,
    spec: TaskSpec,
    config: EvalConfig = EvalConfig(),
    episodes: np.ndarray | None = None,
    progress: bool = True,
) -> dict:
    """The metric on `episodes` of `dataset` (default all); returns a JSON-ready dict (see module docstring)."""
    episodes = np.arange(dataset.num_episodes) if episodes is None else np.asarray(episodes)
    model = model.to(config.device).eval()
    windows = WindowData(dataset, normalizer, config.device)
    cap = max(config.horizons) if config.max_horizon is None else config.max_horizon
    longest = min(int(dataset.episode_lengths[episodes].max()) - config.history, cap)
    if longest < 1:
        raise ValueError(f"{dataset.path}: no evaluated episode is longer than the history ({config.history} rows)")
    horizons = sorted({n for n in config.horizons if n <= longest} | {longest})
    generator = torch.Generator().manual_seed(config.seed)
    data_mean = windows.states.mean(0)
    result: dict = {
        "history": config.history,
        "horizons": horizons,
        "longest": longest,
        "episodes": len(episodes),
        "episode_ids": [int(e) for e in episodes],
        "windows": {},
        "error": {},
        "group_error": {},
        "contact_accuracy": {},
        "floors": {"no change": {}, "predict the mean": {}},
        "max_abs": {},
        "running_mean_by_horizon": {},
        "noise": {str(s): {} for s in config.noise_levels},
    }
    jobs = [(n, s) for n in horizons for s in (0.0, *config.noise_levels)]
    for horizon, noise in tqdm(jobs, desc="evaluate", disable=not progress, dynamic_ncols=True):
        starts = windows.window_starts(episodes, config.history + horizon)
        pick = torch.randperm(len(starts), generator=torch.Generator().manual_seed(config.seed + horizon))
        starts = starts[pick[: config.max_windows].to(starts.device)].sort().values
        run = _rollout(model, windows, starts, config, horizon, noise, generator, data_mean)
        error = float(_ratio(run["abs_error"], run["abs_true"]).mean())
        key = str(horizon)
        if noise > 0:
            result["noise"][str(noise)][key] = error
            continue
        result["windows"][key], result["error"][key] = len(starts), error
        result["group_error"][key] = {
            name: float(_ratio(run["abs_error"][..., s], run["abs_true"][..., s]).mean())
            for name, s in spec.state_slices.items()
        }
        result["floors"]["no change"][key] = float(_ratio(run["no_change"], run["abs_true"]).mean())
        result["floors"]["predict the mean"][key] = float(_ratio(run["mean"], run["abs_true"]).mean())
        result["max_abs"][key] = {
            "prediction": float(run["max_prediction"].max()),
            "data": float(run["max_true"].max()),
        }
        per_step = _ratio(run["abs_error"], run["abs_true"]).mean(0)  # over this horizon's own windows
        result["running_mean_by_horizon"][key] = (per_step.cumsum(0) / torch.arange(1, horizon + 1)).tolist()
        hits = run["contact_hit"]
        result["contact_accuracy"][key] = float(hits.float().mean()) if hits.shape[-1] else None
        if horizon == longest:
            curve = _ratio(run["abs_error"], run["abs_true"]).mean(0)
            result["curve"] = curve.tolist()  # per-step error at step n, over the longest horizon's windows
            result["running_mean"] = (curve.cumsum(0) / torch.arange(1, len(curve) + 1)).tolist()
    return result


def format_table(result: dict) -> str:
    """The error table: one row per horizon (error, the floors, per-group errors, contact accuracy, largest |x|),
    then robustness."""
    groups = list(next(iter(result["group_error"].values())))
    floors = list(result.get("floors", {}))
    head = ["N", "windows", "error", *floors, *groups, "contact acc", "max|pred| / max|true|"]
    lines = [" | ".join(head), " | ".join("---" for _ in head)]
    for key in result["error"]:
        acc, span = result["contact_accuracy"][key], result.get("max_abs", {}).get(key)
        lines.append(
            " | ".join(
                [
                    key,
                    str(result["windows"][key]),
                    f"{result['error'][key]:.4f}",
                    *(f"{result['floors'][f][key]:.4f}" for f in floors),
                    *(f"{result['group_error'][key][g]:.4f}" for g in groups),
                    "-" if acc is None else f"{acc:.3f}",
                    "-" if span is None else f"{span['prediction']:.1f} / {span['data']:.1f}",
                ]
            )
        )
    if result["noise"]:
        lines += [
            "",
            " | ".join(["noise std", *(f"N={k}" for k in result["error"])]),
            " | ".join("---" for _ in range(len(result["error"]) + 1)),
        ]
        for level, errors in result["noise"].items():
            lines.append(" | ".join([level, *(f"{errors[k]:.4f}" for k in result["error"])]))
    return "\n".join(lines)


def plot_running_mean(results: dict[str, dict], path: str | os.PathLike, title: str = "") -> None:
    """The error the table reports against the open-loop horizon N, one line per result (model or data source).
    Between two table horizons the line is the running mean over steps 1..N of the larger one's windows (each horizon
    has its own windows: all that fit, up to `max_windows`), so it meets every table value (marker, with its window
    count) exactly; a step in the line is where the set of windows changes. PNG, log scale."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 4.8))
    for name, result in results.items():
        keys = sorted(result["error"], key=int)
        by_horizon = result.get("running_mean_by_horizon") or {}
        color, previous = None, 0
        for k in keys:  # older results without per-horizon curves get markers only
            if k not in by_horizon:
                continue
            n = np.arange(previous + 1, int(k) + 1)
            (line,) = ax.plot(
                n,
                np.asarray(by_horizon[k])[previous:],
                color=color,
                label=None if color else f"{name} (running mean of each horizon's windows)",
            )
            color, previous = line.get_color(), int(k)
        (markers,) = ax.plot(
            [int(k) for k in keys], [result["error"][k] for k in keys], "o", color=color, label=None if color else name
        )
        for k in keys:
            ax.annotate(
                f"{result['windows'][k]}",
                (int(k), result["error"][k]),
                fontsize=7,
                textcoords="offset points",
                xytext=(3, 3),
                color=markers.get_color(),
            )
    ax.set(
        xlabel="open-loop horizon N (steps after the true history)",
        ylabel="relative error, mean over steps 1..N",
        yscale="log",
        title=title or "markers: the table's values (number: windows)",
    )
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_png(fig, path)


def plot_curves(curves: dict[str, list[float]], path: str | os.PathLike, title: str = "") -> None:
    """Per-step relative error against the open-loop horizon, one line per model (PNG, log scale)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for name, curve in curves.items():
        ax.plot(np.arange(1, len(curve) + 1), curve, label=name)
    ax.set(
        xlabel="open-loop steps after the true history",
        ylabel="relative error  sum|pred-true| / sum|true|",
        yscale="log",
        title=title,
    )
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    save_png(fig, path)


def _episode_key(dataset: Dataset, episode: int) -> bytes:
    """An episode's first two rows of states and actions, as bytes: equal only for the same episode."""
    rows = slice(dataset.episode_starts[episode], dataset.episode_starts[episode] + 2)
    return dataset["state"][rows].tobytes() + dataset["action"][rows].tobytes()


def episodes_seen_in(
    dataset: Dataset, episodes: np.ndarray, training: Dataset, training_episodes: np.ndarray | None = None
) -> np.ndarray:
    """Those of `episodes` that begin, bit for bit, like an episode of `training` (default: all of its episodes): a
    held-out file collected with a training file's policy and seed repeats its episodes."""
    ids = np.arange(training.num_episodes) if training_episodes is None else training_episodes
    seen = {_episode_key(training, int(i)) for i in ids if training.episode_lengths[int(i)] >= 2}
    return np.asarray(
        [i for i in episodes if dataset.episode_lengths[i] >= 2 and _episode_key(dataset, i) in seen], dtype=np.int64
    )


def _training_files(provenance: dict, others: Sequence[str | os.PathLike]) -> list[tuple[Dataset, np.ndarray | None]]:
    """The files to check for repeated episodes: the checkpoint's training file with its training episodes, where it is
    still at its recorded path with its recorded hash, and every file of `others` whole."""
    files: list[tuple[Dataset, np.ndarray | None]] = []
    source = provenance.get("dataset")
    if source and provenance.get("train_episodes") and Path(source).is_file():
        training = Dataset.load(source)
        if training.file_hash() == provenance.get("sha256"):
            files.append((training, np.asarray(provenance["train_episodes"], dtype=np.int64)))
    return files + [(Dataset.load(path), None) for path in others]


def evaluate_checkpoint(
    checkpoint: str | os.PathLike,
    data: str | os.PathLike | Dataset,
    config: EvalConfig = EvalConfig(),
    all_episodes: bool = False,
    progress: bool = True,
    training_data: Sequence[str | os.PathLike] = (),
) -> dict:
    """Load a checkpoint and evaluate it on a dataset of the same task. When the dataset is the checkpoint's own
    training file, only its held-out validation episodes are used; from another file, episodes that repeat a training
    episode of the checkpoint's recorded file or of `training_data` are left out. `all_episodes` keeps every one."""
    dataset = data if isinstance(data, Dataset) else Dataset.load(data)
    spec = dataset.spec()
    model, meta = load_checkpoint(checkpoint, device=config.device, expect_spec=spec)
    episodes, held_out = np.arange(dataset.num_episodes), "all episodes of the file"
    if not all_episodes and meta.provenance.get("sha256") == dataset.file_hash():
        episodes, held_out = np.asarray(meta.provenance["val_episodes"], dtype=np.int64), "validation episodes"
        if len(episodes) == 0:
            raise ValueError(f"{dataset.path}: the checkpoint was trained on this file with no held-out episodes")
    elif not all_episodes:
        repeated = []
        for training, ids in _training_files(meta.provenance, training_data):
            seen = episodes_seen_in(dataset, episodes, training, ids)
            if len(seen) == len(episodes):
                sources = ", ".join([*repeated, str(training.path)])
                raise ValueError(
                    f"{dataset.path}: every evaluated episode repeats a training episode of {sources}; "
                    "collect held-out data with another seed"
                )
            if len(seen):
                episodes, repeated = np.setdiff1d(episodes, seen), [*repeated, str(training.path)]
        if repeated:
            held_out = (
                f"{len(episodes)} of {dataset.num_episodes} episodes; those repeating training episodes of "
                f"{', '.join(repeated)} left out"
            )
    result = evaluate(model, dataset, meta.normalizer, spec, config, episodes, progress)
    return {
        "checkpoint": str(checkpoint),
        "model": meta.model_config.kind,
        "data": str(dataset.path),
        "episode_set": held_out,
        "config": asdict(config),
        **result,
    }

"""World-model rows of the gap report: the correction carried into the learned model, and four predictors compared.

After the effect is named and fitted: regenerate data from the corrected simulator with the excitation policy,
fine-tune the nominal world model (trained on nominal-sim data) on it together with the measured *fitting* episodes
(`rwm_gym.model.train` with `init`), and compare on the held-out measured episodes (never used for fitting):

- `nominal_sim`, `corrected_sim`: open-loop re-simulation from the measured state at the end of the history with the
  measured actions (`gap.resim`);
- `world_model_nominal`, `world_model_corrected`: the world model warmed up on the same `history` measured rows, then
  open loop with the measured actions (`WorldModel.forecast`, mean predictions);
- `world_model_control` (optional): the same fine-tuning with nominal-sim data instead of corrected-sim data, so the
  row shows what fine-tuning on measured data alone buys and the difference to `world_model_corrected` what the
  correction adds.

Metric: the world-model metric of `rwm_gym.model.evaluate` (RWM's relative error sum|pred - true| / sum|true| over the
normalised state per row, averaged over the first N rows and all windows). Every predictor sees the same windows.
"""

from __future__ import annotations

import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from rwm_gym.data.collect import collect, make_physics_core
from rwm_gym.data.dataset import Dataset, merge_datasets, write_dataset
from rwm_gym.gap.resim import Resimulator, Windows, make_windows
from rwm_gym.model.checkpoint import load_checkpoint, read_meta
from rwm_gym.model.config import TrainConfig
from rwm_gym.model.losses import relative_error
from rwm_gym.model.normalization import Normalizer
from rwm_gym.model.train import train
from rwm_gym.model.windows import WindowData
from rwm_gym.physics.params import PhysicsParams
from rwm_gym.policies.excitation import ExcitationPolicy

PREDICTORS = ("nominal_sim", "corrected_sim", "world_model_nominal", "world_model_corrected", "world_model_control")
"""Row names of the comparison, in report order (the control row only with `control`)."""


@dataclass(frozen=True)
class WorldModelGapConfig:
    """How the world model is carried through the correction and compared."""

    episodes: int = 16
    """Episodes regenerated from the corrected simulator (excitation policy)."""
    max_steps: int = 250
    """Policy steps per regenerated episode."""
    iterations: int = 300
    """Fine-tuning budget in gradient steps, starting from the nominal world model."""
    lr: float = 3e-4
    """Adam learning rate of the fine-tuning (cosine schedule)."""
    batch_size: int = 32
    """Windows per gradient step."""
    forecast: int = 8
    """Autoregressive forecast steps of the fine-tuning loss."""
    history: int = 32
    """Measured rows the world models warm up on before each held-out window."""
    horizons: tuple[int, ...] = (1, 5, 25, 100)
    """Open-loop rows N of the comparison (those the held-out episodes are long enough for)."""
    stride: int = 5
    """Rows between the starts of held-out windows."""
    control: bool = True
    """Also fine-tune on nominal-sim data (same budget) as a control row."""
    seed: int = 10_000
    """Seed of the regenerated episodes (apart from the measured ones) and of the fine-tuning."""
    device: str = "cpu"
    """torch device of fine-tuning and evaluation."""


def regenerate(env_id: str, env_kwargs: dict, params: PhysicsParams, config: WorldModelGapConfig, out: Path) -> Path:
    """Collect `config.episodes` excitation episodes from the simulator with `params` into `out`."""
    num_envs = min(8, config.episodes)
    spec = make_physics_core(env_id, 1, **env_kwargs).spec
    return collect(
        env_id,
        ExcitationPolicy(spec, num_envs),
        config.episodes,
        out,
        seed=config.seed,
        num_envs=num_envs,
        max_steps=config.max_steps,
        env_kwargs={**env_kwargs, "physics": params},
        overwrite=True,
        progress=False,
    )


def fine_tune(
    init: str | Path,
    sim_data: Path,
    measured: Dataset,
    fit_episodes: np.ndarray,
    out: Path,
    config: WorldModelGapConfig,
    progress: bool = False,
) -> Path:
    """Fine-tune the checkpoint `init` on `sim_data` plus the measured fitting episodes; write and return `out`."""
    meta = read_meta(init)
    with tempfile.TemporaryDirectory(dir=out.parent) as tmp:
        fit_file, mixed = Path(tmp) / "measured_fit.h5", Path(tmp) / "mixed.h5"
        write_dataset(fit_file, measured.info, (measured.episode(int(e)) for e in fit_episodes))
        merge_datasets([sim_data, fit_file], mixed)
        train_config = TrainConfig(
            history=config.history,
            forecast=config.forecast,
            batch_size=config.batch_size,
            lr=config.lr,
            iterations=config.iterations,
            val_every=max(1, config.iterations),
            checkpoint_every=max(1, config.iterations),
            seed=config.seed % 2**31,
            device=config.device,
        )
        train(mixed, meta.model_config, train_config, out, progress=progress, init=init)
    return out


def held_out_windows(
    measured: Dataset, episodes: np.ndarray, history: int, horizon: int, stride: int, warmup: int
) -> Windows | None:
    """Windows of `horizon` rows whose start row leaves `history` measured rows before it (None if none fits)."""
    try:
        windows = make_windows(measured, episodes, horizon, stride, warmup)
    except ValueError:
        return None
    keep = windows.start >= history - 1
    return windows.subset(keep) if keep.any() else None


def sim_errors(resim: Resimulator, windows: Windows, params: PhysicsParams, normalizer: Normalizer) -> np.ndarray:
    """(W, N) relative error per window and row of the open-loop re-simulation with `params`."""
    simulated = resim.rollout(windows, params)
    pred, true = (torch.as_tensor(normalizer.normalize_state(x)) for x in (simulated, windows.target))
    return relative_error(pred, true).numpy()


@torch.no_grad()
def model_errors(
    checkpoint: str | Path, measured: Dataset, windows: Windows, history: int, device: str = "cpu"
) -> np.ndarray:
    """(W, N) relative error per window and row of the world model warmed up on `history` measured rows."""
    model, meta = load_checkpoint(checkpoint, device=device, expect_spec=measured.spec())
    model.eval()
    data = WindowData(measured, meta.normalizer, device)
    first = measured.episode_starts[windows.episode] + windows.start - (history - 1)
    batch = data.gather(torch.as_tensor(first, dtype=torch.long), history + windows.horizon)
    prediction, _ = model.forecast(
        batch.states[:, :history], batch.actions[:, : history + windows.horizon - 1], windows.horizon, sample=False
    )
    return relative_error(prediction.state_mean, batch.states[:, history:]).cpu().numpy().astype(np.float64)


def compare_predictors(
    resim: Resimulator,
    measured: Dataset,
    held_episodes: np.ndarray,
    nominal: PhysicsParams,
    corrected: PhysicsParams,
    checkpoints: dict[str, Path | str],
    config: WorldModelGapConfig,
    warmup: int,
) -> dict:
    """Error of every predictor at every horizon on the held-out measured episodes.

    checkpoints: {predictor name: checkpoint} of the world-model rows. Returns {"error": {name: {N: error}},
    "windows": {N: count}, "curve": {name: per-row error at the longest horizon}}.
    """
    normalizer = Normalizer.from_spec(resim.spec)
    result: dict = {"error": {}, "windows": {}, "curve": {}}
    sets = {
        n: held_out_windows(measured, held_episodes, config.history, n, config.stride, warmup)
        for n in sorted(config.horizons)
    }
    fitting = [n for n, windows in sets.items() if windows is not None]
    for n in fitting:
        windows = sets[n]
        rows = {
            "nominal_sim": sim_errors(resim, windows, nominal, normalizer),
            "corrected_sim": sim_errors(resim, windows, corrected, normalizer),
        }
        for name, path in checkpoints.items():
            rows[name] = model_errors(path, measured, windows, config.history, config.device)
        result["windows"][str(n)] = len(windows)
        for name in (p for p in PREDICTORS if p in rows):
            result["error"].setdefault(name, {})[str(n)] = float(rows[name].mean())
            if n == fitting[-1]:
                result["curve"][name] = rows[name].mean(0).tolist()
    return result


def config_dict(config: WorldModelGapConfig) -> dict:
    """The config as JSON-ready data (tuples as lists), as the report stores it."""
    return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(config).items()}

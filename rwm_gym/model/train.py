"""Dual-autoregressive training of a world model on a dataset (`rwm-gym train`).

Windows of H history + F forecast rows are drawn uniformly from the training episodes (validation is held out by
whole episode); with `branches` > 1 each drawn window start begins a longer segment that carries that many forecasts
(`branches.py`). The loss is in `losses.py`; one optimiser step is `train_step`. Adam with gradient clipping and a
learning-rate schedule over the budget
(iterations and/or minutes). A run is deterministic in its seed (weights, window sampling and forecast noise all come
from torch's seeded RNG); checkpoints saved every `checkpoint_every` iterations and on Ctrl-C hold the optimizer and
RNG states, so `--resume` continues to the same result as an uninterrupted run.

Under `torchrun --nproc_per_node=N` the same call trains data-parallel (DDP): the global batch is split over the
ranks and only rank 0 validates and writes; see `rwm_gym.model.distributed` for what each rank does and its seeds.
"""

from __future__ import annotations

import math
import os
import signal
import sys
import threading
import time
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import torch

from rwm_gym.data.dataset import Dataset
from rwm_gym.data.lineage import physics_sources
from rwm_gym.model import distributed
from rwm_gym.model.base import WorldModel
from rwm_gym.model.checkpoint import CheckpointError, load_checkpoint, load_training_state, save_checkpoint
from rwm_gym.model.config import ModelConfig, TrainConfig, config_difference
from rwm_gym.model.factory import build_model
from rwm_gym.model.heads import StateHead
from rwm_gym.model.lineage import lineage_provenance
from rwm_gym.model.losses import SegmentLoss, relative_error
from rwm_gym.model.normalization import Normalizer
from rwm_gym.model.windows import Window, WindowData, WindowMirror
from rwm_gym.progress import BudgetBar

RESUME_MAY_CHANGE = ("iterations", "minutes", "schedule_start", "device", "val_every", "checkpoint_every")
"""TrainConfig fields a resumed run may set differently (the budget and bookkeeping); the others must match."""


@dataclass
class TrainResult:
    """What `train` returns: the model, its statistics and the checkpoint written."""

    model: WorldModel
    """The trained model (train mode, on the training device)."""
    stats: dict
    """iterations, wall_s, train_loss (mean over the last validation interval), val_error, log."""
    path: Path | None
    """The checkpoint written, if any."""


def learning_rate_factor(schedule: str, progress: float) -> float:
    """Multiplier of the base learning rate at `progress` in [0, 1] of the budget."""
    progress = min(max(progress, 0.0), 1.0)
    if schedule == "cosine":
        return 0.05 + 0.95 * 0.5 * (1.0 + math.cos(math.pi * progress))
    if schedule == "step":
        return 1.0 if progress < 0.5 else 0.1 if progress < 0.75 else 0.01
    return 1.0


@contextmanager
def _deterministic(device: torch.device) -> Iterator[None]:
    """Deterministic kernels for the duration of a run; the previous global settings are restored afterwards."""
    previous = (
        torch.are_deterministic_algorithms_enabled(),
        torch.is_deterministic_algorithms_warn_only_enabled(),
        torch.backends.cudnn.deterministic,
        torch.backends.cudnn.benchmark,
    )
    if device.type == "cuda":
        os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
    torch.use_deterministic_algorithms(True, warn_only=True)
    torch.backends.cudnn.deterministic, torch.backends.cudnn.benchmark = True, False
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(previous[0], warn_only=previous[1])
        torch.backends.cudnn.deterministic, torch.backends.cudnn.benchmark = previous[2], previous[3]


@torch.no_grad()
def validation_error(model: WorldModel, windows: WindowData, starts: torch.Tensor, config: TrainConfig) -> float | None:
    """Mean relative error (RWM's metric) of open-loop mean forecasts over F steps on fixed validation windows."""
    if len(starts) == 0:
        return None
    was_training, h, f = model.training, config.history, config.forecast
    model.eval()
    total = 0.0
    for chunk in starts.split(1024):
        batch = windows.gather(chunk, h + f)
        prediction, _ = model.forecast(batch.states[:, :h], batch.actions[:, : h + f - 1], f, sample=False)
        total += float(relative_error(prediction.state_mean, batch.states[:, h:]).mean(1).sum())
    model.train(was_training)
    return total / len(starts)


@dataclass
class SegmentBatch:
    """One training batch: segments of `TrainConfig.segment_rows` rows, each the start of a window of H + F rows drawn
    uniformly; rows past an episode's end repeat its last row and the branches reaching them do not count."""

    window: Window
    """(B, R, ...) normalised rows."""
    member: torch.Tensor | None
    """(B,) long ensemble head per segment (None: one head)."""
    real_rows: torch.Tensor
    """(B,) long rows of each segment inside its episode."""


def sample_batch(
    windows: WindowData,
    starts: torch.Tensor,
    config: TrainConfig,
    ensemble_size: int,
    generator: torch.Generator | None = None,
    world: distributed.World = distributed.SINGLE,
    mirror: WindowMirror | None = None,
    recent: torch.Tensor | None = None,
) -> SegmentBatch:
    """Draw `batch_size / branches` segments uniformly from `starts` (window starts of H + F rows) and an ensemble
    head per segment, from `generator` (torch's global RNG if None; a seeded run draws the same batches). In a
    distributed world every rank draws the whole batch and keeps its slice (`distributed.shard`). With `mirror`, each
    segment is replaced by its mirror image with probability 1/2 (`TrainConfig.mirror`). With `recent` (the window
    starts of the recent episodes), the first `TrainConfig.recent_share` of the segments are drawn from those."""
    segments = config.batch_size // config.branches
    index = torch.randint(len(starts), (segments,), generator=generator)
    member = None
    if ensemble_size > 1:
        member = _upload(
            distributed.shard(torch.randint(ensemble_size, (segments,), generator=generator), world), starts.device
        )
    picked = starts[_upload(index, starts.device)]
    fresh = int(round(config.recent_share * segments)) if recent is not None and len(recent) else 0
    if fresh:
        picked[:fresh] = recent[_upload(torch.randint(len(recent), (fresh,), generator=generator), recent.device)]
    window, real_rows = windows.gather_clipped(distributed.shard(picked, world), config.segment_rows)
    if mirror is not None:
        flip = distributed.shard(torch.rand(segments, generator=generator) < 0.5, world)
        window = mirror(window, flip)
    return SegmentBatch(window, member, real_rows)


def _upload(tensor: torch.Tensor, device: torch.device) -> torch.Tensor:
    """A CPU tensor on `device`; to a GPU through pinned memory without waiting for it (a plain copy would)."""
    if device.type != "cuda":
        return tensor.to(device)
    return tensor.pin_memory().to(device, non_blocking=True)


def train_step(
    loss_fn: torch.nn.Module,
    optimizer: torch.optim.Optimizer,
    params: list[torch.nn.Parameter],
    batch: SegmentBatch,
    grad_clip: float,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """One optimiser step on one batch: loss_fn(window, member, real_rows) -> (loss, parts) (a `SegmentLoss`, or a
    data-parallel wrapper of one), backward, global-norm clip, step. Returns the loss and its parts as detached
    0-dim tensors on the device (no host copy per step)."""
    loss, parts = loss_fn(batch.window, batch.member, batch.real_rows)
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    torch.nn.utils.clip_grad_norm_(params, grad_clip)
    optimizer.step()
    return loss.detach(), parts


class _DeferredInterrupt:
    """Ctrl-C ends the run between two iterations, never inside one.

    An interrupt inside an iteration would save the RNG state after the iteration's draws beside the iteration count
    from before them, and `--resume` would then diverge from the uninterrupted run. A second Ctrl-C stops at once.
    """

    def __init__(self):
        self.requested, self._previous = False, None
        if threading.current_thread() is threading.main_thread():
            self._previous = signal.signal(signal.SIGINT, self._handle)

    def _handle(self, signum, frame) -> None:
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True

    def restore(self) -> None:
        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)


def _rng_state(device: torch.device, sampler: torch.Generator) -> dict[str, torch.Tensor]:
    """Rank 0's RNG states: the shared window sampler and its own noise stream (other ranks derive theirs)."""
    state = {"rng_torch": torch.get_rng_state(), "rng_sampler": sampler.get_state()}
    if device.type == "cuda":
        state["rng_cuda"] = torch.cuda.get_rng_state(device)
    return state


def train(
    data: Dataset | str | os.PathLike,
    model_config: ModelConfig,
    config: TrainConfig,
    out: str | os.PathLike | None = None,
    *,
    resume: bool = False,
    progress: bool = True,
    tensorboard: str | None = None,
    callback: Callable[[int, dict], None] | None = None,
    init: str | os.PathLike | None = None,
    overwrite: bool = False,
    clock: Callable[[], float] = time.monotonic,
) -> TrainResult:
    """Train a model of `model_config` on `data`; write the checkpoint to `out` (if given).

    init: start from the weights of this checkpoint (same model config and task; e.g. to fine-tune on new data);
    the optimizer starts fresh.
    resume: continue from the checkpoint at `out` if it exists (same data file, same config except the budget).
    overwrite: replace an existing `out`; without it (or `resume`) an existing `out` is refused.
    callback(iteration, stats) runs after every iteration (e.g. to stop early by raising KeyboardInterrupt, which
    saves a resumable checkpoint first).
    clock: seconds for the `minutes` budget and `wall_s` (e.g. `time.process_time` to count only this process's CPU
    time on a shared machine).
    """
    if out is not None and Path(out).exists() and not (resume or overwrite):
        raise FileExistsError(f"{out}: file exists (pass --resume to continue its run or --overwrite to replace it)")
    if config.reset_std_band and init is None:
        raise ValueError("reset_std_band resets a fine-tuned model's log-std band: give the checkpoint to start from")
    dataset = _training_data(data, model_config)
    world = distributed.init_world(config.device)
    distributed.check_batch(config.batch_size // config.branches, world)
    device, out = distributed.rank_device(config.device, world), out and Path(out)
    with _deterministic(device):
        run = _Run(dataset, model_config, config, out, world, device, clock)
        if init is not None:
            run.start_from(init)
        if resume and out is not None and out.exists():
            run.stats = _resume(out, run.model, run.optimizer, config, run.provenance["sha256"], device, run.sampler)
        distributed.reseed_rank(config.seed, world, run.stats["iterations"])
        return run.learn(progress, tensorboard, callback)


def _training_data(data: Dataset | str | os.PathLike, model_config: ModelConfig) -> Dataset:
    """The dataset (loaded if a path), warned about if its collection was interrupted, whose sizes fit the model."""
    dataset = data if isinstance(data, Dataset) else Dataset.load(data)
    if not dataset.info.complete:
        warnings.warn(
            f"{dataset.path}: complete=false (its collection was interrupted); training on its "
            f"{dataset.num_episodes} finished episodes",
            stacklevel=3,
        )
    spec = dataset.spec()
    sizes = (spec.state_dim, spec.action_dim, spec.contact_dim, spec.foot_dim)
    expected = (model_config.state_dim, model_config.action_dim, model_config.contact_dim, model_config.foot_dim)
    if expected != sizes:
        raise ValueError(
            f"{dataset.path}: data sizes (state, action, contact, foot) {sizes} differ from the model "
            f"config's {expected}"
        )
    return dataset


class _Run:
    """One training run, as rsl_rl's runner separates it: set up (model, optimizer, windows, provenance), `learn` (the
    loop), `_log` (validation and the logged means), `save` (the checkpoint). Built inside `_deterministic`."""

    def __init__(
        self,
        dataset: Dataset,
        model_config: ModelConfig,
        config: TrainConfig,
        out: Path | None,
        world: distributed.World,
        device: torch.device,
        clock: Callable[[], float],
    ):
        self.model_config, self.config, self.out, self.world, self.device, self.clock = (
            model_config,
            config,
            out,
            world,
            device,
            clock,
        )
        self.spec = spec = dataset.spec()
        self.normalizer = Normalizer.from_spec(spec)
        train_ids, val_ids = dataset.split_episodes(config.val_fraction, config.seed)
        torch.manual_seed(config.seed)
        self.sampler = torch.Generator().manual_seed(config.seed)  # window draws, identical on every rank
        self.model = model = build_model(model_config, spec).to(device).train()
        self.windows = windows = WindowData(dataset, self.normalizer, device)
        self.mirror = WindowMirror(spec, self.normalizer, device) if config.mirror else None
        pos_weight = windows.termination_pos_weight(train_ids)
        # per forecast length F trained with (one, or the curriculum's): where a window of H + F rows starts, and the
        # loss of its segments
        self.train_starts: dict[int, torch.Tensor] = {}
        self.recent_starts: dict[int, torch.Tensor] = {}  # of the last `recent_episodes` episodes that train
        recent_ids = train_ids[train_ids >= dataset.num_episodes - config.recent_episodes]
        self.loss_fns: dict[int, SegmentLoss] = {}
        for forecast in config.forecasts:
            rows = config.history + forecast
            self.train_starts[forecast] = windows.window_starts(train_ids, rows)
            self.recent_starts[forecast] = windows.window_starts(recent_ids, rows)
            if len(self.train_starts[forecast]) == 0:
                raise ValueError(f"{dataset.path}: no training episode has {rows} rows (history + forecast)")
            self.loss_fns[forecast] = SegmentLoss(model, config.stage_of(forecast), pos_weight)
        val_starts = windows.window_starts(val_ids, config.history + config.forecast)
        pick = torch.randperm(len(val_starts), generator=torch.Generator().manual_seed(config.seed))
        self.val_starts = val_starts[pick[: config.val_windows].to(val_starts.device)]
        self.params = [p for p in model.parameters() if p.requires_grad]
        self.optimizer = (
            torch.optim.Adam(self.params, lr=config.lr, weight_decay=config.weight_decay) if self.params else None
        )
        self.provenance = {
            "dataset": str(dataset.path),
            "sha256": dataset.file_hash(),
            "env_id": dataset.info.env_id,
            "dataset_steps": int(dataset.num_steps),
            "train_episodes": [int(i) for i in train_ids],
            "val_episodes": [int(i) for i in val_ids],
            "train_windows": len(self.train_starts[config.forecasts[-1]]),
            "termination_pos_weight": pos_weight,
        }
        self.data_sources = physics_sources(dataset, self.provenance["sha256"])
        self.provenance.update(lineage_provenance(self.data_sources))
        self.stats: dict = {"iterations": 0, "wall_s": 0.0, "train_loss": None, "val_error": None, "log": []}
        self.started = 0.0
        self.iteration, self.running, self.parts_sum = 0, 0.0, {}
        self._agreed = {"iteration": -1, "seconds": 0.0}

    def start_from(self, init: str | os.PathLike) -> None:
        """The weights of checkpoint `init` (same model config and task); with `reset_std_band`, its heads' log-std
        band reset."""
        loaded, meta = load_checkpoint(init, device=self.device, expect_spec=self.spec)
        if difference := config_difference(loaded.config, self.model_config):
            raise CheckpointError(f"{init}: cannot start from a model with another config ({difference})")
        self.model.load_state_dict(loaded.state_dict())
        self.provenance["init_checkpoint"] = str(init)
        self.provenance.update(lineage_provenance(self.data_sources, meta))  # its lineage's rows, and this data's
        if self.config.reset_std_band:
            for head in self.model.modules():
                if isinstance(head, StateHead):
                    head.reset_band(
                        self.model_config.log_std_min_init,
                        self.model_config.log_std_max_init,
                        self.config.reset_log_std,
                    )

    def save(self) -> Path | None:
        """The checkpoint at `out` (rank 0 only), with what `--resume` needs: optimizer, RNG states, stats."""
        if self.out is None or not self.world.is_main:
            return None
        return save_checkpoint(
            self.out,
            self.model,
            self.spec,
            normalizer=self.normalizer,
            train_config=self.config,
            provenance=self.provenance,
            stats=self.stats,
            optimizer=self.optimizer,
            training_state=_rng_state(self.device, self.sampler),
        )

    def elapsed(self) -> float:
        """Seconds into the run. Ranks must share the learning rate and the stop: with several, the slowest rank's
        time, agreed every 10 iterations."""
        if not self.world.distributed:
            return self.clock() - self.started
        agreed = self._agreed
        if self.iteration % 10 == 0 and agreed["iteration"] != self.iteration:
            agreed["iteration"] = self.iteration
            agreed["seconds"] = distributed.max_over_ranks(self.clock() - self.started, self.device, self.world)
        return agreed["seconds"]

    def finished(self) -> bool:
        config = self.config
        if self.optimizer is None:
            return True
        by_steps = config.iterations > 0 and self.iteration >= config.iterations
        return by_steps or (config.minutes > 0 and self.elapsed() >= 60 * config.minutes)

    def learn(
        self, progress: bool, tensorboard: str | None, callback: Callable[[int, dict], None] | None
    ) -> TrainResult:
        """Train until the budget is spent (or Ctrl-C, which saves a resumable checkpoint first); validate, log and
        save on the way."""
        config, stats, clock = self.config, self.stats, self.clock
        compute_loss = {f: distributed.data_parallel(loss, self.world) for f, loss in self.loss_fns.items()}
        writer = _tensorboard(tensorboard) if self.world.is_main else None
        self.started = clock() - stats["wall_s"]
        self.iteration = stats["iterations"]
        bar = BudgetBar(
            steps=config.iterations or None,
            minutes=config.minutes or None,
            initial=self.iteration,
            desc=f"train {self.model_config.kind}",
            unit="it",
            disable=not progress or not self.world.is_main,
        )
        interrupt = _DeferredInterrupt()
        try:
            while not self.finished():
                lr = self._iterate(compute_loss)
                if self.iteration % config.val_every == 0 or self.finished():
                    self._log(lr, writer)
                if self.iteration % config.checkpoint_every == 0:
                    self.save()
                    distributed.reseed_rank(config.seed, self.world, self.iteration)
                self._show(bar)
                if callback is not None:
                    callback(self.iteration, stats)
                if interrupt.requested:
                    raise KeyboardInterrupt
            bar.show(self.iteration, clock() - self.started)  # the budget's end (a time bar ends full)
        except KeyboardInterrupt:
            self._interrupted()
            raise
        finally:
            interrupt.restore()
            bar.close()
            if writer is not None:
                writer.close()
        if self.optimizer is None and self.world.is_main:
            stats["val_error"] = validation_error(self.model, self.windows, self.val_starts, config)
        stats["wall_s"] = clock() - self.started
        return TrainResult(self.model, stats, self.save())

    def progress(self) -> float:
        """Where the run is in its schedule, in [0, 1]: the iteration budget's share from `schedule_start`, or the
        `minutes` budget's, whichever is further."""
        config = self.config
        span = config.iterations - config.schedule_start
        by_steps = (self.iteration - config.schedule_start) / span if config.iterations > 0 else 0.0
        by_time = self.elapsed() / (60 * config.minutes) if config.minutes > 0 else 0.0
        return min(max(by_steps, by_time, 0.0), 1.0)

    def _iterate(self, compute_loss: dict[int, torch.nn.Module]) -> float:
        """One optimiser step at the scheduled learning rate (returned) and forecast length (`forecast_curriculum`),
        its loss and parts summed for the log."""
        progress = self.progress()
        config = self.config.stage(progress)
        lr = config.lr * learning_rate_factor(config.schedule, progress)
        for group in self.optimizer.param_groups:
            group["lr"] = lr
        batch = sample_batch(
            self.windows,
            self.train_starts[config.forecast],
            config,
            self.model_config.ensemble_size,
            self.sampler,
            self.world,
            self.mirror,
            self.recent_starts[config.forecast] if config.recent_share else None,
        )
        loss, parts = train_step(compute_loss[config.forecast], self.optimizer, self.params, batch, config.grad_clip)
        self.iteration += 1
        self.running += loss
        for name, value in parts.items():
            self.parts_sum[name] = self.parts_sum.get(name, 0.0) + value
        self.stats["iterations"], self.stats["wall_s"] = self.iteration, self.clock() - self.started
        return lr

    def _log(self, lr: float, writer) -> None:
        """The interval's mean loss (over the ranks) and parts, the validation error (rank 0), a log row, and the
        row's scalars to TensorBoard."""
        stats, iteration = self.stats, self.iteration
        count = iteration - (stats["log"][-1]["iteration"] if stats["log"] else 0)
        running = float(
            distributed.mean_over_ranks(torch.as_tensor(self.running, device=self.device).double(), self.world)
        )  # the logged loss: the ranks' mean
        stats["train_loss"] = running / max(count, 1)
        stats["train_parts"] = {k: float(v) / max(count, 1) for k, v in self.parts_sum.items()}
        stats["val_error"] = (
            validation_error(self.model, self.windows, self.val_starts, self.config) if self.world.is_main else None
        )
        stats["log"].append(
            {
                "iteration": iteration,
                "lr": lr,
                "train_loss": stats["train_loss"],
                "val_error": stats["val_error"],
                "wall_s": stats["wall_s"],
            }
        )
        self.running, self.parts_sum = 0.0, {}
        if writer is not None:
            for name, value in stats["log"][-1].items():
                if name != "iteration" and value is not None:
                    writer.add_scalar(name, value, iteration)

    def _show(self, bar: BudgetBar) -> None:
        """The progress bar, with the loss and validation error on iterations that logged them."""
        stats, postfix = self.stats, {}
        if stats["log"] and stats["log"][-1]["iteration"] == self.iteration:  # not per step: a host copy
            postfix = {"loss": f"{stats['train_loss']:.4f}", "val": stats["val_error"] and f"{stats['val_error']:.4f}"}
        bar.show(self.iteration, stats["wall_s"], **postfix)

    def _interrupted(self) -> None:
        """Ctrl-C (or a callback's KeyboardInterrupt): save a resumable checkpoint and say how to continue."""
        self.stats["wall_s"] = self.clock() - self.started
        out, iteration = self.out, self.iteration
        if self.world.distributed:  # ranks may stop an iteration apart: the periodic checkpoint is the consistent one
            if self.world.is_main and out is not None:
                print(
                    f"\ninterrupted at iteration {iteration}; continue from the last periodic checkpoint "
                    f"({out}, every {self.config.checkpoint_every} iterations) with --resume",
                    file=sys.stderr,
                )
        elif self.save() is not None:
            print(f"\ninterrupted at iteration {iteration}; saved {out} (continue with --resume)", file=sys.stderr)


def _resume(
    path: Path,
    model: WorldModel,
    optimizer: torch.optim.Optimizer | None,
    config: TrainConfig,
    sha256: str,
    device: torch.device,
    sampler: torch.Generator,
) -> dict:
    """Load the state of an interrupted run into model and optimizer; return its stats."""
    meta, state = load_training_state(path, model, optimizer)
    if meta.train_config is None:
        raise CheckpointError(f"{path}: no training config saved, cannot resume")
    if difference := config_difference(meta.train_config, config, ignore=RESUME_MAY_CHANGE):
        raise CheckpointError(f"{path}: cannot resume with a different training config ({difference})")
    if meta.provenance.get("sha256") != sha256:
        raise CheckpointError(f"{path}: was trained on another data file (sha256 {meta.provenance.get('sha256')})")
    if "rng_torch" not in state:
        raise CheckpointError(f"{path}: no RNG state saved, cannot resume")
    torch.set_rng_state(state["rng_torch"])
    if "rng_sampler" in state:
        sampler.set_state(state["rng_sampler"])
    else:  # a checkpoint from before the shared sampler: its draws continue from a stream derived from the iteration
        sampler.manual_seed(distributed.rank_seed(config.seed, 0, int(meta.stats.get("iterations", 0))))
    if device.type == "cuda" and "rng_cuda" in state:
        torch.cuda.set_rng_state(state["rng_cuda"], device)
    return meta.stats


def _tensorboard(log_dir: str | None):
    """A SummaryWriter when a log dir is asked for (`rwm_gym.tensorboard`: one line naming the extra without the
    package)."""
    if not log_dir:
        return None
    from rwm_gym.tensorboard import summary_writer

    return summary_writer(log_dir)

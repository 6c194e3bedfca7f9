"""Typed, frozen configuration of world models and of their training; both are saved into every checkpoint.

Sizes of the robot (state, action, contacts, feet) come from the task spec and the data, never from code. Field
docstrings double as the `--help` text of `rwm-gym train`.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import asdict, dataclass, fields, replace
from typing import Any

from rwm_gym.options import check_ranges, option, torch_device

MODEL_KINDS = ("rwm", "mlp", "rssm", "transformer", "no_change")
LOSSES = ("mse", "nll")
SCHEDULES = ("cosine", "step", "constant")


@dataclass(frozen=True)
class ModelConfig:
    """Architecture of one world model. Units: everything the model sees and predicts is normalised."""

    kind: str
    """Model family: rwm, mlp, rssm, transformer or no_change."""
    state_dim: int
    """S, size of the world-model state."""
    action_dim: int
    """A, size of the action."""
    contact_dim: int = 0
    """C, number of contact flags (0: no contact head)."""
    foot_dim: int = 0
    """F, number of foot heights (0: no foot-height head)."""
    hidden_size: int = option(256, ge=1)
    """Width of the recurrent cores (GRU units) and of the MLP baseline's layers."""
    num_layers: int = option(2, ge=1)
    """Stacked GRU layers (RWM, RSSM) or hidden layers (MLP)."""
    head_hidden: int = option(128, ge=1)
    """Width of the one hidden layer of every prediction head."""
    ensemble_size: int = option(1, ge=1)
    """k state heads; their disagreement is the epistemic uncertainty (RWM-U uses 5)."""
    log_std_min_init: float = option(-5.0, finite=True)
    """Initial learned lower bound of the predicted log-std (normalised units)."""
    log_std_max_init: float = option(0.5, finite=True)
    """Initial learned upper bound of the predicted log-std (normalised units)."""
    mlp_history: int = option(4, ge=1)
    """Number of past (state, action) pairs the MLP baseline stacks as its input."""
    rssm_latent: int = option(32, ge=1)
    """Size of the RSSM stochastic Gaussian latent."""
    transformer_context: int = option(32, ge=1)
    """Tokens (past (state, action) pairs) the causal Transformer attends to."""
    transformer_dim: int = option(128, ge=1)
    """Token width of the Transformer."""
    transformer_heads: int = option(4, ge=1)
    """Attention heads of the Transformer."""
    transformer_layers: int = option(2, ge=1)
    """Encoder layers of the Transformer."""
    unit_gravity: bool = False
    """Renormalise the predicted projected gravity to a unit vector (physical units) when the spec has that group."""
    joint_limits: bool = False
    """Clamp predicted joint positions to the MJCF joint ranges (gradient passes straight through)."""

    def __post_init__(self) -> None:
        if self.kind not in MODEL_KINDS:
            raise ValueError(f"model kind {self.kind!r} unknown (choose from {', '.join(MODEL_KINDS)})")
        check_ranges(self, "{field}")
        if min(self.state_dim, self.action_dim) < 1 or min(self.contact_dim, self.foot_dim) < 0:
            raise ValueError(
                f"model sizes must be positive: state {self.state_dim}, action {self.action_dim}, "
                f"contact {self.contact_dim}, foot {self.foot_dim}"
            )
        if self.ensemble_size < 1:
            raise ValueError(f"ensemble_size must be >= 1, got {self.ensemble_size}")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> ModelConfig:
        """Fields a file predates take the value that reproduces how it was built, not today's default."""
        return cls(**{**_MODEL_LEGACY, **_checked(cls, data)})


_MODEL_LEGACY = {"unit_gravity": False, "joint_limits": False}
"""ModelConfig fields added after the first checkpoints, with the behaviour of the files written before them."""


@dataclass(frozen=True)
class TrainConfig:
    """Dual-autoregressive training of a world model on windows of history + forecast steps."""

    history: int = option(32, ge=1)
    """H: true steps the model warms up on before forecasting."""
    forecast: int = option(8, ge=1)
    """F: steps predicted autoregressively from the model's own samples (1 = teacher forcing)."""
    batch_size: int = option(64, ge=1)
    """Forecast windows per gradient step (segments x branches)."""
    branches: int = option(1, ge=1)
    """Forecast branches per sampled segment: one teacher-forced pass over the segment, then this many F-step
    forecasts from its hidden states, batched (1: one window of H + F rows, the paper's recipe)."""
    branch_stride: int = option(1, ge=1)
    """Rows between the starts of consecutive branches of a segment."""
    warmup_gradients: bool = True
    """Backpropagate through the teacher-forced warm-up, as the paper does. Off, the warm-up runs without autograd
    and gradients flow through the F forecast steps only (truncated at each forecast's start): several times the
    windows per second with many branches per segment (the docs' Results, "World-model error"). Not for models whose
    warm-up
    carries a loss of its own (rssm's KL)."""
    lr: float = option(1e-3, gt=0)
    """Adam learning rate at the start of the schedule."""
    weight_decay: float = option(0.0, ge=0)
    """Adam (L2) weight decay."""
    grad_clip: float = option(1.0, gt=0)
    """Global gradient-norm clip."""
    schedule: str = "cosine"
    """Learning-rate schedule over the budget: cosine (to 5%), step (x0.1 at 50% and 75%) or constant."""
    schedule_start: int = option(0, ge=0)
    """Iteration at which the learning-rate schedule (and `forecast_curriculum`) starts over the iteration budget:
    a resumed run given a larger `iterations` and this set to the iteration it resumes at runs a fresh schedule from
    `lr` over the added iterations (a warm restart). Applies to the iteration budget, not to `minutes`."""
    forecast_curriculum: tuple[int, ...] = ()
    """Forecast lengths F trained with in turn, each for an equal share of the budget (e.g. 8 32 100: short
    forecasts first); empty: `forecast` throughout. Validation forecasts `forecast` steps."""
    iterations: int = option(2000, ge=0)
    """Budget in gradient steps (0: no limit, then `minutes` must be set)."""
    minutes: float = option(0.0, ge=0)
    """Budget in wall-clock minutes (0: no limit); the run stops at whichever budget ends first."""
    val_fraction: float = option(0.1, ge=0, lt=1)
    """Fraction of episodes held out for validation (whole episodes)."""
    val_every: int = option(100, ge=1)
    """Iterations between validation passes."""
    val_windows: int = option(256, ge=1)
    """Validation windows (fixed, drawn once per run)."""
    checkpoint_every: int = option(100, ge=1)
    """Iterations between checkpoints (with optimizer and RNG state, for --resume)."""
    seed: int = 0
    """Seeds weights, window sampling and forecast noise; a run is deterministic in it."""
    device: str = option("cpu", parse=torch_device)
    """torch device: cpu or cuda."""
    loss: str = "mse"
    """State loss on forecast steps: mse (of reparameterised samples, as RWM) or nll (Gaussian)."""
    contact_weight: float = option(1.0, ge=0)
    """Weight of the contact BCE."""
    termination_weight: float = option(1.0, ge=0)
    """Weight of the class-weighted termination BCE."""
    foot_weight: float = option(1.0, ge=0)
    """Weight of the foot-height MSE."""
    bound_weight: float = option(0.01, ge=0)
    """Weight of the log-std band term sum(max_log_std) - sum(min_log_std)."""
    reset_std_band: bool = False
    """With `init`: put the state heads' learned log-std band back to the model config's initial limits and their
    predicted log-std to `reset_log_std` first. Under the mse loss nothing pushes the std up: the band inverts and its
    floor settles where the penalty on samples meets `bound_weight` (0.34 normalised units on ANYmal D, on every
    channel of every state), so the sampled feedback is that noise, not the model's error. An nll fine-tune needs
    the std free."""
    reset_log_std: float = option(-2.3, finite=True)
    """The log-std every state head predicts after `reset_std_band` (-2.3: 0.1 normalised units)."""
    kl_weight: float = option(1.0, ge=0)
    """Weight of the RSSM KL term (posterior from the true next state vs prior)."""
    kl_free_nats: float = option(1.0, ge=0)
    """KL below this many nats per step is not penalised (RSSM)."""
    mirror: bool = False
    """Train on each window or, with probability 1/2, its left-right mirror image (the spec's `[symmetry]`): a
    symmetric robot's data, doubled. Validation windows are never mirrored."""
    recent_episodes: int = option(0, ge=0)
    """The dataset's last this many episodes are its recent data (a merged buffer keeps its files' order, so an MBPO
    buffer's newest collection comes last); 0: none."""
    recent_share: float = option(0.0, ge=0, le=1)
    """Share of each batch's segments drawn from the windows of the recent training episodes, the rest from every
    training window (0: all uniform): fresh data the policy just found outweighs a large buffer."""

    def __post_init__(self) -> None:
        check_ranges(self)
        if self.history < 1 or self.forecast < 1:
            raise ValueError(f"history and forecast must be >= 1, got {self.history} and {self.forecast}")
        if self.loss not in LOSSES:
            raise ValueError(f"loss {self.loss!r} unknown (choose from {', '.join(LOSSES)})")
        if self.schedule not in SCHEDULES:
            raise ValueError(f"schedule {self.schedule!r} unknown (choose from {', '.join(SCHEDULES)})")
        if self.iterations <= 0 and self.minutes <= 0:
            raise ValueError("set a budget: iterations > 0 or minutes > 0")
        if self.schedule_start < 0 or (self.schedule_start and self.schedule_start >= self.iterations):
            raise ValueError(
                f"schedule_start must be >= 0 and below iterations ({self.iterations}), got {self.schedule_start}"
            )
        object.__setattr__(self, "forecast_curriculum", tuple(int(f) for f in self.forecast_curriculum))
        if any(f < 1 for f in self.forecast_curriculum):
            raise ValueError(f"forecast_curriculum lengths must be >= 1, got {list(self.forecast_curriculum)}")
        for name in ("batch_size", "val_every", "checkpoint_every", "val_windows"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not self.lr > 0:
            raise ValueError(f"lr must be > 0, got {self.lr}")
        if self.branches < 1 or self.branch_stride < 1 or self.batch_size % self.branches:
            raise ValueError(
                f"branches ({self.branches}) and branch_stride ({self.branch_stride}) must be >= 1 and "
                f"divide batch_size ({self.batch_size}) into whole segments"
            )

    @property
    def forecasts(self) -> tuple[int, ...]:
        """The forecast lengths trained with, in order: `forecast_curriculum`, or `forecast` alone."""
        return self.forecast_curriculum or (self.forecast,)

    def stage(self, progress: float) -> TrainConfig:
        """This config at `progress` in [0, 1] of the schedule: `forecast` set to the curriculum's length there."""
        if not self.forecast_curriculum:
            return self
        index = min(int(progress * len(self.forecast_curriculum)), len(self.forecast_curriculum) - 1)
        return self.stage_of(self.forecast_curriculum[index])

    def stage_of(self, forecast: int) -> TrainConfig:
        """This config training `forecast`-step forecasts (one stage of the curriculum)."""
        return replace(self, forecast=forecast, forecast_curriculum=())

    @property
    def segment_rows(self) -> int:
        """Rows of one training segment: H history rows, then a branch start every `branch_stride` rows, F after the
        last."""
        return self.history + (self.branches - 1) * self.branch_stride + self.forecast

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> TrainConfig:
        """Fields a file predates take the value that reproduces how it was trained, not today's default."""
        return cls(**{**_TRAIN_LEGACY, **_checked(cls, data)})


_TRAIN_LEGACY = {
    "branches": 1,
    "branch_stride": 1,
    "warmup_gradients": True,
    "reset_std_band": False,
    "reset_log_std": -2.3,
    "schedule_start": 0,
    "forecast_curriculum": (),
}
"""TrainConfig fields added after the first checkpoints, with the behaviour of the files written before them."""


def _checked(cls: type, data: dict[str, Any]) -> dict[str, Any]:
    """`data` if every key is a field of `cls`; an unknown key (a newer file) is refused, not silently dropped."""
    names = {f.name for f in fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ValueError(f"{cls.__name__}: unknown field {unknown[0]!r}")
    return dict(data)


def config_difference(found: Any, expected: Any, ignore: Iterable[str] = ()) -> str | None:
    """The first field in which two configs of one class differ, as "name: a in the file, b now"; None if none."""
    a, b = found.to_dict(), expected.to_dict()
    for name in a:
        if name not in ignore and a[name] != b[name]:
            return f"{name}: {a[name]!r} in the file, {b[name]!r} now"
    return None

"""How imagined episodes run: `ImaginationOptions`, one frozen dataclass read by the imagined core, its envs and
every command that trains in imagination (their flags are generated from its fields). No torch here, so a config
that nests it (`rwm_gym.rl.mbpo.MBPOConfig`) imports light."""

from __future__ import annotations

from dataclasses import dataclass

from rwm_gym.options import check_ranges, option

MATMUL_PRECISION_NAMES = ("float32", "bfloat16")
"""The values of `ImaginationOptions.matmul_precision` (`rwm_gym.imagination.core.MATMUL_PRECISIONS` maps them to
dtypes)."""


@dataclass(frozen=True)
class ImaginationOptions:
    """How imagined episodes run."""

    sample_predictions: bool = False
    """Step with a sample of the predicted Gaussian instead of its mean."""
    history: int | None = option(None, ge=1)
    """Real rows replayed at every reset (None: the checkpoint's training history)."""
    episode_steps: int | None = option(None, ge=1)
    """Time limit in policy steps (None: the task spec's)."""
    uncertainty_penalty: float = option(0.0, ge=0)
    """lambda of the RWM-U penalty -lambda * max(u - uncertainty_floor, 0) * dt, u the ensemble disagreement."""
    uncertainty_floor: float = option(0.0, ge=0)
    """Disagreement the penalty leaves free: the model's own level on states like its data (the shipped ANYmal model:
    about 0.02 while the teacher walks or the robot stands). A penalty on every step would make ending the episode
    early pay; charging only the excess keeps surviving worth it."""
    uncertainty_halt: float = option(0.0, ge=0)
    """End an episode (terminated, no bootstrap) where u exceeds this (0: never): MOReL's halt, so a policy cannot
    collect reward in states the model does not know."""
    fall_tilt: float = option(0.0, ge=0, le=180)
    """End an episode (terminated, no bootstrap) where the predicted base tilts more than this many degrees from
    upright (0: never; needs a projected_gravity state group). The model's termination head fires on predicted base
    contact, late or never, while its own predicted tilt already shows a fall; a walking robot stays far below a
    tilt from which it rarely recovers (both measured on the Policies results page)."""
    torque_halt: float = option(0.0, ge=0)
    """End an episode (terminated, no bootstrap) where a predicted joint torque reaches this fraction of the spec's
    effort limit (0: never; needs a joint_torque state group and a finite limit). Saturated actuators are states a
    model's data rarely covers, and policies trained in imagination that fell in physics often fell there: the halt
    keeps a policy out of them, as MOReL's keeps it where the heads agree."""
    random_first_episode_length: bool = False
    """Start each env's first episode at a random elapsed step in [0, episode_steps), drawn from its own generator
    (rsl_rl's `init_at_random_ep_len`): without it, N envs with an equal time limit all restart on the same step, and
    every PPO rollout sees the same phase of its episodes."""
    resample_commands: bool = True
    """Resample commands on the spec's period (off: one command per episode)."""
    command_from_history: float = option(0.0, ge=0, le=1)
    """Share of restarts whose command is the velocity their real history was moving at (its last rows' mean vx, vy
    and yaw rate, within the command range) instead of a fresh draw: the episode starts mid-gait with that gait's
    own goal (reference-state initialisation), so a young policy is paid for keeping a gait before it has found one
    (0: every command drawn; needs commands named vx, vy, yaw_rate)."""
    kinematics: bool = True
    """Compute what a fixed-base arm's MJCF fixes instead of predicting it: joint angles integrate the predicted joint
    velocities, sites on the arm follow by forward kinematics (`rwm_gym.imagination.kinematics`; dm_control's
    manipulation arms only, no effect on other robots)."""
    push_interval_s: float = option(0.0, ge=0)
    """Seconds between random pushes (0: none); a push adds a uniform base velocity."""
    push_velocity: float = option(0.5, ge=0)
    """m/s, half-width of a push."""
    report_uncertainty: bool = False
    """Compute the ensemble disagreement every step and report it as info['uncertainty'] even without a penalty
    (it runs all k heads per step; off and penalty 0, each env runs only its own head and info has no uncertainty)."""
    divergence_bound: float = option(50.0, gt=0)
    """|normalised state| above which the model is taken to have diverged and the episode ends."""
    trust_entry_points: bool = False
    """Import the reward / termination functions the checkpoint's spec names (`[imagination]`): importing a module
    runs its code, so only for a checkpoint you trust (off: naming one is an error; pass reward_fn= instead)."""
    warm_up_cache_mb: float = option(512.0, ge=0)
    """Keep each reset window's warm hidden state for reuse if all windows fit in this many MB (0: warm up on every
    reset); models whose warm-up reads the ensemble member always warm up."""

    matmul_precision: str = "float32"
    """dtype of the world model's matrix products in each imagined step: float32, or bfloat16 (RWM's GRUs; 2.5-4x
    their fp32 rate on CPUs with AVX512-BF16 or AMX and on GPUs, forecast error within 0.5 % of fp32 on the shipped
    ANYmal model: benchmarks/RESULTS.md). Gates, hidden state and heads stay float32."""

    def __post_init__(self) -> None:
        check_ranges(self)
        if self.matmul_precision not in MATMUL_PRECISION_NAMES:
            raise ValueError(
                f"ImaginationOptions.matmul_precision {self.matmul_precision!r} unknown (choose from "
                f"{', '.join(MATMUL_PRECISION_NAMES)})"
            )

    @property
    def acts_on_disagreement(self) -> bool:
        """Whether the penalty or the halt reads the ensemble's disagreement (so the model needs several heads)."""
        return self.uncertainty_penalty > 0 or self.uncertainty_halt > 0

"""Judge a locomotion policy where it matters: in physics (`AnymalD-MuJoCo-v0`), over fixed commands and seeds.

Every (command, seed) pair is one env of the batched physics core; the command is set after reset and never resampled,
so the numbers of two policies are comparable.

The headline figure is the **tracking score**: the mean over every evaluated step of
`(w_xy * exp(-|cmd_xy - v_xy|^2 / sigma) + w_yaw * exp(-(cmd_yaw - w_z)^2 / sigma)) / (w_xy + w_yaw)` with the
task's own tracking weights and sigma (1.0, 0.5 and 0.25 for ANYmal D), so 1.0 is perfect tracking; a robot that
falls (or whose physics blows up: `physics_diverged`) scores 0 for the rest of its episode and counts as a fall.
`scoring_commands` is the fixed command set it is measured on. Beside it we report the return, the velocity-tracking
errors, the falls, the distance walked and the velocity achieved.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from rwm_gym.atomic import save_png
from rwm_gym.spec import TaskSpec

PolicyFn = Callable[[np.ndarray], np.ndarray]
"""Observations (N, O) -> actions (N, A) in [-1, 1]."""

SCORING_SEED = 20261123
"""Seed of the random half of the scoring command set: fixed, so every score is measured on the same commands."""


def scoring_commands(
    spec: str | TaskSpec = "anymal_d", num_random: int = 16, seed: int = SCORING_SEED
) -> tuple[tuple[float, ...], ...]:
    """The scoring command set: standing, 1 m/s forward (the top of the forward range where that is lower), then
    `num_random` commands drawn uniformly from the spec's ranges with a fixed seed. (vx m/s, vy m/s, yaw rate rad/s)
    in the body frame for the legged tasks."""
    from rwm_gym.spec import load_spec

    task = spec if isinstance(spec, TaskSpec) else load_spec(spec)
    low, high = np.asarray(task.command.low), np.asarray(task.command.high)
    fixed = [np.zeros_like(low), np.where(np.arange(len(low)) == 0, min(1.0, float(high[0])), 0.0)]
    drawn = np.random.default_rng(seed).uniform(low, high, (num_random, len(low)))
    return tuple(tuple(round(float(x), 3) for x in c) for c in [*fixed, *drawn])


def tracking_terms(spec: TaskSpec, state: np.ndarray, command: np.ndarray) -> np.ndarray:
    """Per-env tracking score of one step (N,), in [0, 1]: the task's two tracking terms, weighted as in its reward."""
    s, sigma, w = spec.state_slices, spec.reward.tracking_sigma, spec.reward.weights
    v, wz = state[:, s["base_lin_vel"]][:, :2], state[:, s["base_ang_vel"]][:, 2]
    lin = np.exp(-np.sum((command[:, :2] - v) ** 2, axis=1) / sigma)
    yaw = np.exp(-((command[:, 2] - wz) ** 2) / sigma)
    w_lin, w_yaw = w["track_lin_vel_xy"], w["track_ang_vel_z"]
    return (w_lin * lin + w_yaw * yaw) / (w_lin + w_yaw)


@dataclass(frozen=True)
class CommandResult:
    """One command, averaged over seeds."""

    command: tuple[float, float, float]
    """(vx m/s, vy m/s, yaw rate rad/s)."""
    tracking: float
    """Tracking score (see the module docstring): 1.0 is perfect, a fall scores 0 for the rest of its episode."""
    episode_return: float
    """Mean sum of rewards (the task's weighted terms, each x dt); about 30 for a perfect 20 s episode."""
    lin_vel_error: float
    """m/s, mean |v_xy - cmd_xy| over the steps after settling (a fallen robot's velocity counts as 0)."""
    yaw_rate_error: float
    """rad/s, mean |w_z - cmd_yaw| over the same steps."""
    falls: int
    """Episodes that terminated (base contact) before the end."""
    distance: float
    """m, distance walked along the commanded xy direction (body-frame velocity integrated); 0 for no xy command."""
    achieved: tuple[float, float, float]
    """Mean (vx, vy, yaw rate) over the settled steps (0 after a fall)."""
    achieved_std: tuple[float, float, float]
    """Std of the per-seed means of (vx, vy, yaw rate)."""
    disagreement: float | None = None
    """In a world model that reports it: the mean ensemble disagreement over the steps before a fall, the signal the
    RWM-U penalty acts on (a policy that exploits the model where this stays low is invisible to the penalty).
    None in physics."""


@dataclass(frozen=True)
class Evaluation:
    """A policy's physics evaluation: per command and overall (means over commands; falls summed)."""

    commands: list[CommandResult]
    tracking: float
    """Mean tracking score over every (command, seed) episode: the figure policies are judged by."""
    episode_return: float
    lin_vel_error: float
    yaw_rate_error: float
    falls: int
    episodes: int
    steps: int
    """Policy steps per episode (0.02 s each for ANYmal D)."""
    wall_s: float
    extra: dict = field(default_factory=dict)
    """Free fields the caller adds (e.g. physics samples used for training, training wall time)."""

    def to_dict(self) -> dict:
        return asdict(self)


def as_policy(policy: str | os.PathLike | PolicyFn | object) -> PolicyFn:
    """A deterministic policy function from an SB3 `.zip` path, an SB3 model (anything with `predict`) or a callable."""
    if isinstance(policy, (str, os.PathLike)):
        from rwm_gym.policy_zip import load_policy

        policy = load_policy(policy, device="cpu")
    if hasattr(policy, "predict"):
        model = policy
        return lambda obs: model.predict(obs.astype(np.float32), deterministic=True)[0]
    if callable(policy):
        return policy
    raise TypeError(f"cannot use {type(policy).__name__} as a policy (give a .zip path, an SB3 model or a callable)")


def evaluate_policy(
    policy: str | os.PathLike | PolicyFn | object,
    *,
    commands: Sequence[Sequence[float]] | None = None,
    seeds: Sequence[int] = (0, 1, 2),
    steps: int | None = None,
    settle_steps: int = 50,
    spec: str | TaskSpec = "anymal_d",
    env_kwargs: dict | None = None,
    core=None,
) -> Evaluation:
    """Run `policy` in physics for `steps` policy steps (default: a full episode) per (command, seed) pair.

    commands: default `scoring_commands(spec)`. settle_steps: the first steps (1 s at 50 Hz) are left out of the
    velocity errors (not of the tracking score), so the start-up transient does not dominate them. env_kwargs go to the
    physics core (e.g. `physics`, `observation_noise`). `core`: a batched core of len(commands) x len(seeds) envs to
    run instead of physics, e.g. an imagined one (`ImaginedCore`, commands not resampled) for the same score in a model.
    """
    act = as_policy(policy)
    started = time.monotonic()
    commands = [tuple(float(c) for c in cmd) for cmd in (commands or scoring_commands(spec))]
    pairs = [(c, s) for c in commands for s in seeds]
    tally = run_episodes(
        act, pairs, steps=steps, settle_steps=settle_steps, spec=spec, env_kwargs=env_kwargs, core=core
    )
    return summarize(tally, commands, pairs, time.monotonic() - started)


def run_episodes(
    act: PolicyFn,
    pairs: Sequence[tuple[tuple[float, ...], int]],
    *,
    steps: int | None = None,
    settle_steps: int = 50,
    spec: str | TaskSpec = "anymal_d",
    env_kwargs: dict | None = None,
    core=None,
) -> _Tally:
    """The per-env sums of one episode per (command, seed) pair, env k running pair k (`evaluate_policy`'s work
    before its means; `_Tally.concatenate` joins the tallies of consecutive blocks of pairs run apart)."""
    core = _evaluation_core(core, spec, len(pairs), env_kwargs)
    task = core.spec
    steps = steps or task.episode_steps
    if len(pairs[0][0]) != len(task.command.names):
        raise ValueError(f"commands have {len(pairs[0][0])} entries, the task's {task.name} has {task.command.names}")
    n = len(pairs)
    obs = core.reset(np.arange(n), [s for _, s in pairs], np.asarray([c for c, _ in pairs], dtype=np.float32))
    tally = _Tally.start(task, core.command.astype(np.float64), steps)
    for t in range(steps):
        obs, reward, terminated, _, info = core.step(np.clip(act(obs), -1.0, 1.0))
        state = core.current.state if hasattr(core, "current") else core.state
        tally.add(reward, terminated, info, state, settled=t >= settle_steps)
    return tally


def summarize(
    tally: _Tally, commands: Sequence[tuple[float, ...]], pairs: Sequence[tuple[tuple[float, ...], int]], wall_s: float
) -> Evaluation:
    """The evaluation of the episodes of `pairs` (a tally of all of them, in their order): per command and overall."""
    steps, n = tally.steps, len(pairs)
    rows = [tally.result(c, np.array([pc == c for pc, _ in pairs]), steps) for c in commands]
    return Evaluation(
        commands=rows,
        tracking=float(tally.tracking.mean() / steps),
        episode_return=float(np.mean([r.episode_return for r in rows])),
        lin_vel_error=float(np.mean([r.lin_vel_error for r in rows])),
        yaw_rate_error=float(np.mean([r.yaw_rate_error for r in rows])),
        falls=int(sum(r.falls for r in rows)),
        episodes=n,
        steps=steps,
        wall_s=wall_s,
    )


def _evaluation_core(core, spec: str | TaskSpec, num_envs: int, env_kwargs: dict | None):
    """The physics core of `num_envs` envs, or the given `core` if it has that many."""
    from rwm_gym.physics.locomotion import make_core

    if core is None:
        return make_core(spec, num_envs, **(env_kwargs or {}))
    if core.num_envs != num_envs:
        raise ValueError(f"core has {core.num_envs} envs, the evaluation needs {num_envs} (commands x seeds)")
    return core


@dataclass
class _Tally:
    """Per-env sums over an evaluation's steps; arrays are (N,) unless said otherwise."""

    task: TaskSpec
    cmd: np.ndarray
    """(N, K) each env's command."""
    direction: np.ndarray
    """(N, 2) unit vector of the commanded xy velocity (0 for none)."""
    alive: np.ndarray
    returns: np.ndarray
    counted: np.ndarray
    """Settled steps counted in the velocity sums."""
    tracking: np.ndarray
    alive_steps: np.ndarray
    sums: dict[str, np.ndarray]
    """lin_err, yaw_err, vx, vy, wz over the settled steps; dist over every step."""
    steps: int = 0
    """Policy steps of each episode."""
    disagreement: np.ndarray | None = None
    """Summed over each env's steps before a fall, where the core reports it."""

    @classmethod
    def start(cls, task: TaskSpec, cmd: np.ndarray, steps: int) -> _Tally:
        n = len(cmd)
        cmd_norm = np.linalg.norm(cmd[:, :2], axis=1)
        direction = np.divide(cmd[:, :2], cmd_norm[:, None], out=np.zeros((n, 2)), where=cmd_norm[:, None] > 0)
        return cls(
            task,
            cmd,
            direction,
            np.ones(n, dtype=bool),
            np.zeros(n),
            np.zeros(n),
            np.zeros(n),
            np.zeros(n),
            {k: np.zeros(n) for k in ("lin_err", "yaw_err", "vx", "vy", "wz", "dist")},
            steps,
        )

    @classmethod
    def concatenate(cls, parts: Sequence[_Tally]) -> _Tally:
        """One tally of the envs of `parts`, in their order (the same arrays one core of all of them gives)."""
        first = parts[0]
        arrays = ("cmd", "direction", "alive", "returns", "counted", "tracking", "alive_steps")
        joined = {name: np.concatenate([getattr(p, name) for p in parts]) for name in arrays}
        sums = {k: np.concatenate([p.sums[k] for p in parts]) for k in first.sums}
        disagreement = None if first.disagreement is None else np.concatenate([p.disagreement for p in parts])
        return cls(task=first.task, **joined, sums=sums, steps=first.steps, disagreement=disagreement)

    def add(self, reward: np.ndarray, terminated: np.ndarray, info: dict, state: np.ndarray, settled: bool) -> None:
        """One step: the reward and disagreement before a fall, then tracking, distance and (once `settled`) the
        velocities of the envs still up."""
        alive, cmd, sums = self.alive, self.cmd, self.sums
        self.returns += np.where(alive, reward, 0.0)
        if "uncertainty" in info:
            self.disagreement = np.zeros(len(alive)) if self.disagreement is None else self.disagreement
            self.disagreement += np.where(alive, info["uncertainty"], 0.0)
            self.alive_steps += alive
        alive &= ~terminated
        self.tracking += np.where(alive, tracking_terms(self.task, state, cmd), 0.0)
        # a fallen robot makes no progress: it counts as standing still for the rest of the evaluation
        lin, ang = self.task.state_slices["base_lin_vel"], self.task.state_slices["base_ang_vel"]
        v = np.where(alive[:, None], state[:, lin][:, :2], 0.0)
        wz = np.where(alive, state[:, ang][:, 2], 0.0)
        sums["dist"] += np.where(alive, (v * self.direction).sum(1) * self.task.policy_dt, 0.0)
        if settled:
            self.counted += 1
            sums["lin_err"] += np.linalg.norm(v - cmd[:, :2], axis=1)
            sums["yaw_err"] += np.abs(wz - cmd[:, 2])
            sums["vx"] += v[:, 0]
            sums["vy"] += v[:, 1]
            sums["wz"] += wz

    def result(self, command: tuple[float, ...], m: np.ndarray, steps: int) -> CommandResult:
        """The means over the envs `m` (a mask) of one command."""
        means = {k: s / np.maximum(self.counted, 1) for k, s in self.sums.items() if k != "dist"}
        achieved = np.stack([means["vx"][m], means["vy"][m], means["wz"][m]], axis=1)
        disagreement = self.disagreement
        return CommandResult(
            command=command,
            tracking=float(self.tracking[m].mean() / steps),
            episode_return=float(self.returns[m].mean()),
            lin_vel_error=float(means["lin_err"][m].mean()),
            yaw_rate_error=float(means["yaw_err"][m].mean()),
            falls=int((~self.alive[m]).sum()),
            distance=float(self.sums["dist"][m].mean()),
            achieved=tuple(float(x) for x in achieved.mean(0)),
            achieved_std=tuple(float(x) for x in achieved.std(0)),
            disagreement=None if disagreement is None else float(disagreement[m].sum() / self.alive_steps[m].sum()),
        )


def format_table(evaluation: Evaluation) -> str:
    """A plain-text table: one row per command and a mean row; in a world model that reports it, each command's mean
    ensemble disagreement too."""
    in_model = any(r.disagreement is not None for r in evaluation.commands)
    head = (
        f"{'command (vx, vy, wz)':>22} | {'track':>5} | {'return':>7} | {'|dv_xy| m/s':>11} | "
        f"{'|dwz| rad/s':>11} | {'falls':>5} | {'dist m':>7} | {'achieved (vx, vy, wz)':>22}"
        + (" | disagreement" if in_model else "")
    )
    lines = [head, "-" * len(head)]
    for r in evaluation.commands:
        cmd = "(" + ", ".join(f"{x:+.1f}" for x in r.command) + ")"
        got = "(" + ", ".join(f"{x:+.2f}" for x in r.achieved) + ")"
        lines.append(
            f"{cmd:>22} | {r.tracking:5.3f} | {r.episode_return:7.2f} | {r.lin_vel_error:11.3f} | "
            f"{r.yaw_rate_error:11.3f} | {r.falls:5d} | {r.distance:7.2f} | {got:>22}"
            + (f" | {r.disagreement:12.4f}" if in_model else "")
        )
    e = evaluation
    lines.append("-" * len(head))
    lines.append(
        f"{'mean':>22} | {e.tracking:5.3f} | {e.episode_return:7.2f} | {e.lin_vel_error:11.3f} | "
        f"{e.yaw_rate_error:11.3f} | {e.falls:5d} | {'':>7} | {e.episodes} episodes x {e.steps} steps"
    )
    return "\n".join(lines)


def plot(evaluation: Evaluation, path: str | os.PathLike, title: str = "") -> Path:
    """Commanded vs achieved (vx, vy, yaw rate) per command as grouped bars; written atomically as PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = evaluation.commands
    labels = ["(" + ", ".join(f"{x:+.1f}" for x in r.command) + ")" for r in rows]
    x = np.arange(len(rows))
    fig, axes = plt.subplots(1, 3, figsize=(14, 4), sharex=True)
    for k, (ax, name) in enumerate(zip(axes, ("vx (m/s)", "vy (m/s)", "yaw rate (rad/s)"))):
        ax.bar(x - 0.2, [r.command[k] for r in rows], 0.4, label="commanded", color="0.7")
        ax.bar(
            x + 0.2,
            [r.achieved[k] for r in rows],
            0.4,
            yerr=[r.achieved_std[k] for r in rows],
            label="achieved",
            color="tab:blue",
            capsize=3,
        )
        ax.axhline(0.0, color="k", lw=0.5)
        ax.set_title(name)
        ax.set_xticks(x, labels, rotation=45, ha="right", fontsize=8)
    axes[0].legend()
    fig.suptitle(
        title
        or f"physics evaluation: tracking {evaluation.tracking:.3f}, "
        f"return {evaluation.episode_return:.2f}, "
        f"|dv_xy| {evaluation.lin_vel_error:.3f} m/s, falls {evaluation.falls}/{evaluation.episodes}"
    )
    fig.tight_layout()
    return save_png(fig, path, dpi=100)

"""`rwm-gym score`: a policy's tracking score in physics (or in a world model), beside the zero-action floor.

    rwm-gym score --policy P.zip --out DIR [--checkpoint CKPT [--reset-data H5]] [--video] [--workers N]
                  [--backend processes|ray]

Runs the policy on the fixed scoring command set (`scoring_commands`: standing, 1 m/s forward and 16 commands drawn
from the spec's ranges with a fixed seed), `--seeds` episodes each, commands held for the whole 20 s episode, and
does the same for a policy that sends zero actions (it stands still: the floor any walking policy must beat).
Writes DIR/score.json (tracking, return, falls, per command; the floor beside), DIR/score.md (the table) and
DIR/score.png; `--video` adds DIR/walk.gif and a still DIR/walk.png of the policy walking through forward, lateral,
turn and stop commands. `--workers N` splits the episodes over N workers (spawned processes, or Ray tasks with
`--backend ray`; `rwm_gym.workers`), each a batched physics core of a consecutive block of them: the same seeds give
the same figures (to float rounding for an SB3 policy, whose network then acts on smaller batches).
"""

from __future__ import annotations

import functools
import itertools
import os
import time
from pathlib import Path

import numpy as np

from rwm_gym.atomic import atomic_write
from rwm_gym.rl.evaluate_policy import (
    Evaluation,
    _Tally,
    as_policy,
    evaluate_policy,
    run_episodes,
    scoring_commands,
    summarize,
)
from rwm_gym.spec import TaskSpec
from rwm_gym.workers import run_in_workers, threads_per_worker, uses_workers

VIDEO_COMMANDS: tuple[tuple[str, tuple[float, float, float]], ...] = (
    ("forward 1.0 m/s", (1.0, 0.0, 0.0)),
    ("lateral 0.5 m/s", (0.0, 0.5, 0.0)),
    ("turn 1.0 rad/s", (0.0, 0.0, 1.0)),
    ("stop", (0.0, 0.0, 0.0)),
)


def zero_policy(obs: np.ndarray, action_dim: int = 12) -> np.ndarray:
    """The floor: zero actions hold the default pose, so the robot stands still (`action_dim` actions)."""
    return np.zeros((len(obs), action_dim), dtype=np.float32)


SCRIPTED = ("zero", "gait", "random")
"""Policies `--policy` also takes by name: the zero-action floor, the scripted trot (`rwm_gym.policies.gait`) and the
datasets' correlated random actions (`rwm_gym.policies.base.RandomPolicy`)."""


def task_of(spec: str | TaskSpec) -> TaskSpec:
    """The task spec of a physics env id, a shipped spec name, a spec file path or a TaskSpec."""
    from rwm_gym.registration import resolve_spec

    return resolve_spec(spec)


def resolve_policy(policy, num_envs: int, spec: str | TaskSpec = "anymal_d", first: int = 0):
    """A policy function for `num_envs` envs of the task `spec` from a name in `SCRIPTED` (env k draws from generator
    `first` + k, so a block of envs acts as those envs of one whole batch), a zip path, an SB3 model or a callable."""
    if isinstance(policy, str) and policy == "zero":
        return functools.partial(zero_policy, action_dim=task_of(spec).action_dim)
    if isinstance(policy, str) and policy in SCRIPTED:
        from rwm_gym.policies.factory import make_policy

        scripted = make_policy(policy, task_of(spec), num_envs)
        scripted.reset(np.arange(num_envs), [np.random.default_rng(first + k) for k in range(num_envs)])
        return scripted.act
    return as_policy(policy)


def score(
    policy,
    *,
    seeds: int = 3,
    steps: int | None = None,
    num_random: int = 16,
    checkpoint: str | None = None,
    reset_data: str | os.PathLike | None = None,
    spec: str | TaskSpec = "anymal_d",
    workers: int = 1,
    backend: str = "processes",
    physics: dict | None = None,
    trust_entry_points: bool = False,
) -> Evaluation:
    """The tracking score of `policy` (a name in `SCRIPTED`, zip path, SB3 model or callable) in physics, or in the
    world model `checkpoint`, its episodes starting from windows of `reset_data` (default: the checkpoint's);
    `trust_entry_points`: import the reward / termination functions the checkpoint's spec names.

    workers > 1 (or backend "ray"): the physics episodes split over that many workers of `backend` ("processes" or
    "ray", `rwm_gym.workers`; `policy` then a name or a path); the figures are those of one process, exactly for the
    scripted policies; an SB3 network acting on a smaller batch rounds differently (about 1e-9 relative, tested).
    `physics`: the robot's `PhysicsParams` (a dict of its fields; None: the MJCF's). `spec`: the task scored on (a
    physics env id, a shipped spec name, a spec file or a TaskSpec): its command ranges, its robot, its falls.
    """
    commands = scoring_commands(task_of(spec), num_random)
    if uses_workers(workers, backend):
        if checkpoint is not None:
            raise ValueError("workers score in physics; a world model scores in one process")
        if not isinstance(policy, (str, os.PathLike)):
            raise ValueError("score in workers needs the policy as a name or a path, not an object")
        return _score_in_workers(str(policy), commands, seeds, steps, spec, workers, backend, physics)
    policy = resolve_policy(policy, len(commands) * seeds, spec)
    core = None
    if checkpoint is not None and physics:
        raise ValueError("physics parameters apply in physics; a world model scores as it was trained")
    if checkpoint is not None:
        from rwm_gym.imagination.core import ImaginationOptions, ImaginedCore

        core = ImaginedCore(
            checkpoint,
            len(commands) * seeds,
            reset_data=reset_data,
            options=ImaginationOptions(
                resample_commands=False, report_uncertainty=True, trust_entry_points=trust_entry_points
            ),
        )
    env_kwargs = {"physics": physics} if physics else None
    return evaluate_policy(
        policy, commands=commands, seeds=range(seeds), steps=steps, spec=task_of(spec), core=core, env_kwargs=env_kwargs
    )


def _score_in_workers(
    policy: str,
    commands,
    seeds: int,
    steps: int | None,
    spec: str | TaskSpec,
    workers: int,
    backend: str,
    physics: dict | None,
) -> Evaluation:
    """`score` in physics with the (command, seed) episodes in `workers` consecutive blocks, one worker each; their
    tallies joined in order, so the means are taken over the same arrays as in one process."""
    started = time.monotonic()
    pairs = [(c, s) for c in commands for s in range(seeds)]
    bounds = np.linspace(0, len(pairs), min(workers, len(pairs)) + 1).round().astype(int)
    blocks = [range(int(a), int(b)) for a, b in itertools.pairwise(bounds)]
    threads = threads_per_worker(len(blocks), backend)
    job = functools.partial(_score_block, policy, pairs, steps, spec, threads, physics)
    tallies = list(run_in_workers(job, blocks, len(blocks), backend))
    return summarize(_Tally.concatenate(tallies), commands, pairs, time.monotonic() - started)


def _score_block(
    policy: str, pairs, steps: int | None, spec: str | TaskSpec, threads: int, physics: dict | None, block: range
):
    """A worker's share: the episodes of `pairs[block]` in one physics core of `threads` threads."""
    import torch

    torch.set_num_threads(threads)
    act = resolve_policy(policy, len(block), spec, first=block.start)
    env_kwargs = {"nthread": threads, **({"physics": physics} if physics else {})}
    return run_episodes(act, [pairs[k] for k in block], steps=steps, spec=task_of(spec), env_kwargs=env_kwargs)


def record_walk(
    policy,
    gif: str | os.PathLike,
    still: str | os.PathLike,
    *,
    seconds_each: float = 3.0,
    fps: int = 15,
    size: tuple[int, int] = (400, 272),
    spec: str | TaskSpec = "anymal_d",
    physics: dict | None = None,
) -> tuple[Path, Path]:
    """Render `policy` in physics (of the robot `physics`, a dict of `PhysicsParams` fields; None: the MJCF's) through
    `VIDEO_COMMANDS`, clipped to the task's command ranges (tracking camera), as an animated GIF and one still PNG."""
    from PIL import Image, ImageDraw

    from rwm_gym.physics.locomotion import LocomotionEnv

    task = task_of(spec)
    act = resolve_policy(policy, 1, task)
    low, high = np.asarray(task.command.low), np.asarray(task.command.high)
    # the video's commands, not the task's random ones
    env = LocomotionEnv(
        task, render_mode="rgb_array", width=size[0], height=size[1], resample_commands=False, physics=physics
    )
    try:
        obs, _ = env.reset(seed=0)
        core = env.core
        every = max(1, round(1.0 / (fps * env.task_spec.policy_dt)))
        frames, stills = [], []
        for label, command in VIDEO_COMMANDS:
            core.command[0] = np.clip(command, low, high)
            obs = core.observe()[0]
            for t in range(round(seconds_each / env.task_spec.policy_dt)):
                obs, _, terminated, _, _ = env.step(act(obs[None])[0])
                if t % every == 0:
                    image = Image.fromarray(env.render())
                    ImageDraw.Draw(image).text((8, 8), label, fill=(255, 255, 255))
                    frames.append(image)
                if terminated:
                    break
            stills.append(frames[-1])
            if terminated:
                break
    finally:
        env.close()
    duration_ms = int(1000 * every * env.task_spec.policy_dt)
    gif = atomic_write(
        gif,
        lambda tmp: frames[0].save(
            tmp, format="GIF", save_all=True, append_images=frames[1:], duration=duration_ms, loop=0
        ),
    )
    still = atomic_write(still, lambda tmp: stills[0].save(tmp, format="PNG"))
    return gif, still


def summary_line(name: str, e: Evaluation) -> str:
    """One line of an evaluation: tracking, return, falls and velocity error."""
    return (
        f"{name}: tracking {e.tracking:.3f}, return {e.episode_return:.2f}, falls {e.falls}/{e.episodes}, "
        f"|dv_xy| {e.lin_vel_error:.3f} m/s"
    )

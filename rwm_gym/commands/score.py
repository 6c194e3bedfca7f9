"""`rwm-gym score`: a policy's tracking score beside the zero-action floor (`rwm_gym.rl.score`)."""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

from rwm_gym.atomic import write_json, write_text
from rwm_gym.commands._options import OverwriteOption, WorkerOptions, add_group, parse_physics
from rwm_gym.options import option
from rwm_gym.output_guard import OutputError, check_output, claim
from rwm_gym.rl.evaluate_policy import as_policy, format_table, plot
from rwm_gym.rl.score import SCRIPTED, record_walk, score, summary_line
from rwm_gym.workers import RayMissing, check_backend, uses_workers


@dataclass(frozen=True, kw_only=True)
class ScoreOptions:
    """The policy scored, where, on which episodes, and the folder written."""

    policy: str
    """SB3 .zip policy to score, or 'zero' (zero-action floor), 'gait' (the scripted trot) or 'random' (correlated
    random actions)"""
    out: Path
    """folder for score.json, score.md, score.png"""
    env: str | None = None
    """the task scored on, a physics env id (e.g. Go2-MuJoCo-v0) or a task spec file: its robot, command ranges and
    falls (default: --checkpoint's task, else the task the policy names, else the shipped ANYmal D task)"""
    checkpoint: str | None = None
    """score in this world model (the imagined env) instead of physics, same commands and seeds"""
    reset_data: Path | None = None
    """with --checkpoint: dataset of real histories the imagined episodes start from (default: the checkpoint's; the
    shipped one's are mostly early falls)"""
    seeds: int = option(3, ge=1)
    """episodes per command (default: 3)"""
    steps: int | None = option(None, ge=1)
    """policy steps per episode (default: the task's, 20 s)"""
    commands: int = option(16, ge=0)
    """random commands in the set, beside standing and 1 m/s forward (default: 16)"""
    video: bool = False
    """also write walk.gif and walk.png (needs offscreen GL)"""
    trust_entry_points: bool = False
    """with --checkpoint: import the reward / termination functions its task spec names ([imagination]); importing
    a module runs its code, so only for a checkpoint you trust"""
    physics: str | None = None
    """the robot scored on: a JSON dict of PhysicsParams, or a JSON file of one (e.g. a robot with hidden effects
    standing in for a measured one, or `rwm-gym gap`'s corrected_physics.json; default: the MJCF's robot). The zero
    floor is scored on the same robot"""


OPTIONS = (ScoreOptions, WorkerOptions, OverwriteOption)
"""The dataclasses the flags of `rwm-gym score` come from."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `rwm-gym score`."""
    for group in OPTIONS:
        add_group(parser, group)


def run(args: argparse.Namespace) -> int:
    """`rwm-gym score`: 0, or 2 with one line on stderr on bad input."""
    if args.policy not in SCRIPTED and not Path(args.policy).is_file():
        raise SystemExit(f"rwm-gym score: --policy {args.policy}: no such file")
    if uses_workers(args.workers, args.backend) and args.checkpoint is not None:
        raise SystemExit("rwm-gym score: --workers splits physics episodes; a --checkpoint scores in one process")
    if args.physics is not None and args.checkpoint is not None:
        raise SystemExit("rwm-gym score: --physics sets the robot in physics; a --checkpoint scores in a world model")
    try:
        args.physics = None if args.physics is None else parse_physics(args.physics)
    except ValueError as err:
        raise SystemExit(f"rwm-gym score: {err}") from None
    try:
        check_backend(args.backend)
    except RayMissing as err:
        raise SystemExit(f"rwm-gym score: {err}") from None
    if args.trust_entry_points and args.checkpoint is None:
        raise SystemExit("rwm-gym score: --trust-entry-points applies to --checkpoint (a world model's spec)")
    inputs = [None if args.policy in SCRIPTED else args.policy, args.checkpoint, args.reset_data]
    try:
        check_output(args.out, overwrite=True, folder=True)  # a folder (its files are checked one by one below)
        for name in ("score.md", "score.png", *(("walk.gif", "walk.png") if args.video else ())):
            check_output(args.out / name, inputs=inputs, overwrite=args.overwrite)
        report = check_output(args.out / "score.json", inputs=inputs, overwrite=args.overwrite)
        with claim(report):
            return _score(args)
    except OutputError as err:
        raise SystemExit(f"rwm-gym score: {err}") from None


def _task(args: argparse.Namespace, policy=None):
    """The task scored on: --env's, else --checkpoint's, else the one the policy names (`trained_task`), else ANYmal
    D's; one line on a bad --env, a mismatch or a policy of a task that is not registered."""
    from rwm_gym.registration import resolve_spec

    if args.env is None and args.checkpoint is None and policy is not None:
        from rwm_gym.rl.ppo import trained_task

        named = trained_task(policy)
        if named is not None:
            try:
                return resolve_spec(named)
            except ValueError:
                raise SystemExit(
                    f"rwm-gym score: --policy {args.policy} was made for {named}, which is not a registered physics "
                    "env: name its task with --env (its spec file)"
                ) from None
    try:
        task = resolve_spec(args.env or "anymal_d")
    except ValueError as err:
        raise SystemExit(f"rwm-gym score: --env: {err}") from None
    if args.checkpoint is not None:
        from rwm_gym.model.checkpoint import read_meta

        trained_on = read_meta(args.checkpoint).spec
        if args.env is not None and trained_on.name != task.name:
            raise SystemExit(f"rwm-gym score: --checkpoint is a {trained_on.name} model; --env is {task.name}")
        task = trained_on
    return task


def _score(args: argparse.Namespace) -> int:
    if args.policy not in SCRIPTED:
        from rwm_gym.policy_zip import check_spaces, load_policy

        model = load_policy(args.policy)
        task = _task(args, model)
        check_spaces(model, task, args.policy)  # refused here, in one line
        policy = as_policy(model)
    else:
        task, policy = _task(args), args.policy
    if args.reset_data is not None and args.checkpoint is None:
        raise SystemExit("rwm-gym score: --reset-data applies to --checkpoint (a world model)")
    if args.reset_data is not None and not args.reset_data.is_file():
        raise SystemExit(f"rwm-gym score: --reset-data {args.reset_data}: no such file")
    where = f"world model {args.checkpoint}" if args.checkpoint else f"physics ({task.physics_env_id})"
    if args.physics:
        where += " with " + ", ".join(f"{k}={v}" for k, v in args.physics.items())
    if args.reset_data is not None:
        where += f" from {args.reset_data}"
    options = dict(
        seeds=args.seeds,
        steps=args.steps,
        num_random=args.commands,
        checkpoint=args.checkpoint,
        reset_data=args.reset_data,
        workers=args.workers,
        backend=args.backend,
        physics=args.physics,
        trust_entry_points=args.trust_entry_points,
        spec=task,
    )
    in_workers = uses_workers(args.workers, args.backend)
    if in_workers:  # each worker loads the policy itself
        policy = args.policy
    result = score(policy, **options)
    floor = result if args.policy == "zero" else score("zero", **options)
    table = format_table(result)
    lines = [
        summary_line(f"policy {args.policy} in {where}", result),
        summary_line(f"zero-action floor in {where}", floor),
    ]
    print(table)
    print("\n".join(lines))
    args.out.mkdir(parents=True, exist_ok=True)
    write_text(
        args.out / "score.md",
        f"# Tracking score of {args.policy} in {where}\n\n```\n{table}\n```\n\n"
        + "\n".join(f"- {line}" for line in lines)
        + "\n",
    )
    plot(result, args.out / "score.png", title=lines[0])
    report = {
        "policy": str(args.policy),
        "where": where,
        "task": task.name,
        "physics": args.physics,
        "tracking": result.tracking,
        "return": result.episode_return,
        "falls": result.falls,
        "episodes": result.episodes,
        "floor": {"tracking": floor.tracking, "return": floor.episode_return, "falls": floor.falls},
        "evaluation": result.to_dict(),
        "floor_evaluation": floor.to_dict(),
    }
    write_json(args.out / "score.json", report)
    if args.video:
        gif, still = record_walk(policy, args.out / "walk.gif", args.out / "walk.png", spec=task, physics=args.physics)
        print(f"video: {gif}, still: {still}")
    print(f"wrote {args.out / 'score.json'}")
    return 0

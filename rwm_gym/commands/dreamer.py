"""`rwm-gym dreamer`: a Dreamer-style actor-critic on lambda-returns through a world model (`rwm_gym.rl.dreamer`), in
a resumable run folder, scored in physics at the end.

    rwm-gym dreamer --checkpoint CKPT --run-dir RUN --timesteps N [--minutes M] [--fall-tilt 30] --out policy.zip

The run folder has `TrainingRun`'s layout (latest.zip and state.json, snapshots/step_N.zip, log.csv with one row per
update: imagined return, actor gradient norm, return scale, entropy, ...), as `rwm-gym shac`'s; `latest_dreamer.pt`
beside latest.zip holds the optimisers, the slow critic, the return scale and the noise generator (tensors only).
Running the same command again continues to the same `--timesteps`; a resumed run restarts its envs from fresh
windows. The final policy's physics score (`rwm-gym score`'s episodes, `--score-seeds` per command) is printed and
written beside the zip as JSON.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import asdict, dataclass, fields
from pathlib import Path

from rwm_gym.commands._differentiable import IMAGINATION_FIELDS, append_log_row, jsonable, refuse_entry_points
from rwm_gym.commands._imagination import add_imagination_options, imagination_from_args
from rwm_gym.commands._options import (
    OverwriteOption,
    RunFolderOptions,
    TensorBoardOption,
    TorchOptions,
    WorldModelOptions,
    add_group,
)
from rwm_gym.imagination.options import ImaginationOptions
from rwm_gym.options import add_dataclass_options, dataclass_from_args, option
from rwm_gym.rl.dreamer import Dreamer, DreamerConfig

STATE_FILE = "latest_dreamer.pt"
"""The learner's own resume point beside the run folder's latest.zip."""


@dataclass(frozen=True)
class RunOptions:
    """The run's budget, what it writes and how its policy is scored."""

    timesteps: int = option(ge=1)
    """the run's budget in imagined env steps"""
    minutes: float | None = option(None, gt=0)
    """stop this process after this wall time (default: none, the --timesteps budget alone)"""
    seed: int = 0
    out: Path = Path("policy.zip")
    """SB3 zip of the final policy; its physics score goes beside it (OUT with .json)"""
    score_seeds: int = option(3, ge=0)
    """physics episodes per scoring command for the final score (0: no score)"""
    score_steps: int | None = option(None, ge=1)
    """policy steps per scoring episode (default: the task's 20 s)"""


OPTIONS = (
    RunOptions,
    RunFolderOptions,
    WorldModelOptions,
    TorchOptions,
    TensorBoardOption,
    OverwriteOption,
    DreamerConfig,
    ImaginationOptions,
)
"""The dataclasses the flags of `rwm-gym dreamer` come from."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `rwm-gym dreamer`."""
    add_group(parser, WorldModelOptions)
    add_imagination_options(parser, skip={f.name for f in fields(ImaginationOptions)} - set(IMAGINATION_FIELDS))
    add_dataclass_options(parser.add_argument_group("Dreamer-style learner"), DreamerConfig, nargs={"net_arch": "+"})
    add_group(parser, RunOptions)
    add_group(
        parser, RunFolderOptions, defaults=RunFolderOptions(save_every=20, snapshot_every=20), required={"run_dir"}
    )
    add_group(parser, TorchOptions)
    add_group(parser, TensorBoardOption)
    add_group(parser, OverwriteOption)


def run(args: argparse.Namespace) -> int:
    """`rwm-gym dreamer`: refuse an --out or --run-dir that would replace an input or another run's files (a run that
    resumes may rewrite its own), then train holding the lock of --out, and score the policy in physics."""
    from rwm_gym.output_guard import OutputError, check_folder, check_output, claim
    from rwm_gym.rl.training_run import TrainingRun
    from rwm_gym.tensorboard import check_tensorboard

    check_tensorboard(args.tensorboard, "rwm-gym dreamer")
    refuse_entry_points(args.checkpoint, "rwm-gym dreamer", "the Dreamer-style learner")
    run_folder = TrainingRun(args.run_dir)
    own = run_folder.resumable and (run_folder.folder / STATE_FILE).is_file()
    inputs = [args.checkpoint, args.reset_data]
    try:
        continues = own or (run_folder.folder.is_dir() and run_folder.holds_only_a_run())  # killed before a save
        check_folder(args.run_dir, inputs=inputs, overwrite=args.overwrite, continues=continues, flag="--run-dir")
        check_output(args.out, inputs=inputs, overwrite=args.overwrite or own)
        check_output(score_path(args.out), inputs=inputs, overwrite=args.overwrite or own)
        with claim(args.out):
            return _train(args)
    except OutputError as err:
        raise SystemExit(f"rwm-gym dreamer: {err}") from None


def score_path(out: Path) -> Path:
    """Where the final policy's physics score is written: beside the zip, with .json."""
    return Path(out).with_suffix(".json")


def _learner(args: argparse.Namespace, config: DreamerConfig):
    """The imagined core, its differentiable stepper, the SB3 model whose policy is trained, and the learner."""
    import torch

    from rwm_gym.imagination.core import ImaginedCore
    from rwm_gym.rl.ppo import make_ppo
    from rwm_gym.rl.shac import DifferentiableImagination
    from rwm_gym.vector.sb3_vec_env import CoreSB3VecEnv

    options = imagination_from_args(args)
    try:
        core = ImaginedCore(
            args.checkpoint, config.num_envs, device=args.device, reset_data=args.reset_data, options=options
        )
        imagination = DifferentiableImagination(core)
    except (ValueError, FileNotFoundError) as error:
        raise SystemExit(f"rwm-gym dreamer: {error}") from None
    torch.manual_seed(args.seed)
    model = make_ppo(CoreSB3VecEnv(core), config.ppo_config(), seed=args.seed, device=args.device)
    return core, imagination, model, Dreamer(imagination, model.policy, config, seed=args.seed), options


def _train(args: argparse.Namespace) -> int:
    import torch

    from rwm_gym.rl.policy_file import save_policy
    from rwm_gym.rl.training_run import TrainingRun

    if args.threads:
        torch.set_num_threads(args.threads)
    config = dataclass_from_args(DreamerConfig, args)
    core, imagination, model, learner, options = _learner(args, config)
    run_folder = TrainingRun(args.run_dir)
    environment = {"checkpoint": args.checkpoint and str(args.checkpoint), "imagination": asdict(options)}
    state = run_folder.state()
    resumed = run_folder.resumable and (run_folder.folder / STATE_FILE).is_file()
    if resumed and (state.get("dreamer") != jsonable(asdict(config)) or state.get("env") != jsonable(environment)):
        raise SystemExit(f"rwm-gym dreamer: {run_folder.folder} was started with other settings (see its state.json)")
    if resumed:
        from rwm_gym.policy_zip import load_policy

        model.policy.load_state_dict(load_policy(run_folder.latest, device=args.device).policy.state_dict())
        learner.load_state_dict(torch.load(run_folder.folder / STATE_FILE, weights_only=True))
        print(f"resuming {run_folder.folder} at {learner.timesteps:,} steps")
    restarts = state.get("restarts", -1) + 1
    seeds = [args.seed + 7919 * restarts + i for i in range(core.num_envs)]
    imagination.reset(list(range(core.num_envs)), seeds)
    record = {"dreamer": jsonable(asdict(config)), "env": jsonable(environment), "restarts": restarts}
    last = train(learner, model, run_folder, args, state.get("wall_s", 0.0) if resumed else 0.0, record)
    out = save_policy(model, args.out)
    print(f"{run_folder.folder}: {learner.timesteps:,} imagined steps in all; wrote {out}")
    if last is not None:
        print(
            f"last update: imagined return {last.imagined_return:.3f}, actor gradient norm "
            f"{last.actor_grad_norm:.3g}, return scale {last.return_scale:.3g}, entropy {last.entropy:.2f}"
        )
    if args.score_seeds:
        _score(args, learner, last)
    return 0


def _score(args: argparse.Namespace, learner: Dreamer, last) -> None:
    """The final policy's tracking in physics on its checkpoint's task, printed and written beside the zip."""
    from rwm_gym.atomic import write_json
    from rwm_gym.model.checkpoint import read_meta
    from rwm_gym.rl.score import score

    spec = learner.imagination.spec if args.checkpoint is None else read_meta(args.checkpoint).spec
    result = score(str(args.out), seeds=args.score_seeds, steps=args.score_steps, spec=spec)
    report = {
        "policy": str(args.out),
        "learner": "dreamer",
        "imagined_steps": learner.timesteps,
        "physics": {"tracking": result.tracking, "falls": result.falls, "episodes": result.episodes},
        "physics_return": result.episode_return,
        "last_update": None if last is None else asdict(last),
    }
    write_json(score_path(args.out), report)
    print(
        f"physics score: tracking {result.tracking:.3f}, falls {result.falls}/{result.episodes}, return "
        f"{result.episode_return:.2f}; wrote {score_path(args.out)}"
    )


def train(learner: Dreamer, model, run_folder, args: argparse.Namespace, prior_wall_s: float, record: dict):
    """Updates until `--timesteps` (or `--minutes`), with snapshots, resume points and one log row per update; the
    last update's statistics (None if none ran)."""
    import torch

    from rwm_gym.atomic import atomic_write, write_json
    from rwm_gym.progress import BudgetBar
    from rwm_gym.rl.policy_file import save_policy

    def save() -> None:
        save_policy(model, run_folder.latest)
        atomic_write(run_folder.folder / STATE_FILE, lambda tmp: torch.save(learner.state_dict(), tmp))
        wall = prior_wall_s + time.monotonic() - started
        write_json(run_folder.state_path, {**record, "timesteps": learner.timesteps, "wall_s": wall})

    run_folder.folder.mkdir(parents=True, exist_ok=True)
    writer = None
    if args.tensorboard is not None:
        from rwm_gym.tensorboard import summary_writer

        writer = summary_writer(args.tensorboard)
    config = learner.config
    bar = BudgetBar(steps=args.timesteps, minutes=None, desc="dreamer", initial=learner.timesteps, unit_scale=True)
    started, update, stats = time.monotonic(), learner.timesteps // (config.num_envs * config.horizon), None
    try:
        while learner.timesteps < args.timesteps:
            if args.minutes is not None and time.monotonic() - started >= 60 * args.minutes:
                break
            if update % args.snapshot_every == 0:
                save_policy(model, run_folder.snapshots / f"step_{learner.timesteps}.zip")
            stats = learner.update()
            update += 1
            append_log_row(run_folder.log_path, stats, prior_wall_s + time.monotonic() - started)
            if writer is not None:
                for name, value in asdict(stats).items():
                    if name != "timesteps":
                        writer.add_scalar(f"dreamer/{name}", value, stats.timesteps)
            bar.show(
                stats.timesteps,
                time.monotonic() - started,
                ret=f"{stats.imagined_return:.3f}",
                grad=f"{stats.actor_grad_norm:.2g}",
            )
            if update % args.save_every == 0:
                save()
        save()
    finally:
        bar.close()
        if writer is not None:
            writer.close()
    return stats

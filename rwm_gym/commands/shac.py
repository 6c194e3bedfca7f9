"""`rwm-gym shac`: train a policy by SHAC through a world model (`rwm_gym.rl.shac`), in a resumable run folder.

    rwm-gym shac --checkpoint CKPT --run-dir RUN --timesteps N [--minutes M] [--fall-tilt 30] --out policy.zip

The run folder has `TrainingRun`'s layout (latest.zip and state.json, snapshots/step_N.zip, log.csv with one row per
update), so `benchmarks/time_to_walk.py` and `benchmarks/ppo_curve.py` read it like a PPO run's; `latest_shac.pt`
beside latest.zip holds the optimisers, the target critic and the noise generator (tensors only). Running the same
command again continues to the same `--timesteps`; a resumed run restarts its envs from fresh windows.
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
from rwm_gym.rl.shac import SHAC, DifferentiableImagination, SHACConfig


@dataclass(frozen=True)
class RunOptions:
    """The run's budget and what it writes (its folder: `RunFolderOptions`)."""

    timesteps: int = option(ge=1)
    """the run's budget in imagined env steps"""
    minutes: float | None = option(None, gt=0)
    """stop this process after this wall time (default: none, the --timesteps budget alone)"""
    seed: int = 0
    out: Path = Path("policy.zip")
    """SB3 zip of the final policy"""


OPTIONS = (
    RunOptions,
    RunFolderOptions,
    WorldModelOptions,
    TorchOptions,
    TensorBoardOption,
    OverwriteOption,
    SHACConfig,
    ImaginationOptions,
)
"""The dataclasses the flags of `rwm-gym shac` come from."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `rwm-gym shac`."""
    add_group(parser, WorldModelOptions)
    add_imagination_options(parser, skip={f.name for f in fields(ImaginationOptions)} - set(IMAGINATION_FIELDS))
    add_dataclass_options(
        parser.add_argument_group("SHAC"),
        SHACConfig,
        nargs={"net_arch": "+"},
        choices={"activation": ("elu", "tanh", "relu")},
    )
    add_group(parser, RunOptions)
    add_group(
        parser, RunFolderOptions, defaults=RunFolderOptions(save_every=20, snapshot_every=20), required={"run_dir"}
    )
    add_group(parser, TorchOptions)
    add_group(parser, TensorBoardOption)
    add_group(parser, OverwriteOption)


def run(args: argparse.Namespace) -> int:
    """`rwm-gym shac`: refuse an --out or --run-dir that would replace an input or another run's files (a run that
    resumes may rewrite its own: running the command again continues it; else only with --overwrite), then train
    holding the lock of --out."""
    from rwm_gym.output_guard import OutputError, check_folder, check_output, claim
    from rwm_gym.rl.training_run import TrainingRun
    from rwm_gym.tensorboard import check_tensorboard

    check_tensorboard(args.tensorboard, "rwm-gym shac")
    refuse_entry_points(args.checkpoint)
    run_folder = TrainingRun(args.run_dir)
    own = run_folder.resumable and (run_folder.folder / "latest_shac.pt").is_file()
    inputs = [args.checkpoint, args.reset_data]
    try:
        continues = own or (run_folder.folder.is_dir() and run_folder.holds_only_a_run())
        check_folder(args.run_dir, inputs=inputs, overwrite=args.overwrite, continues=continues, flag="--run-dir")
        check_output(args.out, inputs=inputs, overwrite=args.overwrite or own)
        with claim(args.out):
            return _train(args)
    except OutputError as err:
        raise SystemExit(f"rwm-gym shac: {err}") from None


def _train(args: argparse.Namespace) -> int:
    import torch

    from rwm_gym.imagination.core import ImaginedCore
    from rwm_gym.rl.policy_file import save_policy
    from rwm_gym.rl.ppo import make_ppo
    from rwm_gym.rl.training_run import TrainingRun
    from rwm_gym.vector.sb3_vec_env import CoreSB3VecEnv

    if args.threads:
        torch.set_num_threads(args.threads)
    config = dataclass_from_args(SHACConfig, args)
    options = imagination_from_args(args)
    try:
        core = ImaginedCore(
            args.checkpoint, config.num_envs, device=args.device, reset_data=args.reset_data, options=options
        )
        imagination = DifferentiableImagination(core)
    except (ValueError, FileNotFoundError) as error:
        raise SystemExit(f"rwm-gym shac: {error}") from None
    torch.manual_seed(args.seed)
    run_folder = TrainingRun(args.run_dir)
    environment = {"checkpoint": args.checkpoint and str(args.checkpoint), "imagination": asdict(options)}
    state = run_folder.state()
    resumed = run_folder.resumable and (run_folder.folder / "latest_shac.pt").is_file()
    if resumed and (state.get("shac") != jsonable(asdict(config)) or state.get("env") != jsonable(environment)):
        raise SystemExit(f"rwm-gym shac: {run_folder.folder} was started with other settings (see its state.json)")
    model = make_ppo(CoreSB3VecEnv(core), config.ppo_config(), seed=args.seed, device=args.device)
    learner = SHAC(imagination, model.policy, config, seed=args.seed)
    if resumed:
        from rwm_gym.policy_zip import load_policy

        model.policy.load_state_dict(load_policy(run_folder.latest, device=args.device).policy.state_dict())
        learner.load_state_dict(torch.load(run_folder.folder / "latest_shac.pt", weights_only=True))
        print(f"resuming {run_folder.folder} at {learner.timesteps:,} steps")
    seed_offset = 7919 * (state.get("restarts", -1) + 1)
    imagination.reset(list(range(core.num_envs)), [args.seed + seed_offset + i for i in range(core.num_envs)])
    train(
        learner,
        model,
        run_folder,
        args,
        state.get("wall_s", 0.0) if resumed else 0.0,
        state.get("restarts", -1) + 1,
        config,
        environment,
    )
    out = save_policy(model, args.out)
    print(f"{run_folder.folder}: {learner.timesteps:,} imagined steps in all; wrote {out}")
    return 0


def train(
    learner: SHAC,
    model,
    run_folder,
    args: argparse.Namespace,
    prior_wall_s: float,
    restarts: int,
    config: SHACConfig,
    environment: dict,
) -> None:
    """Updates until `--timesteps` (or `--minutes`), with snapshots, resume points and one log row per update."""
    import torch

    from rwm_gym.atomic import atomic_write, write_json
    from rwm_gym.progress import BudgetBar
    from rwm_gym.rl.policy_file import save_policy

    def save() -> None:
        save_policy(model, run_folder.latest)
        atomic_write(run_folder.folder / "latest_shac.pt", lambda tmp: torch.save(learner.state_dict(), tmp))
        write_json(
            run_folder.state_path,
            {
                "shac": jsonable(asdict(config)),
                "env": jsonable(environment),
                "timesteps": learner.timesteps,
                "restarts": restarts,
                "wall_s": prior_wall_s + time.monotonic() - started,
            },
        )

    run_folder.folder.mkdir(parents=True, exist_ok=True)
    writer = None
    if args.tensorboard is not None:
        from rwm_gym.tensorboard import summary_writer

        writer = summary_writer(args.tensorboard)
    bar = BudgetBar(steps=args.timesteps, minutes=None, desc="shac", initial=learner.timesteps, unit_scale=True)
    started, update = time.monotonic(), learner.timesteps // (config.num_envs * config.horizon)
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
                    if name != "timesteps":  # the step itself
                        writer.add_scalar(f"shac/{name}", value, stats.timesteps)
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

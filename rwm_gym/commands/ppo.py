"""`rwm-gym ppo`: train PPO in imagination (or in physics), report what it cost, and judge it in physics.

The library half is `rwm_gym.rl.ppo` (settings, env, learner); this module is the command: options, the behaviour-
cloning warm start, the resumable run folder (`rwm_gym.rl.training_run`), and the JSON / PNG report beside the zip.
"""

from __future__ import annotations

import argparse
import json
import os
from dataclasses import asdict, dataclass
from pathlib import Path

from stable_baselines3.common.vec_env import VecEnv

from rwm_gym.commands._imagination import add_imagination_options, imagination_from_args, non_default
from rwm_gym.commands._options import (
    OverwriteOption,
    RunFolderOptions,
    TensorBoardOption,
    TorchOptions,
    WorldModelOptions,
    add_group,
    parse_physics,
)
from rwm_gym.imagination.options import ImaginationOptions
from rwm_gym.options import add_dataclass_options, dataclass_from_args, option
from rwm_gym.output_guard import OutputError, check_folder, check_output, claim
from rwm_gym.policy_zip import load_policy
from rwm_gym.rl.policy_file import save_policy
from rwm_gym.rl.ppo import (
    ACTIVATIONS,
    WHERE,
    PositiveReward,
    PPOConfig,
    TrainStats,
    learn,
    make_env,
    make_ppo,
    start_from,
    update_callbacks,
    warm_up_critic,
)
from rwm_gym.rl.warm_start import CloneConfig


def physics_samples(where: str, checkpoint: str | os.PathLike | None, trained_steps: int) -> tuple[int | None, str]:
    """Physics transitions the policy cost, and where that figure comes from (or why it is unknown): its own steps
    in physics; in imagination, the physics rows of the world model's whole lineage (its data and that of every
    model it was fine-tuned from, each source once: `rwm_gym.model.lineage`)."""
    if where == "physics":
        return trained_steps, "the policy's own physics steps"
    if checkpoint is None:
        from rwm_gym.imagination.core import default_checkpoint

        checkpoint = default_checkpoint()
    from rwm_gym.model.lineage import physics_rows

    return physics_rows(checkpoint)


def anneal_steps(config: PPOConfig, timesteps: int | None) -> float:
    """Env steps of the learning-rate anneal: `lr_anneal_fraction` of the whole `--timesteps` budget."""
    if config.lr_anneal_fraction and not timesteps:
        raise SystemExit("rwm-gym ppo: --lr-anneal-fraction needs a --timesteps budget (the anneal ends with it)")
    return config.lr_anneal_fraction * (timesteps or 0)


@dataclass(frozen=True)
class RunOptions:
    """What the run trains in, for how long, and what it writes."""

    where: str = option("imagination", flags=["--in"], choices=WHERE)
    """train in the imagined env (world model) or in physics (model-free baseline)"""
    timesteps: int | None = option(None, ge=0)
    """budget in env steps (default: none; with neither budget, --minutes 8)"""
    minutes: float | None = option(None, ge=0)
    """budget in wall-clock minutes (default: none; 8 when --timesteps is not given either)"""
    env: str | None = None
    """with --in physics: the physics env id or task spec to train in (default: the shipped legged task); a
    dm_control task is judged by its return and success"""
    seed: int = 0
    out: Path = Path("policy.zip")
    """SB3 zip to write (JSON and PNG beside)"""
    record_every: int = option(0, ge=0)
    """with --run-dir --in physics: write the episodes of every N-th env to experience/ as world-model data
    (0: none)"""
    physics: str | None = None
    """with --in physics: the robot trained on (and judged on after training), a JSON dict of PhysicsParams or a JSON
    file of one, e.g. `rwm-gym gap`'s corrected_physics.json (default: the MJCF's robot)"""
    init_policy: Path | None = None
    """SB3 zip whose network the policy starts from, instead of a fresh one (fine-tuning, e.g. in a corrected
    simulator); same observation, action and network sizes; the PPO settings are this command's"""


@dataclass(frozen=True)
class BCOptions:
    """Behaviour cloning of a demonstrator into the actor before PPO (rwm_gym.rl.warm_start)."""

    bc_data: tuple[Path, ...] | None = option(None, nargs="+")
    """datasets of a demonstrator (e.g. the scripted trot) whose actions the actor is cloned from before PPO
    (rwm_gym.rl.warm_start)"""
    bc_steps: int = option(CloneConfig.steps, ge=0)
    """behaviour-cloning Adam steps"""
    bc_log_std: float = option(CloneConfig.log_std, finite=True)
    """action log std after cloning"""
    bc_mirror: bool = False
    """clone the half of the commands the demonstrator tracks better and its left-right mirror image (the spec's
    [symmetry]), so a demonstrator that walks to one side only teaches both"""
    keep_best: bool = False
    """with --bc-data: if the physics tracking score after PPO is below the clone's, write the clone as --out (said
    in the output and the JSON; the PPO policy stays as *_ppo.zip)"""


@dataclass(frozen=True)
class EvalOptions:
    """The physics evaluation of the trained policy (rwm_gym.rl.evaluate_policy)."""

    eval: bool = True
    """judge the policy in physics after training (--no-eval: skip the physics evaluation)"""
    eval_seeds: int = option(3, ge=1)
    """physics episodes per evaluation command (a dm_control task: episodes, seeds 0..N-1)"""
    eval_steps: int | None = option(None, ge=1)
    """policy steps per evaluation episode (default: the task's episode, 20 s)"""


OPTIONS = (
    RunOptions,
    WorldModelOptions,
    TorchOptions,
    OverwriteOption,
    TensorBoardOption,
    RunFolderOptions,
    BCOptions,
    EvalOptions,
    PPOConfig,
    ImaginationOptions,
)
"""The dataclasses the flags of `rwm-gym ppo` come from."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `rwm-gym ppo`: the run, then one flag per `PPOConfig` and `ImaginationOptions` field."""
    for group in (RunOptions, WorldModelOptions, TorchOptions, OverwriteOption, TensorBoardOption):
        add_group(parser, group)
    add_group(parser, RunFolderOptions, "run folder")
    add_group(parser, BCOptions, "behaviour cloning")
    add_group(parser, EvalOptions, "evaluation")
    add_dataclass_options(
        parser.add_argument_group("PPO", "PPO's settings (rwm_gym.rl.ppo.PPOConfig)"),
        PPOConfig,
        defaults_none=True,
        nargs={"net_arch": "+"},
        choices={"activation": ACTIVATIONS},
    )
    add_imagination_options(parser)


def run(args: argparse.Namespace) -> int:
    """`rwm-gym ppo`: refuse an --out that would replace an input or another run's file, then train holding its
    lock; a --run-dir run may rewrite its own --out (running the command again resumes it)."""
    if (args.timesteps == 0 or args.minutes == 0) and not args.bc_data:
        raise SystemExit("rwm-gym ppo: a budget of 0 trains nothing (0 is for --bc-data: the cloned actor alone)")
    from rwm_gym.tensorboard import check_tensorboard

    check_tensorboard(args.tensorboard, "rwm-gym ppo")
    inputs = [args.checkpoint, args.reset_data, args.init_policy, *(args.bc_data or [])]
    from rwm_gym.rl.training_run import TrainingRun

    folder = TrainingRun(args.run_dir) if args.run_dir is not None else None
    own = folder is not None and folder.resumable  # a resumed run rewrites its own files
    try:
        if folder is not None:
            continues = own or (folder.folder.is_dir() and folder.holds_only_a_run())
            check_folder(args.run_dir, inputs=inputs, overwrite=args.overwrite, continues=continues, flag="--run-dir")
        for path in written_files(args):
            check_output(path, inputs=inputs, overwrite=args.overwrite or own)
        with claim(args.out):
            return _train(args)
    except OutputError as err:
        raise SystemExit(f"rwm-gym ppo: {err}") from None


def written_files(args: argparse.Namespace) -> list[Path]:
    """Every file `rwm-gym ppo` writes beside --out: the zip, its JSON report and PNG plot, the cloned actor
    (--bc-data) and the PPO policy --keep-best may set aside; each follows --overwrite."""
    out = Path(args.out)
    files = [out, out.with_suffix(".json")]
    if args.eval:
        files.append(out.with_suffix(".png"))
        if args.bc_data:
            files.append(out.with_name(out.stem + "_bc.zip"))
    if args.keep_best:
        files.append(out.with_name(out.stem + "_ppo.zip"))
    return files


def _train(args: argparse.Namespace) -> int:
    """Build the env and the learner, warm-start, train, save, judge in physics and write the report."""
    config = dataclass_from_args(PPOConfig, args)
    if args.threads:
        import torch

        torch.set_num_threads(args.threads)
    if args.timesteps is None and args.minutes is None:
        args.minutes = 8.0
    env_kwargs, imagined = _imagination(args)
    try:
        env = make_env(
            args.where,
            config.num_envs,
            checkpoint=args.checkpoint,
            device=args.device,
            seed=args.seed,
            env_kwargs=env_kwargs,
            physics_env=args.env,
        )
    except (ValueError, FileNotFoundError) as error:  # a checkpoint or reset data that cannot serve these options
        raise SystemExit(f"rwm-gym ppo: {error}") from None
    if args.init_policy is not None and args.bc_data:
        raise SystemExit("rwm-gym ppo: --init-policy and --bc-data both set the starting actor; give one")
    judged_on = env_kwargs if args.where == "physics" else {}  # the robot trained on, which every evaluation uses
    if args.run_dir is not None:
        if args.bc_data:
            raise SystemExit("rwm-gym ppo: --bc-data warm-starts a run without --run-dir (give --init-policy)")
        return run_resumable(args, config, env, imagined, judged_on)
    model = _fresh_model(args, env, config)
    warm = _behaviour_clone(args, model, judged_on)
    warmup = None
    if config.critic_warmup_steps and not (args.timesteps == 0 or args.minutes == 0):
        warmup = warm_up_critic(model, config.critic_warmup_steps)
        print(f"critic warm-up: {warmup.timesteps:,} {args.where} steps in {warmup.wall_s:.0f} s, actor frozen")
    if args.timesteps == 0 or args.minutes == 0:  # the warm start alone
        stats = TrainStats(0, 0.0, 0.0)
    else:
        stats = learn(
            model,
            timesteps=args.timesteps,
            minutes=args.minutes,
            target_kl=config.target_kl,
            callbacks=(*update_callbacks(config, model), *_tensorboard(args, model)),
            anneal_steps=anneal_steps(config, args.timesteps),
        )
    out = save_policy(model, args.out)
    print(
        f"trained {stats.timesteps:,} {args.where} steps in {stats.wall_s:.0f} s ({stats.steps_per_s:.0f} steps/s); "
        f"wrote {out}"
    )
    report = _report(args, config, judged_on, imagined, warm, stats.timesteps + (warmup.timesteps if warmup else 0))
    report["critic_warmup"] = None if warmup is None else asdict(warmup)
    report["train"] = asdict(stats)
    _judge_and_write(args, model, out, warm, report, judged_on)
    return 0


def _report(
    args: argparse.Namespace, config: PPOConfig, judged_on: dict, imagined: dict, warm: _WarmStart, steps: int
) -> dict:
    """The report's settings and the physics samples behind a policy trained for `steps` steps (printed)."""
    report = {
        "where": args.where,
        "checkpoint": args.checkpoint,
        "env": args.env,
        "physics": judged_on.get("physics"),
        "init_policy": None if args.init_policy is None else str(args.init_policy),
        "seed": args.seed,
        "ppo": config.to_dict(),
        "imagination": imagined,
        "behaviour_cloning": warm.report(args),
        "kept": "ppo",  # which policy --out holds; --keep-best may hand back the clone
    }
    report["physics_samples"], report["physics_samples_source"] = physics_samples(args.where, args.checkpoint, steps)
    from rwm_gym.model.lineage import n_mf, share_text

    samples, task = report["physics_samples"], _task_trained_on(args).physics_env_id
    n = n_mf(task)
    report["fraction_of_n_mf"] = None if samples is None or n is None else samples / n
    print(f"physics samples behind the policy: {share_text(samples, task)} ({report['physics_samples_source']})")
    return report


def _judge_and_write(
    args: argparse.Namespace, model, out: Path, warm: _WarmStart, report: dict, judged_on: dict
) -> None:
    """Judge the policy in physics (unless --no-eval) and write the report beside --out."""
    from rwm_gym.atomic import write_json

    if args.eval:
        _judge(args, model, out, warm, report, judged_on)
    print(f"report: {write_json(out.with_suffix('.json'), report)}")


def _fresh_model(args: argparse.Namespace, env: VecEnv, config: PPOConfig):
    """A new PPO learner on `env`: a fresh network, or --init-policy's weights."""
    model = make_ppo(env, config, seed=args.seed, device=args.device)
    if args.init_policy is not None:
        try:
            start_from(model, args.init_policy)
        except (ValueError, FileNotFoundError) as err:
            raise SystemExit(f"rwm-gym ppo: {err}") from None
        print(f"starting from the network of {args.init_policy}")
    return model


def _tensorboard(args: argparse.Namespace, model) -> tuple:
    """With --tensorboard: `model` logs to TensorBoard, and the callbacks that add the env's scalars."""
    if args.tensorboard is None:
        return ()
    from rwm_gym.rl.tensorboard import tensorboard_callbacks, tensorboard_logger

    return tensorboard_callbacks(model, tensorboard_logger(args.tensorboard))


def _imagination(args: argparse.Namespace) -> tuple[dict, dict]:
    """The imagined env's kwargs (its `ImaginationOptions` and reset data) and what the run records of them: the
    options given (those that differ from the defaults); refused for --in physics."""
    options = imagination_from_args(args)
    imagined = {**non_default(options), **({"reset_data": str(args.reset_data)} if args.reset_data else {})}
    refused = [k for k in imagined if k != "episode_steps"]  # --in physics has always ignored --episode-steps
    if args.env is not None and args.where != "physics":
        raise SystemExit("rwm-gym ppo: --env applies to --in physics (an imagined env's task is its --checkpoint's)")
    if refused and args.where != "imagination":
        raise SystemExit(
            f"rwm-gym ppo: {', '.join('--' + k.replace('_', '-') for k in refused)} apply to --in imagination"
        )
    if args.physics is not None and args.where != "physics":
        raise SystemExit("rwm-gym ppo: --physics applies to --in physics (a world model is the robot it learnt)")
    if args.where != "imagination":
        try:
            return ({"physics": parse_physics(args.physics)} if args.physics else {}), {}
        except ValueError as err:
            raise SystemExit(f"rwm-gym ppo: {err}") from None
    return {"options": options, "reset_data": args.reset_data}, imagined


@dataclass
class _WarmStart:
    """The behaviour-cloned actor (`--bc-data`): its statistics, its physics evaluation and its zip."""

    cloned: object = None
    evaluation: object = None
    path: Path | None = None

    def report(self, args: argparse.Namespace) -> dict | None:
        if self.cloned is None:
            return None
        return {
            "data": [str(p) for p in args.bc_data],
            **self.cloned.to_dict(),
            "evaluation": self.evaluation.to_dict() if args.eval else None,
        }


def _behaviour_clone(args: argparse.Namespace, model, env_kwargs: dict | None = None) -> _WarmStart:
    """With --bc-data: clone the demonstrator's actions into the actor and judge the clone alone in physics, on the
    robot PPO trains on (`env_kwargs`: its physics, with --in physics --physics), so --keep-best compares like with
    like."""
    from rwm_gym.rl.evaluate_policy import evaluate_policy, format_table

    if not args.bc_data:
        return _WarmStart()
    from rwm_gym.rl.warm_start import behaviour_clone

    warm = _WarmStart(
        behaviour_clone(
            model,
            args.bc_data,
            CloneConfig(steps=args.bc_steps, log_std=args.bc_log_std, mirror=args.bc_mirror, seed=args.seed),
            progress=True,
        )
    )
    cloned = warm.cloned
    held_out = "none" if cloned.val_mse_after is None else f"{cloned.val_mse_after:.3f}"
    print(
        f"behaviour cloning: {cloned.pairs:,} pairs from {cloned.episodes} episodes, action MSE "
        f"{cloned.train_mse_before:.3f} -> {cloned.train_mse_after:.3f} (held out: {held_out}) "
        f"in {cloned.wall_s:.0f} s"
    )
    if args.eval:  # the warm start alone, so the effect of PPO is plain to see
        warm.evaluation = evaluate_policy(
            model,
            seeds=range(args.eval_seeds),
            steps=args.eval_steps,
            spec=_task_trained_on(args),
            env_kwargs=env_kwargs,
        )
        print("physics evaluation of the cloned actor, before PPO:")
        print(format_table(warm.evaluation))
        save_policy(model, out_bc := args.out.with_name(args.out.stem + "_bc.zip"))
        warm.path = out_bc
        print(f"wrote {out_bc}")
    return warm


def _task_trained_on(args: argparse.Namespace):
    """The task spec trained on: --env's in physics, the --checkpoint's in imagination, else the shipped ANYmal D."""
    from rwm_gym.registration import resolve_spec

    if args.where == "physics" and args.env is not None:
        return resolve_spec(args.env)
    if args.where == "imagination" and args.checkpoint is not None:
        from rwm_gym.model.checkpoint import read_meta

        return read_meta(args.checkpoint).spec
    return resolve_spec("anymal_d")


def _dm_control_task(args: argparse.Namespace):
    """The task spec trained on when it is a dm_control task (judged by its return and success), else None."""
    from rwm_gym.registration import simulator_of

    spec = _task_trained_on(args)
    return spec if simulator_of(spec) == "dm_control" else None


def _judge(
    args: argparse.Namespace, model, out: Path, warm: _WarmStart, report: dict, env_kwargs: dict | None = None
) -> None:
    """The physics evaluation after PPO into `report`, on the robot trained on (`env_kwargs`: its physics, with
    --in physics --physics); with --keep-best, the clone as --out if PPO made it worse.

    A dm_control task is judged by its own return over full episodes (and its success, for a manipulation task) in
    its physics env, seeds 0..--eval-seeds - 1 (`rwm_gym.rl.evaluate_dmc`); the legged task by its tracking score."""
    from rwm_gym.rl.evaluate_policy import evaluate_policy, format_table, plot

    dm_control = _dm_control_task(args)
    if dm_control is not None:
        if args.keep_best:
            raise SystemExit("rwm-gym ppo: --keep-best compares tracking scores, which a dm_control task has not")
        from rwm_gym.rl.evaluate_dmc import evaluate_episodes

        episodes = evaluate_episodes(model, dm_control, seeds=args.eval_seeds, steps=args.eval_steps)
        print(f"physics evaluation: {episodes.summary()}")
        report["evaluation"] = episodes.to_dict()
        return
    evaluation = evaluate_policy(
        model, seeds=range(args.eval_seeds), steps=args.eval_steps, spec=_task_trained_on(args), env_kwargs=env_kwargs
    )
    print("physics evaluation" + (" after PPO:" if warm.cloned else ":"))
    print(format_table(evaluation))
    report["evaluation"] = evaluation.to_dict()
    cloned_eval = warm.evaluation
    if args.keep_best and warm.cloned is not None and cloned_eval.tracking > evaluation.tracking:
        os.replace(out, out.with_name(out.stem + "_ppo.zip"))
        save_policy(load_policy(warm.path, device=args.device), out)
        evaluation, report["kept"] = cloned_eval, "behaviour_cloning"
        print(
            f"PPO made the policy worse in physics (tracking {cloned_eval.tracking:.3f} -> "
            f"{report['evaluation']['tracking']:.3f}, falls {cloned_eval.falls} -> "
            f"{report['evaluation']['falls']}): {out} is the cloned actor, the PPO policy is "
            f"{out.with_name(out.stem + '_ppo.zip')}"
        )
    elif warm.cloned is not None:
        print(
            f"{out} is the PPO policy (physics tracking {cloned_eval.tracking:.3f} cloned -> "
            f"{evaluation.tracking:.3f} after PPO)"
        )
    print(f"plot: {plot(evaluation, out.with_suffix('.png'))}")


def _run_environment(args: argparse.Namespace, imagined: dict, judged_on: dict) -> dict:
    """What a run folder records of the env it trains in (a resumed run must train in the same one)."""
    environment = {"where": args.where, "checkpoint": args.checkpoint and str(args.checkpoint), "imagination": imagined}
    if args.env is not None:
        environment["env"] = args.env
    if judged_on.get("physics"):
        environment["physics"] = judged_on["physics"]
    if args.init_policy is not None:
        environment["init_policy"] = str(args.init_policy)
    return environment


def run_resumable(
    args: argparse.Namespace, config: PPOConfig, env: VecEnv, imagined: dict, judged_on: dict | None = None
) -> int:
    """`rwm-gym ppo --run-dir RUN`: train to `--timesteps` and/or `--minutes` of training in all (whichever ends
    first, counted over every restart) in a folder that survives a killed process, then judge the policy in physics
    (on `judged_on`'s robot, the one trained on) and write the report beside --out."""
    from rwm_gym.rl.training_run import RunCheckpoint, TrainingRun, resume_model

    run = TrainingRun(args.run_dir)
    state = run.state()
    saved = {**json.loads(json.dumps(PPOConfig().to_dict())), **state.get("ppo", {})}  # a field added since: default
    if run.resumable and saved != json.loads(json.dumps(config.to_dict())):
        raise SystemExit(f"rwm-gym ppo: {run.folder} was started with other PPO settings (see its state.json)")
    judged_on = judged_on or {}
    environment = _run_environment(args, imagined, judged_on)
    if run.resumable and state.get("env", environment) != json.loads(json.dumps(environment)):
        raise SystemExit(
            f"rwm-gym ppo: {run.folder} was started in another env ({state['env']}); use another --run-dir"
        )
    recorder = None
    if args.record_every:
        if args.where != "physics":
            raise SystemExit("rwm-gym ppo: --record-every records physics experience; use it with --in physics")
        from rwm_gym.rl.experience import RecordingCore

        env.core = recorder = RecordingCore(
            env.core,
            run.next_experience_file(),
            every=args.record_every,
            policy=f"ppo ({args.run_dir})",
            seed=args.seed,
        )
    if run.resumable:
        env.seed(args.seed + 7919 * (state["restarts"] + 1))  # fresh episodes, not a replay of the first start
        model = resume_model(run, PositiveReward(env) if config.positive_reward_only else env, args.device)
        print(f"resuming {run.folder} at {model.num_timesteps:,} steps (restart {state['restarts'] + 1})")
    else:
        model = _fresh_model(args, env, config)
    checkpoint = RunCheckpoint(
        run,
        config,
        save_every=args.save_every,
        snapshot_every=args.snapshot_every,
        recorder=recorder,
        prior_wall_s=state.get("wall_s", 0.0),
        restarts=state.get("restarts", -1) + 1,
        environment=environment,
    )
    remaining = args.timesteps - model.num_timesteps if args.timesteps else None
    minutes_left = None if args.minutes is None else args.minutes - state.get("wall_s", 0.0) / 60.0
    try:
        if (remaining is None or remaining > 0) and (minutes_left is None or minutes_left > 0):
            learn(
                model,
                timesteps=remaining,
                minutes=minutes_left,
                target_kl=config.target_kl,
                callbacks=(checkpoint, *update_callbacks(config, model), *_tensorboard(args, model)),
                on_rollout=checkpoint.log_row,
                anneal_steps=anneal_steps(config, args.timesteps),
            )
            checkpoint.save()
        else:
            budget = f"{args.timesteps:,} steps" if remaining is not None and remaining <= 0 else f"{args.minutes} min"
            print(f"{run.folder} already has its {budget}")
    finally:
        if recorder is not None:
            recorder.close()
    out = save_policy(model, args.out)
    print(f"{run.folder}: {model.num_timesteps:,} steps in all; wrote {out}")
    report = _report(args, config, judged_on, imagined, _WarmStart(), model.num_timesteps)
    state = run.state()
    report["run_dir"] = str(run.folder)
    report["train"] = {
        "timesteps": int(model.num_timesteps),
        "wall_s": state.get("wall_s"),
        "restarts": state.get("restarts"),
    }
    _judge_and_write(args, model, out, _WarmStart(), report, judged_on)
    return 0

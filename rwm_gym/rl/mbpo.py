"""MBPO-PPO (`rwm-gym mbpo`): the RWM paper's online loop, resumable, every physics sample counted.

Iteration k: (1) PPO continues in imagination on model k-1, its episodes restarting from real histories of the
buffer; (2) the policy's tracking score is measured in physics; (3) physics episodes are collected with it, acting
with no noise, half and all of its own current std (the deterministic policy that is judged, and the exploration PPO
used in imagination); (4) the model's error on that fresh data is measured (the states the policy now visits); (5) the
model is fine-tuned (or retrained) on the buffer:
`base_episodes` episodes of the starting data plus every fresh episode so far, so the states an imagined policy
exploits get real data (the cause of exploitation is missing coverage, and this is its fix).

Physics samples are the starting data's rows plus every collected row. The folder holds each iteration's policy,
model and fresh data, and `mbpo.json` (config, log). The same command run again resumes after the last finished
iteration: each iteration reloads its inputs from those files and is seeded by (seed, k), so a resumed run gives the
numbers of one never stopped.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import TYPE_CHECKING

from tqdm import tqdm

from rwm_gym.imagination.options import ImaginationOptions
from rwm_gym.options import check_ranges, option
from rwm_gym.rl.mbpo_curve import TRACKING_TARGET, plot_curve, read_curve  # noqa: F401  (their home before)
from rwm_gym.spec import TaskSpec

if TYPE_CHECKING:
    from rwm_gym.model.config import TrainConfig

TENSORBOARD_FIELDS = (
    "tracking",
    "falls",
    "physics_return",
    "lin_vel_error",
    "yaw_rate_error",
    "physics_samples",
    "imagined_steps",
    "imagined_step_reward",
)
"""The fields of an iteration's log row written as TensorBoard scalars `mbpo/<field>` (beside the model's error)."""

RESUME_MAY_CHANGE = ("iterations",)
"""MBPOConfig fields a resumed run may set differently; the others must match the folder's."""


@dataclass(frozen=True)
class MBPOConfig:
    """Budget of one MBPO-PPO run (PPO's own settings are `PPOConfig`)."""

    iterations: int = option(4, ge=0)
    """Loop iterations (0: only iteration 0, the starting model and policy scored)."""
    ppo_timesteps: int = option(300_000, ge=1)
    """Imagined steps of PPO per iteration."""
    num_envs: int = option(512, ge=1)
    """Imagined envs."""
    positive_reward_only: bool = False
    """PPO sees each imagined step's reward clipped at 0 from below (`PPOConfig.positive_reward_only`); also for an
    `init_policy`, whose zip does not carry it."""
    log_std_init: float = option(0.0, finite=True)
    """Initial log std of a fresh policy (`PPOConfig.log_std_init`; an `init_policy` keeps its own)."""
    symmetry: bool = False
    """PPO trains on each imagined sample and its left-right mirror image (`PPOConfig.symmetry`; the task spec's
    `[symmetry]` table)."""
    collect_episodes: int = option(32, ge=1)
    """Physics episodes collected per iteration."""
    collect_steps: int = option(250, ge=1)
    """Cap on a collected episode's length (policy steps)."""
    action_noise: float | None = option(None, ge=0)
    """Gaussian std added to the policy's actions while collecting (default: a third of the episodes each at 0, half
    and all of the policy's own mean std: the states of the deterministic policy the score judges and of the exploring
    one PPO runs in imagination)."""
    base_episodes: int = option(0, ge=0)
    """Episodes of the starting data kept in the buffer beside the fresh ones (0: all of it)."""
    model_iterations: int = option(1000, ge=1)
    """World-model gradient steps per retraining."""
    model_finetune: bool = False
    """Fine-tune the current world model on the buffer instead of retraining it from scratch."""
    model_lr: float = option(1e-3, gt=0)
    """Adam learning rate of the world-model (re)training (lower it for fine-tuning, e.g. 3e-4)."""
    model_recent_share: float = option(0.0, ge=0, le=1)
    """Share of each model training batch drawn from the episodes the iteration just collected
    (`TrainConfig.recent_share`; 0: every buffer window alike)."""
    critic_warmup_steps: int = option(0, ge=0)
    """Imagined steps that train only the critic of `init_policy` before the first PPO iteration."""
    eval_seeds: int = option(3, ge=1)
    """Physics evaluation episodes per command (3 with full episodes: the tracking score)."""
    eval_steps: int | None = option(None, ge=1)
    """Policy steps per physics evaluation episode (None: the task's episode)."""
    seed: int = 0
    """Seeds PPO, collection and model training (each iteration offsets it)."""
    imagination: ImaginationOptions = field(default_factory=lambda: ImaginationOptions(episode_steps=250))
    """How PPO's imagined episodes run (their time limit: 250 policy steps; PPO bootstraps at the limit)."""

    def __post_init__(self) -> None:
        check_ranges(self)

    def to_dict(self) -> dict:
        """The config as JSON-ready data (`imagination` a nested dict), as `mbpo.json` stores it."""
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> MBPOConfig:
        """The config of a `to_dict`, also of a run folder from before `imagination` was nested (its fields flat
        beside the loop's, the time limit named `imagined_episode_steps`); a field added since gets its default."""
        data = dict(data)
        nested = data.pop("imagination", None)
        if nested is None:  # the flat layout of 0.1
            names = {f.name for f in fields(ImaginationOptions)}
            nested = {k: data.pop(k) for k in [k for k in data if k in names]}
            nested["episode_steps"] = data.pop("imagined_episode_steps", cls().imagination.episode_steps)
        known = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in data.items() if k in known}, imagination=replace(cls().imagination, **nested))


def mbpo(
    data: str | Path,
    out: str | Path,
    config: MBPOConfig = MBPOConfig(),
    *,
    checkpoint: str | Path | None = None,
    init_policy: str | Path | None = None,
    model_kind: str = "rwm",
    device: str = "cpu",
    model_free_curve: str | Path | None = None,
    progress: bool = True,
    tensorboard: str | Path | None = None,
    start_train: TrainConfig | None = None,
    start_model: dict | None = None,
) -> dict:
    """Run (or resume) the loop from the dataset `data` in the folder `out`; returns the report (`out/mbpo.json`).

    checkpoint: the world model to start from (default: trained on `data` first, with `model_iterations` steps;
    five ensemble heads when the uncertainty penalty or halt is on, else one). start_train: the `TrainConfig` of that
    first training instead (its own iterations, batch and lr; the loop's seed and device); start_model: fields of its
    `ModelConfig` (e.g. `unit_gravity`) on top of the kind's defaults.
    init_policy: an SB3 PPO zip to start from (its saved PPO settings are kept); default a fresh `PPOConfig` policy.
    model_free_curve: a CSV with `timesteps` and `tracking` columns (a model-free PPO run's physics curve, e.g.
    `benchmarks/ppo_curve.py`'s) drawn beside the loop's in `mbpo.png`.
    tensorboard: a folder for TensorBoard event files: PPO's scalars at its imagined steps (`rwm_gym.rl.tensorboard`)
    and, at each iteration k as the step, `mbpo/<field>` of its log row (physics tracking, falls, return and velocity
    errors, samples, imagined steps and reward) and `mbpo/model_error_fresh/<horizon>`.
    """
    from rwm_gym.data.dataset import Dataset
    from rwm_gym.imagination.reset_data import make_reset_data
    from rwm_gym.model.checkpoint import read_meta

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    model_free = read_curve(model_free_curve) if model_free_curve else None
    report_path = out / "mbpo.json"
    report = json.loads(report_path.read_text()) if report_path.exists() else None
    if report is not None:
        _check_resume(report, config, report_path)
    starting = Dataset.load(data)
    loop = _Loop(out, config, device, progress, model_free, tensorboard, starting.spec())
    loop.start_train, loop.start_model = start_train, dict(start_model or {})
    started = time.monotonic()
    if not loop.base.exists():  # a file of the starting data: the buffer's fixed part and the first reset histories
        keep = config.base_episodes or starting.num_episodes
        make_reset_data(starting, loop.base, episodes=keep, rows=starting.spec().episode_steps + 1, seed=config.seed)
    if report is None:  # iteration 0: the starting model and policy, scored
        report = loop.start(data, starting, checkpoint, init_policy, model_kind, started)
    loop.model_config = read_meta(loop.model_path(0)).model_config
    report.setdefault("task", starting.spec().physics_env_id)  # a report written before it named its task
    started = time.monotonic() - report["log"][-1]["wall_s"]
    done = report["log"][-1]["iteration"]
    for k in tqdm(
        range(done + 1, config.iterations + 1), desc="mbpo", disable=not progress, initial=done, total=config.iterations
    ):
        loop.iteration(k, report, started, starting.spec().physics_env_id)
    plot_curve(report["log"], out / "mbpo.png", model_free)  # also when resumed with nothing left to run
    return report


class _Loop:
    """The steps of one run folder's loop: its files, the imagined env, (re)training and one iteration."""

    def __init__(
        self,
        out: Path,
        config: MBPOConfig,
        device: str,
        progress: bool,
        model_free,
        tensorboard: str | Path | None,
        spec: TaskSpec,
    ) -> None:
        from rwm_gym.rl.ppo import PPOConfig
        from rwm_gym.rl.tensorboard import tensorboard_logger

        self.out, self.config, self.device, self.progress, self.model_free = out, config, device, progress, model_free
        self.logger = None if tensorboard is None else tensorboard_logger(tensorboard)
        self.base = out / "buffer_base.h5"
        self.spec = spec
        """The task the data come from, and the policies are judged on."""
        self.model_config = None
        self.start_train, self.start_model = None, {}
        self.ppo_config = PPOConfig(
            num_envs=config.num_envs,
            log_std_init=config.log_std_init,
            positive_reward_only=config.positive_reward_only,
            symmetry=config.symmetry,
        )

    def model_path(self, k: int) -> Path:
        return self.out / f"model_{k}.safetensors"

    def env(self, k: int, reset_data: Path):
        """The imagined env of iteration k: model k-1 (k=0: the starting one), episodes restarting from `reset_data`."""
        from rwm_gym.rl.ppo import make_env

        return make_env(
            "imagination",
            self.config.num_envs,
            checkpoint=self.model_path(max(k - 1, 0)),
            device=self.device,
            seed=self.config.seed + k,
            env_kwargs={"options": self.config.imagination, "reset_data": reset_data},
        )

    def trained_on(self, env):
        """What a loaded policy learns from: the zip keeps PPO's settings, not the reward clip."""
        from rwm_gym.rl.ppo import PositiveReward

        return PositiveReward(env) if self.config.positive_reward_only else env

    def retrain(self, buffer: Path, k: int, previous: Path | None) -> Path:
        """Model k trained on `buffer` (fine-tuned from `previous` with `model_finetune`); the starting model (k=0,
        no `previous`) with `start_train`'s budget and rate where given."""
        from rwm_gym.model.checkpoint import CheckpointError, read_meta
        from rwm_gym.model.config import TrainConfig
        from rwm_gym.model.train import train

        config = self.config
        previous_config = read_meta(previous).train_config if previous is not None else TrainConfig()
        train_config = replace(
            previous_config,
            iterations=config.model_iterations,
            minutes=0.0,
            seed=config.seed + k,
            device=self.device,
            lr=config.model_lr,
            val_every=max(1, config.model_iterations // 4),
            checkpoint_every=config.model_iterations,
            recent_episodes=config.collect_episodes if config.model_recent_share else 0,
            recent_share=config.model_recent_share,
        )
        if previous is None and self.start_train is not None:
            train_config = replace(self.start_train, seed=config.seed, device=self.device)
        init = previous if config.model_finetune else None
        out = self.model_path(k)
        settings = dict(progress=self.progress, init=init)
        if out.exists():  # a killed run's checkpoint of this model: continue it (a finished one returns at once)
            try:
                return train(buffer, self.model_config, train_config, out, resume=True, **settings).path
            except CheckpointError as error:  # another run's model: trained again below
                tqdm.write(f"{out}: not resumed ({error}); training it again")
        return train(buffer, self.model_config, train_config, out, overwrite=True, **settings).path

    def start(self, data, starting, checkpoint, init_policy, model_kind: str, started: float) -> dict:
        """Iteration 0: the starting model (trained on `data`, or a copy of `checkpoint`) and policy, scored."""
        from rwm_gym.model.checkpoint import read_meta
        from rwm_gym.model.factory import model_config_for
        from rwm_gym.policy_zip import load_policy
        from rwm_gym.rl.evaluate_policy import evaluate_policy
        from rwm_gym.rl.ppo import make_ppo, save_policy, warm_up_critic

        config = self.config
        if checkpoint is None:  # RWM-U's five heads where a penalty or halt reads their disagreement
            uncertain = config.imagination.acts_on_disagreement
            self.model_config = model_config_for(
                model_kind, starting.spec(), **{"ensemble_size": 5 if uncertain else 1, **self.start_model}
            )
            self.retrain(self.base if config.base_episodes else Path(data), 0, None)
        else:
            self.model_config = read_meta(checkpoint).model_config
            self.model_path(0).write_bytes(Path(checkpoint).read_bytes())
        env = self.env(0, self.base)
        if init_policy is not None:
            policy = load_policy(init_policy, env=self.trained_on(env), device=self.device)
            if config.critic_warmup_steps:
                warm_up_critic(policy, config.critic_warmup_steps, progress=self.progress)
        else:
            policy = make_ppo(env, self.ppo_config, seed=config.seed, device=self.device)
        save_policy(policy, self.out / "policy_0.zip")
        evaluation = evaluate_policy(policy, seeds=range(config.eval_seeds), steps=config.eval_steps, spec=self.spec)
        report = {
            "task": self.spec.physics_env_id,
            "config": config.to_dict(),
            "data": str(data),
            "start_checkpoint": None if checkpoint is None else str(checkpoint),
            "start_train": None if checkpoint is not None or self.start_train is None else self.start_train.to_dict(),
            "ppo": self.ppo_config.to_dict() if init_policy is None else {"init_policy": str(init_policy)},
            "log": [
                {
                    "iteration": 0,
                    "imagined_steps": 0,
                    "imagined_step_reward": None,
                    **_physics(evaluation),
                    "model_error_fresh": None,
                    "physics_samples": _starting_rows(starting, self.model_path(0)),
                    "learning_rate": policy.learning_rate,
                    "wall_s": time.monotonic() - started,
                }
            ],
        }
        self.write_report(report)
        self.log_row(report["log"][0])
        tqdm.write(f"iteration 0: physics tracking {evaluation.tracking:.3f}, falls {evaluation.falls}")
        return report

    def iteration(self, k: int, report: dict, started: float, physics_env_id: str) -> None:
        """Iteration k (PPO in imagination, physics score, collection, model error, retraining), logged in `report`."""
        from rwm_gym.data.dataset import Dataset, is_merge_of, merge_datasets
        from rwm_gym.model.evaluate import EvalConfig, evaluate_checkpoint
        from rwm_gym.model.lineage import share_text
        from rwm_gym.rl.evaluate_policy import evaluate_policy, format_table
        from rwm_gym.rl.ppo import learn, load_ppo, save_policy, update_callbacks
        from rwm_gym.rl.tensorboard import tensorboard_callbacks

        config, out, previous = self.config, self.out, report["log"][-1]
        fresh_files = [out / f"data_{j}.h5" for j in range(1, k)]
        buffer = out / "buffer.h5" if fresh_files else self.base
        if fresh_files and not is_merge_of(buffer, [self.base, *fresh_files]):  # written by the iteration before
            merge_datasets([self.base, *fresh_files], buffer)
        # the same path whether resumed or not
        policy = load_ppo(
            out / f"policy_{k - 1}.zip", self.trained_on(self.env(k, buffer)), self.ppo_config, device=self.device
        )
        policy.learning_rate = previous["learning_rate"]
        policy._setup_lr_schedule()
        policy.set_random_seed(config.seed + k)
        stats = learn(
            policy,
            timesteps=config.ppo_timesteps,
            target_kl=self.ppo_config.target_kl,
            progress=self.progress,
            callbacks=(*update_callbacks(self.ppo_config, policy), *tensorboard_callbacks(policy, self.logger)),
        )
        zip_path = save_policy(policy, out / f"policy_{k}.zip")
        evaluation = evaluate_policy(policy, seeds=range(config.eval_seeds), steps=config.eval_steps, spec=self.spec)
        noise = config.action_noise
        if noise is None:  # the deterministic policy the score judges, and the exploring one PPO runs in imagination
            std = float(policy.policy.log_std.detach().exp().mean())
            noise = [0.0, std / 2, std]
        fresh = _collect(
            physics_env_id,
            zip_path,
            config,
            k,
            noise if isinstance(noise, list) else [noise],
            out / f"data_{k}.h5",
            self.progress,
        )
        model_error = evaluate_checkpoint(
            self.model_path(k - 1),
            fresh,
            EvalConfig(horizons=(8, 32), max_horizon=100, max_windows=512, device=self.device),
            all_episodes=True,
            progress=False,
        )["error"]
        merge_datasets([self.base, *fresh_files, fresh], out / "buffer.h5")
        self.retrain(out / "buffer.h5", k, self.model_path(k - 1))
        row = {
            "iteration": k,
            "imagined_steps": previous["imagined_steps"] + stats.timesteps,
            "imagined_step_reward": stats.log[-1]["mean_step_reward"] if stats.log else None,
            **_physics(evaluation),
            "model_error_fresh": model_error,
            "physics_samples": previous["physics_samples"] + int(Dataset.load(fresh).num_steps),
            "action_noise": noise,
            "learning_rate": float(policy.learning_rate),
            "wall_s": time.monotonic() - started,
        }
        report["log"].append(row)
        self.write_report(report)
        self.log_row(row)
        tqdm.write(
            f"iteration {k}: physics tracking {row['tracking']:.3f}, falls {row['falls']}, "
            f"|dv_xy| {row['lin_vel_error']:.3f}, "
            f"physics samples {share_text(row['physics_samples'], physics_env_id)}, "
            f"imagined steps {row['imagined_steps']:,}, model error on fresh data {model_error}"
        )
        tqdm.write(format_table(evaluation))

    def log_row(self, row: dict) -> None:
        """An iteration's log row as TensorBoard scalars at the step k (with --tensorboard)."""
        if self.logger is None:
            return
        for name in TENSORBOARD_FIELDS:
            if row.get(name) is not None:
                self.logger.record(f"mbpo/{name}", row[name])
        for horizon, error in (row["model_error_fresh"] or {}).items():
            self.logger.record(f"mbpo/model_error_fresh/{horizon}", error)
        self.logger.dump(step=row["iteration"])

    def write_report(self, report: dict) -> None:
        """`mbpo.json` with the best iteration so far, and `mbpo.png`."""
        from rwm_gym.atomic import write_json

        log = report["log"]
        best = max(log, key=lambda row: row["tracking"])
        report["best_iteration"], report["best_tracking"] = best["iteration"], best["tracking"]
        write_json(self.out / "mbpo.json", report)
        plot_curve(log, self.out / "mbpo.png", self.model_free)


def _starting_rows(starting, model: Path) -> int:
    """Physics rows behind iteration 0: the starting model's whole lineage united with the starting data's sources
    (a model trained on that data counts it once; a model trained on other data adds its own)."""
    from rwm_gym.data.lineage import physics_sources, total_rows, union
    from rwm_gym.model.checkpoint import read_meta
    from rwm_gym.model.lineage import checkpoint_lineage

    return total_rows(union(checkpoint_lineage(read_meta(model)), physics_sources(starting)))


def _collect(
    env_id: str, policy: Path, config: MBPOConfig, k: int, noise_levels: list[float], out: Path, progress: bool
) -> Path:
    """Iteration k's physics episodes, split evenly over the action-noise levels, in one file."""
    from rwm_gym.data.collect import collect
    from rwm_gym.data.dataset import merge_datasets

    counts = [
        config.collect_episodes // len(noise_levels) + (i < config.collect_episodes % len(noise_levels))
        for i in range(len(noise_levels))
    ]
    parts = [
        collect(
            env_id,
            str(policy),
            n,
            out.with_name(f".{out.stem}_{i}.h5"),
            seed=config.seed + 1000 * k + 100 * i,
            num_envs=min(n, 64),
            action_noise=level,
            max_steps=config.collect_steps,
            overwrite=True,
            progress=progress,
        )
        for i, (n, level) in enumerate(zip(counts, noise_levels))
        if n
    ]
    merge_datasets(parts, out)
    for part in parts:
        part.unlink()
    return out


def _check_resume(report: dict, config: MBPOConfig, path: Path) -> None:
    """Refuse to resume a folder started with other settings (only `RESUME_MAY_CHANGE` may differ); a folder from
    before a field was added (or `imagination` nested) reads as `MBPOConfig.from_dict` does."""
    saved = _flat(MBPOConfig.from_dict(report["config"]).to_dict())
    given = _flat(config.to_dict())
    differ = sorted(k for k in given if k not in RESUME_MAY_CHANGE and saved.get(k) != given[k])
    if differ:
        raise ValueError(f"{path}: this folder's run has other settings ({', '.join(differ)}); use another --out")


def _flat(config: dict) -> dict:
    """A config dict with its nested `imagination` fields beside the others, as JSON would give them back."""
    config = json.loads(json.dumps(config))
    return {**{k: v for k, v in config.items() if k != "imagination"}, **config.get("imagination", {})}


def _physics(evaluation) -> dict:
    """The log fields of a physics evaluation (`rwm_gym.rl.evaluate_policy.Evaluation`)."""
    return {
        "tracking": evaluation.tracking,
        "physics_return": evaluation.episode_return,
        "lin_vel_error": evaluation.lin_vel_error,
        "yaw_rate_error": evaluation.yaw_rate_error,
        "falls": evaluation.falls,
    }

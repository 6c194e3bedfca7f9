"""The MBPO-PPO loop (`rwm-gym mbpo`): PPO in imagination, judge in physics, collect, retrain the model, repeat.

Each iteration: (1) continue PPO on the imagined env of the current world model; (2) evaluate the policy in physics
(fixed commands and seeds) and keep the best zip; (3) collect fresh physics episodes with the policy (plus action
noise); (4) measure the current model's prediction error on that fresh data (the states the policy now visits);
(5) retrain the world model on all data so far (from scratch, same budget each time: `train` resumes only on an
unchanged dataset) or fine-tune it from its last weights (`model_finetune`, the cheap choice on a small CPU). Logged
per iteration, as JSON and a PNG curve: model error on fresh data, imagined reward, physics return and tracking error,
physics samples so far. A policy to start from (`init_policy`, e.g. the behaviour-cloned actor `rwm-gym ppo --bc-data
... --timesteps 0` writes) is evaluated first as iteration 0, and its critic is warmed up before the actor moves.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import asdict, dataclass, fields
from pathlib import Path

from tqdm import tqdm

from rwm_gym.atomic import atomic_write
from rwm_gym.model.config import add_dataclass_options


@dataclass(frozen=True)
class MBPOConfig:
    """Budget of one MBPO-PPO run (PPO's own settings are `PPOConfig`)."""

    iterations: int = 4
    """Loop iterations."""
    ppo_timesteps: int = 300_000
    """Imagined steps of PPO per iteration."""
    num_envs: int = 512
    """Imagined envs."""
    imagined_episode_steps: int = 250
    """Time limit of an imagined episode (policy steps); PPO bootstraps at the limit."""
    collect_episodes: int = 32
    """Physics episodes collected per iteration."""
    collect_steps: int = 250
    """Cap on a collected episode's length (policy steps)."""
    action_noise: float = 0.1
    """Gaussian std added to the policy's actions while collecting (exploration)."""
    model_iterations: int = 1000
    """World-model gradient steps per retraining."""
    model_finetune: bool = False
    """Fine-tune the current world model on all data so far instead of retraining it from scratch."""
    model_lr: float = 1e-3
    """Adam learning rate of the world-model (re)training (lower it for fine-tuning, e.g. 3e-4)."""
    critic_warmup_steps: int = 0
    """Imagined steps that train only the critic of `init_policy` before the first PPO iteration."""
    eval_seeds: int = 2
    """Physics evaluation episodes per command."""
    eval_steps: int = 500
    """Policy steps per physics evaluation episode."""
    seed: int = 0
    """Seeds PPO, collection and model training (each iteration offsets it)."""

    def to_dict(self) -> dict:
        return asdict(self)


def mbpo(data: str | Path, out: str | Path, config: MBPOConfig = MBPOConfig(), *, checkpoint: str | Path | None = None,
         init_policy: str | Path | None = None, model_kind: str = "rwm", device: str = "cpu",
         progress: bool = True) -> dict:
    """Run the loop from the dataset `data` into the folder `out`; returns the report (also `out/mbpo.json`).

    checkpoint: the world model to start from (default: trained on `data` first, with `model_iterations` steps).
    init_policy: an SB3 PPO zip to start from (its saved PPO settings are kept); default a fresh `PPOConfig` policy.
    """
    from rwm_gym.data.collect import collect
    from rwm_gym.data.dataset import Dataset, merge_datasets
    from rwm_gym.rl.evaluate_policy import evaluate_policy, format_table, write_json
    from stable_baselines3 import PPO

    from rwm_gym.rl.ppo import PPOConfig, learn, make_env, make_ppo, save_policy, warm_up_critic
    from rwm_gym.model.config import TrainConfig
    from rwm_gym.model.evaluate import EvalConfig, evaluate_checkpoint
    from rwm_gym.model.checkpoint import read_meta
    from rwm_gym.model.factory import model_config_for
    from rwm_gym.model.train import train

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    started = time.monotonic()
    spec = Dataset.load(data).spec()
    model_config = read_meta(checkpoint).model_config if checkpoint else model_config_for(model_kind, spec)

    def retrain(dataset: Path, k: int, previous: Path | None) -> Path:
        train_config = TrainConfig(iterations=config.model_iterations, seed=config.seed + k, device=device,
                                   lr=config.model_lr, val_every=max(1, config.model_iterations // 4),
                                   checkpoint_every=config.model_iterations)
        init = previous if config.model_finetune else None
        return train(dataset, model_config, train_config, out / f"model_{k}.safetensors", progress=progress,
                     init=init).path

    all_data = Path(data)
    physics_samples = int(Dataset.load(all_data).num_steps)
    checkpoint = Path(checkpoint) if checkpoint else retrain(all_data, 0, None)
    ppo_config = PPOConfig(num_envs=config.num_envs)
    env_kwargs = {"episode_steps": config.imagined_episode_steps}
    env = make_env("imagination", config.num_envs, checkpoint=checkpoint, device=device, seed=config.seed,
                   env_kwargs=env_kwargs)
    log: list[dict] = []
    best = None
    if init_policy is not None:
        policy = PPO.load(init_policy, env=env, device=device)
        evaluation = evaluate_policy(policy, seeds=range(config.eval_seeds), steps=config.eval_steps)
        best = (0, evaluation.tracking)
        save_policy(policy, out / "best_policy.zip")
        log.append({"iteration": 0, "imagined_step_reward": None, "imagined_steps": 0, **_physics(evaluation),
                    "model_error_fresh": None, "physics_samples": physics_samples,
                    "wall_s": time.monotonic() - started})
        tqdm.write(f"iteration 0 ({init_policy}): physics tracking {evaluation.tracking:.3f}, "
                   f"return {evaluation.episode_return:.2f}")
        if config.critic_warmup_steps:
            warm_up_critic(policy, config.critic_warmup_steps, progress=progress)
    else:
        policy = make_ppo(env, ppo_config, seed=config.seed, device=device)
    for k in tqdm(range(1, config.iterations + 1), desc="mbpo", disable=not progress):
        if k > 1:
            policy.set_env(make_env("imagination", config.num_envs, checkpoint=checkpoint, device=device,
                                    seed=config.seed + k, env_kwargs=env_kwargs))
        stats = learn(policy, timesteps=config.ppo_timesteps, target_kl=ppo_config.target_kl, progress=progress)
        zip_path = save_policy(policy, out / f"policy_{k}.zip")
        evaluation = evaluate_policy(policy, seeds=range(config.eval_seeds), steps=config.eval_steps)
        if best is None or evaluation.tracking > best[1]:
            best = (k, evaluation.tracking)
            save_policy(policy, out / "best_policy.zip")
        fresh = collect(spec.physics_env_id, str(zip_path), config.collect_episodes, out / f"data_{k}.h5",
                        seed=config.seed + 1000 * k, num_envs=config.collect_episodes,
                        action_noise=config.action_noise, max_steps=config.collect_steps, overwrite=True,
                        progress=progress)
        model_error = evaluate_checkpoint(checkpoint, fresh, EvalConfig(horizons=(8, 32), max_horizon=100,
                                                                        noise_levels=(), device=device),
                                          all_episodes=True, progress=False)["error"]
        physics_samples += int(Dataset.load(fresh).num_steps)
        merged = out / f"all_{k}.h5"
        merge_datasets([all_data, fresh], merged)
        all_data = merged
        checkpoint = retrain(all_data, k, checkpoint)
        row = {"iteration": k, "imagined_step_reward": stats.log[-1]["mean_step_reward"] if stats.log else None,
               "imagined_steps": stats.timesteps, **_physics(evaluation), "model_error_fresh": model_error,
               "physics_samples": physics_samples,
               "wall_s": time.monotonic() - started}
        log.append(row)
        tqdm.write(f"iteration {k}: physics tracking {row['tracking']:.3f}, return {row['physics_return']:.2f}, "
                   f"|dv_xy| {row['lin_vel_error']:.3f}, "
                   f"model error on fresh data {model_error}, imagined step reward {row['imagined_step_reward']:.4f}")
        tqdm.write(format_table(evaluation))
        ppo = ppo_config.to_dict() if init_policy is None else {"init_policy": str(init_policy)}  # its zip's settings
        report = {"config": config.to_dict(), "ppo": ppo, "data": str(data), "log": log,
                  "best_iteration": best[0], "best_tracking": best[1]}
        write_json(report, out / "mbpo.json")
        plot_curve(log, out / "mbpo.png")
    return report


def _physics(evaluation) -> dict:
    """The log fields of a physics evaluation (`rwm_gym.rl.evaluate_policy.Evaluation`)."""
    return {"tracking": evaluation.tracking, "physics_return": evaluation.episode_return,
            "lin_vel_error": evaluation.lin_vel_error,
            "yaw_rate_error": evaluation.yaw_rate_error, "falls": evaluation.falls}


def plot_curve(log: list[dict], path: Path) -> None:
    """Physics return, tracking error and fresh-data model error per iteration, written atomically."""

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    it = [r["iteration"] for r in log]
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.5))
    axes[0].plot(it, [r["tracking"] for r in log], "o-")
    axes[0].set_title("physics tracking score")
    axes[1].plot(it, [r["lin_vel_error"] for r in log], "o-", label="|dv_xy| m/s")
    axes[1].plot(it, [r["yaw_rate_error"] for r in log], "o-", label="|dwz| rad/s")
    axes[1].set_title("tracking error")
    axes[1].legend()
    measured = [r for r in log if r["model_error_fresh"]]
    for horizon in (measured[0]["model_error_fresh"] if measured else []):
        axes[2].plot([r["iteration"] for r in measured], [r["model_error_fresh"][horizon] for r in measured], "o-",
                     label=f"{horizon} steps")
    axes[2].set_title("model error on fresh physics data")
    axes[2].legend()
    for ax in axes:
        ax.set_xlabel("iteration")
    fig.tight_layout()
    atomic_write(path, lambda tmp: fig.savefig(tmp, format="png", dpi=100))
    plt.close(fig)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", required=True, type=Path, help="initial physics dataset (HDF5)")
    parser.add_argument("--out", required=True, type=Path, help="folder for models, data, policies and the report")
    parser.add_argument("--checkpoint", default=None, help="world model to start from (default: train one on --data)")
    parser.add_argument("--model", default="rwm", help="world-model kind to (re)train")
    parser.add_argument("--init-policy", default=None, type=Path,
                        help="SB3 PPO zip to start from, e.g. a behaviour-cloned actor (default: a fresh policy)")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    add_dataclass_options(parser, MBPOConfig)


def run(args: argparse.Namespace) -> int:
    if args.threads:
        import torch

        torch.set_num_threads(args.threads)
    config = MBPOConfig(**{f.name: getattr(args, f.name) for f in fields(MBPOConfig)})
    report = mbpo(args.data, args.out, config, checkpoint=args.checkpoint, init_policy=args.init_policy,
                  model_kind=args.model, device=args.device)
    print(f"best physics tracking {report['best_tracking']:.3f} at iteration {report['best_iteration']}; "
          f"report {args.out / 'mbpo.json'}, curve {args.out / 'mbpo.png'}")
    return 0

"""PPO in imagination against PPO in physics on a dm_control task, both scored in dm_control physics.

Imagination: collect random + noisy episodes in physics (the cross-robot benchmark's mix), train RWM with the
cross-robot recipe (`model_config_for("rwm", spec)`, `TrainConfig` defaults), then train SB3 PPO on
`RWM-<Domain>-v0`. Physics: the same PPO (`rwm_gym.rl.ppo.make_ppo`, same config and
seed) on `DMC-<Domain>-<Task>-v0` for the same PPO wall time. Both policies then act deterministically for a full
episode (the suite's 1000 steps, the Jaco tasks' 250) from fixed seeds in physics; the score is the task's return,
and for a manipulation task (`DMC-Jaco-ReachSite-v0`, `DMC-Jaco-LiftBrick-v0`) its success rate.

Writes `results.json`, `results.md` and `training.png` (PPO's mean step reward per rollout) to `--out`.

    python benchmarks/dmc_imagination.py --env DMC-Cheetah-Run-v0
    python benchmarks/dmc_imagination.py --env DMC-Walker-Walk-v0 --ppo-minutes 5
    python benchmarks/dmc_imagination.py --wm-iterations 5 --ppo-minutes 0.1 --episodes 2 --eval-seeds 1  # smoke
"""

from __future__ import annotations

import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import torch

from rwm_gym.atomic import save_png, write_json, write_text
from rwm_gym.data.dataset import Dataset
from rwm_gym.model import TrainConfig, model_config_for
from rwm_gym.model.train import train
from rwm_gym.options import parse_dataclass_args
from rwm_gym.registration import DMC_SPECS
from rwm_gym.rl.evaluate_dmc import evaluate_episodes
from rwm_gym.rl.ppo import PPOConfig, learn, make_ppo, save_policy
from rwm_gym.vector.sb3_vec_env import DMCSB3VecEnv, ImaginedSB3VecEnv

sys.path.insert(0, str(Path(__file__).parent))
from cross_robot import collect_mix


@dataclass(frozen=True)
class Options:
    """PPO in imagination (RWM-<Domain>-v0) vs PPO in physics (DMC-<Domain>-<Task>-v0), scored in physics."""

    env: str = "DMC-Cheetah-Run-v0"
    """Physics env id (its spec names the imagined id)."""
    out: Path = Path("benchmarks/results/dmc_imagination")
    """Parent folder; results go to <out>/<env>/."""
    episodes: int = 16
    """Episodes per policy (random and noisy) collected for the world model."""
    episode_steps: int = 400
    """Length of each collected episode."""
    wm_iterations: int = 400
    """World-model gradient steps (the cross-robot recipe otherwise)."""
    ppo_minutes: float = 5.0
    """PPO wall-clock budget, the same in imagination and in physics."""
    num_envs: int = 64
    """Envs stepped together, in both arms."""
    n_steps: int = 64
    """Steps per env per PPO update, in both arms."""
    imagined_episode_steps: int = 200
    """Time limit of an imagined episode (PPO bootstraps at it); physics episodes run the task's full episode."""
    eval_seeds: int = 5
    """Physics episodes (seeds 0..n-1) per policy."""
    seed: int = 0
    device: str = "cpu"
    """torch device of the world model and the policies."""
    threads: int = 1
    """torch CPU threads."""


def evaluate(model, env_id: str, seeds: int) -> dict:
    """Deterministic policy for one full episode per seed in physics: the task's returns (and a manipulation task's
    success rate: the share of episodes ending with the goal met, `rwm_gym.rl.evaluate_dmc`)."""
    e = evaluate_episodes(model, env_id, seeds=seeds)
    return {"returns": e.returns, "mean": e.episode_return, "std": e.return_std, "success_rate": e.success_rate}


def ppo_config(options: Options) -> PPOConfig:
    """RWM's PPO settings (`PPOConfig` defaults) sized by `num_envs` and `n_steps`; the same in both arms."""
    return PPOConfig(num_envs=options.num_envs, n_steps=options.n_steps)


def untrained(env, options: Options) -> dict:
    """The physics return of the policy both arms start from (same seed, same initial weights)."""
    model = make_ppo(env, ppo_config(options), seed=options.seed, device=options.device)
    return {"evaluation": evaluate(model, options.env, options.eval_seeds)}


def run_arm(where: str, env, options: Options, out: Path) -> dict:
    config = ppo_config(options)
    model = make_ppo(env, config, seed=options.seed, device=options.device)
    stats = learn(model, minutes=options.ppo_minutes, target_kl=config.target_kl)
    save_policy(model, out / f"ppo_{where}.zip")
    tic = time.perf_counter()
    scores = evaluate(model, options.env, options.eval_seeds)
    print(
        f"{where}: {stats.timesteps} PPO steps in {stats.wall_s:.0f} s; physics return "
        f"{scores['mean']:.1f} +- {scores['std']:.1f}",
        flush=True,
    )
    return {
        "ppo": config.to_dict(),
        "ppo_steps": stats.timesteps,
        "ppo_wall_s": stats.wall_s,
        "log": stats.log,
        "evaluation": scores,
        "eval_wall_s": time.perf_counter() - tic,
    }


def _score(e: dict) -> str:
    """Return (mean +- std), and the success rate where the task has one."""
    success = e.get("success_rate")
    return f"{e['mean']:.1f} +- {e['std']:.1f}" + ("" if success is None else f", success {success:.2f}")


def markdown(r: dict, options: Options) -> str:
    imagination, physics = r["imagination"], r["physics"]
    rows = [
        (
            "imagination",
            imagination,
            r["data_rows"],
            r["collect_wall_s"] + r["wm_wall_s"] + imagination["ppo_wall_s"],
            (
                f"collect {r['collect_wall_s']:.0f} s + world model {r['wm_wall_s']:.0f} s + PPO "
                f"{imagination['ppo_wall_s']:.0f} s ({imagination['ppo_steps']} imagined steps)"
            ),
        ),
        (
            "physics",
            physics,
            physics["ppo_steps"],
            physics["ppo_wall_s"],
            f"PPO {physics['ppo_wall_s']:.0f} s ({physics['ppo_steps']} physics steps)",
        ),
    ]
    lines = [
        (
            f"{options.env}: PPO ({options.num_envs} envs x {options.n_steps} steps per update, seed "
            f"{options.seed}) trained {options.ppo_minutes:g} min in imagination ({r['imagined_env']}, world model "
            f"{options.wm_iterations} iterations, imagined episodes {options.imagined_episode_steps} steps) or in "
            f"physics; return of the deterministic policy over {options.eval_seeds} full physics episodes "
            f"(seeds 0..{options.eval_seeds - 1}, the task's reward: a suite task's at most 1000, a Jaco task's at "
            "most 250; success: the share of episodes ending with the goal met)."
        ),
        "",
        "| trained in | physics return (mean +- std) | physics samples | wall time | of which |",
        "|---|---|---|---|---|",
    ]
    e = r["untrained"]["evaluation"]
    lines.append(f"| (untrained: the initial policy of both) | {_score(e)} | 0 | - | - |")
    for name, arm, samples, wall, detail in rows:
        lines.append(f"| {name} | {_score(arm['evaluation'])} | {samples} | {wall / 60:.1f} min | {detail} |")
    error = r["wm_val_error"]
    lines.append(
        f"\nWorld model: relative L1 validation error of 8-step forecasts {'-' if error is None else f'{error:.3f}'}."
    )
    return "\n".join(lines) + "\n"


def plot(r: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5))
    for where in ("imagination", "physics"):
        log = r[where]["log"]
        ax.plot(
            [row["wall_s"] / 60 for row in log],
            [row["mean_step_reward"] for row in log],
            label=f"in {where} (physics return {r[where]['evaluation']['mean']:.0f})",
        )
    ax.set(xlabel="PPO wall time (min)", ylabel="mean step reward in its own env", title=r["env"])
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_png(fig, path)


def main(argv: list[str] | None = None) -> int:
    options = parse_dataclass_args(Options, argv, choices={"env": list(DMC_SPECS)})
    torch.set_num_threads(options.threads)
    out = options.out / options.env
    out.mkdir(parents=True, exist_ok=True)

    tic = time.perf_counter()
    data = Dataset.load(collect_mix(options.env, out, options.episodes, options.episode_steps, options.seed))
    collect_s = time.perf_counter() - tic
    print(f"data: {data.path} ({data.num_episodes} episodes, {data.num_steps} rows; {collect_s:.0f} s)", flush=True)
    spec = data.spec()

    tic = time.perf_counter()
    trained = train(
        data,
        model_config_for("rwm", spec),
        TrainConfig(
            iterations=options.wm_iterations,
            seed=options.seed,
            device=options.device,
            checkpoint_every=options.wm_iterations,
        ),
        out / "world_model.safetensors",
    )
    wm_s = time.perf_counter() - tic
    print(
        f"world model: {options.wm_iterations} iterations in {wm_s:.0f} s, validation error "
        f"{trained.stats['val_error']}",
        flush=True,
    )

    result = {
        "env": options.env,
        "imagined_env": spec.imagined_env_id,
        "options": {k: str(v) for k, v in asdict(options).items()},
        "data": str(data.path),
        "data_rows": int(data.num_steps),
        "collect_wall_s": collect_s,
        "wm_wall_s": wm_s,
        "wm_val_error": trained.stats["val_error"],
    }
    imagined = ImaginedSB3VecEnv(
        trained.path,
        num_envs=options.num_envs,
        env_id=spec.imagined_env_id,
        device=options.device,
        episode_steps=options.imagined_episode_steps,
    )
    imagined.seed(options.seed)
    result["imagination"] = run_arm("imagination", imagined, options, out)
    physics = DMCSB3VecEnv(num_envs=options.num_envs, spec=DMC_SPECS[options.env])
    physics.seed(options.seed)
    result["untrained"] = untrained(physics, options)
    result["physics"] = run_arm("physics", physics, options, out)

    write_json(out / "results.json", result)
    table = markdown(result, options)
    write_text(out / "results.md", table)
    plot(result, out / "training.png")
    print(table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""rsl_rl's own PPO (`OnPolicyRunner`, the trainer of Isaac Lab and of RWM) in imagination, then scored in physics.

    pip install ".[rsl-rl]"
    python examples/rsl_rl_imagination.py --num-envs 512 --iterations 50
    torchrun --nproc_per_node=2 examples/rsl_rl_imagination.py --num-envs 256      # 2 CPU processes (gloo)
    torchrun --nproc_per_node=8 examples/rsl_rl_imagination.py --device cuda --num-envs 4096   # 8 GPUs (nccl)

The imagined env `RWM-AnymalD-v0` on the shipped world model, presented as rsl_rl's `VecEnv`
(`rwm_gym.vector.rsl_rl_vec_env.ImaginedRslRlVecEnv`); the runner gets RWM's PPO settings (`PPOConfig`, turned into
rsl_rl's `train_cfg` by `rsl_rl_train_cfg`) and is used as it comes: its TensorBoard log, checkpoints
(`model_<it>.pt`) and console report land in `--log-dir`. The trained policy is then run in MuJoCo physics on the
scoring command set (`rwm-gym score`'s), beside the zero-action floor. Options are the fields of `Args`.

Under torchrun every rank trains on its own batch of `--num-envs` imagined robots (rank r's env i seeded
seed + r x num-envs + i, its action noise seeded seed + r) with rsl_rl's own multi-GPU mode
(`rwm_gym.rl.rsl_rl_runner`: gloo on the CPU, nccl and one GPU per rank on cuda); rank 0 logs, saves and scores.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass

import numpy as np
import torch

from rwm_gym.options import add_dataclass_options
from rwm_gym.rl.ppo import PPOConfig


@dataclass(frozen=True)
class Args:
    """Imagined PPO with rsl_rl (RWM's PPO settings; the number of envs sized for a small CPU)."""

    checkpoint: str | None = None
    """World-model checkpoint (None: the shipped ANYmal D one)."""
    num_envs: int = 512
    """Imagined envs stepped together (RWM: 4096)."""
    iterations: int = 50
    """PPO iterations; each collects num_envs x 24 imagined steps."""
    reset_data: str | None = None
    """Dataset of real histories imagined episodes restart from (None: the checkpoint's)."""
    episode_steps: int | None = None
    """Time limit of an imagined episode in policy steps (None: the task's 20 s)."""
    uncertainty_penalty: float = 0.0
    """RWM-U's lambda: reward -lambda * ensemble disagreement * dt."""
    seed: int = 0
    """Seeds the envs (env i: seed + i; under torchrun, rank r's: seed + r x num_envs + i) and torch (seed + r)."""
    log_dir: str = "runs/rsl_rl_imagination"
    """The runner's log folder (TensorBoard, checkpoints)."""
    device: str = "cpu"
    """Where the world model, the policy and the tensors live (cpu or cuda; under torchrun, cuda is cuda:LOCAL_RANK)."""
    threads: int = 1
    """torch CPU threads."""
    score_seeds: int = 1
    """Physics episodes per scoring command (0: no physics score)."""
    score_steps: int | None = None
    """Policy steps per scoring episode (None: a full episode)."""


def policy_function(policy, device: str):
    """numpy (N, 48) -> numpy (N, 12) actions from rsl_rl's inference policy (its TensorDict input)."""
    from tensordict import TensorDict

    def act(obs: np.ndarray) -> np.ndarray:
        with torch.inference_mode():
            x = torch.as_tensor(np.asarray(obs, dtype=np.float32), device=device)
            return policy(TensorDict({"policy": x}, batch_size=[len(x)])).cpu().numpy()

    return act


def main(args: Args) -> dict:
    from rwm_gym.model.distributed import close_world, init_world, rank_device
    from rwm_gym.rl.rsl_rl_runner import DistributedOnPolicyRunner
    from rwm_gym.rl.rsl_rl_train_cfg import rsl_rl_train_cfg
    from rwm_gym.vector.rsl_rl_vec_env import ImaginedRslRlVecEnv

    world = init_world(args.device)  # torchrun's ranks join the process group here; a plain run is a world of one
    device = str(rank_device(args.device, world))
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed + world.rank)
    env = ImaginedRslRlVecEnv(
        args.checkpoint,
        args.num_envs,
        seed=args.seed + world.rank * args.num_envs,
        device=device,
        reset_data=args.reset_data,
        episode_steps=args.episode_steps,
        uncertainty_penalty=args.uncertainty_penalty,
    )
    train_cfg = rsl_rl_train_cfg(PPOConfig(num_envs=args.num_envs), run_name="rwm_imagination")
    log_dir = args.log_dir if world.is_main else None
    runner = DistributedOnPolicyRunner(env, train_cfg, log_dir=log_dir, device=device)
    runner.learn(num_learning_iterations=args.iterations)
    close_world()
    result = {"imagined_steps": args.iterations * train_cfg["num_steps_per_env"] * args.num_envs * world.size}
    if not world.is_main:
        return result
    print(
        f"trained {result['imagined_steps']} imagined steps on {world.size} process(es); the runner's log and "
        f"checkpoints are in {args.log_dir}"
    )

    if args.score_seeds > 0:
        from rwm_gym.rl.score import score, summary_line

        policy = policy_function(runner.get_inference_policy(device=device), device)
        trained = score(policy, seeds=args.score_seeds, steps=args.score_steps)
        floor = score("zero", seeds=args.score_seeds, steps=args.score_steps)
        print(summary_line("rsl_rl PPO in imagination", trained))
        print(summary_line("zero actions (the floor)", floor))
        result.update(tracking=trained.tracking, floor=floor.tracking, falls=trained.falls)
    return result


def parse_args(argv: list[str] | None = None) -> Args:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_dataclass_options(
        parser, Args, types={"checkpoint": str, "reset_data": str, "episode_steps": int, "score_steps": int}
    )
    return Args(**vars(parser.parse_args(argv)))


if __name__ == "__main__":
    main(parse_args())

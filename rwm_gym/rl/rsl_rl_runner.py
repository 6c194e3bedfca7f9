"""rsl_rl's `OnPolicyRunner` in its multi-GPU mode on GPUs or on CPUs: one process per rank under torchrun.

    torchrun --nproc_per_node=2 examples/rsl_rl_imagination.py --device cpu     # 2 CPU processes (gloo)
    torchrun --nproc_per_node=8 examples/rsl_rl_imagination.py --device cuda    # 8 GPUs (nccl), rank r on cuda:r

rsl_rl 5.x trains on several GPUs itself: it reads WORLD_SIZE, RANK and LOCAL_RANK from torchrun's environment,
broadcasts rank 0's parameters when `learn` starts, averages the gradients of every mini-batch over the ranks
(all-reduce), averages the KL divergence that adapts the learning rate, shares the observation normaliser's
statistics, and logs and saves checkpoints on rank 0 only. Each rank steps its own env batch, so one iteration
collects `num_steps_per_env x num_envs x world size` steps. It joins the process group with nccl only, and requires
the device `cuda:LOCAL_RANK`.

`DistributedOnPolicyRunner` changes that join and nothing else: it joins through `rwm_gym.model.distributed.init_world`
(gloo on the CPU, nccl and `cuda:LOCAL_RANK` on cuda, the same as `rwm-gym train` under torchrun), so rsl_rl's own
multi-GPU code runs unchanged on CPU processes too. It overrides rsl_rl's private `_configure_multi_gpu`, which the
`rsl-rl` extra's pin (5.x) keeps stable. Started without torchrun it is rsl_rl's runner as it is.
"""

from __future__ import annotations

import torch
from rsl_rl.runners import OnPolicyRunner

from rwm_gym.model.distributed import init_world, rank_device


class DistributedOnPolicyRunner(OnPolicyRunner):
    """rsl_rl's `OnPolicyRunner` whose multi-GPU mode also runs on CPUs (gloo); see the module docstring."""

    def _configure_multi_gpu(self) -> None:
        world = init_world(self.device)
        self.gpu_world_size, self.gpu_global_rank, self.gpu_local_rank = world.size, world.rank, world.local_rank
        self.is_distributed = world.distributed
        if not world.distributed:
            self.cfg["multi_gpu"] = None
            return
        expected = rank_device(torch.device(self.device).type, world)
        if torch.device(self.device) != expected:
            raise ValueError(f"device {self.device} does not match rank {world.rank}'s device {expected}")
        self.cfg["multi_gpu"] = {"global_rank": world.rank, "local_rank": world.local_rank, "world_size": world.size}

"""Data-parallel training over processes (torch.distributed): the world a process lives in, and what each rank does.

Launch any training command with `torchrun --nproc_per_node=N [--nnodes=M ...]`; torchrun sets RANK, WORLD_SIZE,
LOCAL_RANK, MASTER_ADDR and MASTER_PORT, and `init_world` joins the process group from them: gloo on CPU, nccl on
cuda (rank r then trains on cuda:LOCAL_RANK). Without those variables the world is one process and nothing changes.

What each rank does (see `rwm_gym.model.train`):
- The global batch (`--batch-size`, i.e. batch size / branches segments) is split over the ranks: every rank draws
  the same segment starts (and ensemble heads) of the whole batch from a shared sampler generator seeded by the run's
  seed, and keeps its own slice, so the windows of an iteration do not depend on the world size.
- Gradients are averaged by DistributedDataParallel, so one iteration is one optimizer step on the global batch. The
  average is of the ranks' mean losses: the single-process gradient exactly when every rank counts as many forecast
  branches (branches reaching past an episode's end are not counted, so a rank with more of them weighs more).
- Seeds per rank: all ranks build the model with `torch.manual_seed(seed)` (identical weights; DDP also broadcasts
  rank 0's). Afterwards rank 0 keeps that stream for its forecast noise (the single-process run is rank 0 of a world
  of one); rank r > 0 reseeds with `rank_seed(seed, r, iteration)` at the start and after every checkpoint, so a
  resume from a checkpoint reproduces the uninterrupted run at the same world size.
- Only rank 0 validates, writes checkpoints (atomically), logs and shows a progress bar.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
import torch
import torch.distributed as dist


@dataclass(frozen=True)
class World:
    """This process's place among the training processes."""

    rank: int = 0
    """Global rank, 0..size-1."""
    size: int = 1
    """Number of processes (world size)."""
    local_rank: int = 0
    """Rank on this machine (picks the GPU)."""

    @property
    def is_main(self) -> bool:
        """Rank 0: the one process that writes files, logs and progress bars."""
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.size > 1


SINGLE = World()
"""The world of a process started without torchrun."""


def launched_by_torchrun() -> bool:
    """Whether this process is one of several started by torchrun (WORLD_SIZE > 1)."""
    return int(os.environ.get("WORLD_SIZE", "1")) > 1


def init_world(device: str = "cpu") -> World:
    """Join the process group that torchrun's environment describes (once); the single-process world otherwise.

    device: the training device asked for; "cuda" selects nccl and cuda:LOCAL_RANK, anything else gloo.
    """
    if not launched_by_torchrun():
        return SINGLE
    world = World(int(os.environ["RANK"]), int(os.environ["WORLD_SIZE"]), int(os.environ.get("LOCAL_RANK", "0")))
    if not dist.is_initialized():
        cuda = torch.device(device).type == "cuda"
        if cuda:
            torch.cuda.set_device(world.local_rank)
        dist.init_process_group("nccl" if cuda else "gloo")
    return world


def current_world() -> World:
    """The world of an initialised process group, else the single-process world."""
    if dist.is_available() and dist.is_initialized():
        return World(dist.get_rank(), dist.get_world_size(), int(os.environ.get("LOCAL_RANK", "0")))
    return SINGLE


def barrier(world: World) -> None:
    """Wait until every rank gets here (e.g. until rank 0 has written a file the others read)."""
    if world.distributed:
        dist.barrier()


def close_world() -> None:
    """Leave the process group (after the last collective)."""
    if dist.is_available() and dist.is_initialized():
        dist.destroy_process_group()


def rank_device(device: str, world: World) -> torch.device:
    """The device of this rank: cuda:LOCAL_RANK for "cuda" in a distributed world, else `device` as given."""
    parsed = torch.device(device)
    if parsed.type == "cuda" and parsed.index is None and world.distributed:
        return torch.device("cuda", world.local_rank)
    return parsed


def rank_seed(seed: int, rank: int, iteration: int) -> int:
    """Seed of rank r's noise stream from an iteration on (rank > 0; rank 0 continues the run's own stream)."""
    return int(np.random.SeedSequence([seed, rank, iteration]).generate_state(1, dtype=np.uint64)[0] >> 1)


def reseed_rank(seed: int, world: World, iteration: int) -> None:
    """Give rank r > 0 its own forecast-noise stream (rank 0 keeps the saved one); see the module docstring."""
    if world.rank > 0:
        torch.manual_seed(rank_seed(seed, world.rank, iteration))


def shard(batch: torch.Tensor, world: World) -> torch.Tensor:
    """This rank's rows of a global batch (B, ...) drawn identically on every rank; B must divide by the world size."""
    if not world.distributed:
        return batch
    per_rank = batch.shape[0] // world.size
    return batch[world.rank * per_rank : (world.rank + 1) * per_rank]


def check_batch(batch_size: int, world: World) -> None:
    """Refuse a global batch (in segments: batch size / branches) that does not split evenly over the ranks."""
    if batch_size % world.size:
        raise ValueError(
            f"a batch of {batch_size} segments (batch size / branches) does not split over "
            f"{world.size} processes; choose a multiple of {world.size}"
        )


def data_parallel(loss: torch.nn.Module, world: World) -> torch.nn.Module:
    """A loss module (its model a submodule; forward -> (loss, parts)) whose backward averages gradients over the
    ranks (DistributedDataParallel); the module itself in a world of one, so the single-process path is unchanged."""
    if not world.distributed or not any(p.requires_grad for p in loss.parameters()):
        return loss
    device = next(loss.parameters()).device
    # Every model kind uses all its parameters in every loss (ensemble heads run batched), checked per kind in
    # tests/test_distributed.py, so DDP need not search the graph for unused ones.
    return torch.nn.parallel.DistributedDataParallel(loss, device_ids=[device.index] if device.type == "cuda" else None)


def mean_over_ranks(value: torch.Tensor, world: World) -> torch.Tensor:
    """The mean of a tensor over the ranks (every rank gets it); `value` itself in a world of one."""
    if not world.distributed:
        return value
    value = value.detach().clone()
    dist.all_reduce(value, op=dist.ReduceOp.SUM)
    return value / world.size


def max_over_ranks(value: float, device: torch.device, world: World) -> float:
    """The largest of the ranks' values, on every rank (e.g. the elapsed time, so all ranks stop together)."""
    if not world.distributed:
        return value
    tensor = torch.tensor([value], dtype=torch.float64, device=device)
    dist.all_reduce(tensor, op=dist.ReduceOp.MAX)
    return float(tensor.item())

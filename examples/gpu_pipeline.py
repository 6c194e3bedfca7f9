"""The whole pipeline on a GPU machine, each stage timed: collect -> train -> evaluate -> PPO in imagination (scored in
physics). Written for a machine with NVIDIA GPUs; this version of it has not been run on one (the docs' Results,
"Scaling", keep an earlier version's H100 figures). Run it and send `timings.json`.

    python examples/gpu_pipeline.py                            # all GPUs torch sees, all CPU cores for physics
    python examples/gpu_pipeline.py --device cpu --episodes 2 --episode-steps 40 --iterations 4 \\
        --ppo-timesteps 256 --ppo-envs 8 --no-ppo-eval       # the smoke run of the tests

Stages, as the commands a user would type (printed as they run):
1. `rwm-gym collect --workers <CPU cores> --backend <backend>`: scripted trot with action noise, then random actions;
   merged.
2. `torchrun --nproc_per_node=<GPUs> rwm-gym train --device cuda`: data-parallel (DDP, nccl) with one GPU per rank;
   `--batch-size` is the global batch, split over the GPUs. One GPU: plain `rwm-gym train`.
3. `rwm-gym evaluate --device cuda` on the held-out episodes.
4. `rwm-gym ppo --in imagination --device cuda`: PPO on many imagined robots, evaluated in physics (MuJoCo, CPU).

Writes `timings.json` to --out, atomically after every stage (an interrupted run keeps the stages it finished): per
stage the command, its wall seconds and the load average after it; the machine (torch and CUDA versions, the device
and GPU names, the CPU model, its core count and torch's thread count, the load average before) and the commit.
"""

from __future__ import annotations

import os
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).parent))  # the record of timed stages, a sibling script
from timed_stages import CLI, machine, stage

from rwm_gym.atomic import write_json
from rwm_gym.data.dataset import merge_datasets
from rwm_gym.options import parse_dataclass_args


@dataclass(frozen=True)
class Options:
    """Collect, train, evaluate and run PPO on a GPU machine, timing every stage."""

    out: str = "gpu_pipeline"
    """Folder for data, checkpoint, policy and timings.json."""
    device: str = "cuda"
    """torch device of training, evaluation and PPO."""
    episodes: int = 512
    """Episodes of the noisy scripted trot (plus a quarter as many of random actions)."""
    episode_steps: int = 1000
    """Cap on the length of collected episodes (policy steps)."""
    num_envs: int = 32
    """Simulations per collection worker (mujoco.batch)."""
    workers: int = 0
    """Collection workers (0: one per CPU core)."""
    backend: str = "processes"
    """Where the collection workers run: "processes" on this machine, or "ray" tasks on the Ray cluster."""
    gpus: int = 0
    """Training processes, one GPU each (0: every GPU torch sees; 1 with --device cpu)."""
    iterations: int = 20000
    """Gradient steps of the world model."""
    batch_size: int = 1024
    """Global batch of training windows (split over the GPUs)."""
    ppo_timesteps: int = 20_000_000
    """Imagined steps of PPO."""
    ppo_envs: int = 4096
    """Imagined robots stepped together."""
    ppo_eval: bool = True
    """Score the PPO policy in physics."""
    seed: int = 0


def main(argv: list[str] | None = None) -> dict:
    options = parse_dataclass_args(Options, argv)
    out = Path(options.out)
    (out / "data").mkdir(parents=True, exist_ok=True)
    cuda = torch.device(options.device).type == "cuda"
    gpus = options.gpus or (torch.cuda.device_count() if cuda else 1)
    workers = options.workers or os.cpu_count() or 1
    record = out / "timings.json"
    timings = {"options": asdict(options), "machine": machine(options.device), "stages": {}}

    parts = []
    for policy, episodes, noise, seed in (
        ("gait", options.episodes, 0.3, options.seed),
        ("random", max(1, options.episodes // 4), 0.0, options.seed + 1),
    ):
        path = out / "data" / f"{policy}.h5"
        stage(
            f"collect_{policy}",
            [
                *CLI,
                "collect",
                "--policy",
                policy,
                "--episodes",
                str(episodes),
                "--num-envs",
                str(options.num_envs),
                "--workers",
                str(workers),
                "--backend",
                options.backend,
                "--action-noise",
                str(noise),
                "--max-steps",
                str(options.episode_steps),
                "--seed",
                str(seed),
                "--out",
                str(path),
                "--overwrite",
            ],
            timings,
            record,
        )
        parts.append(path)
    data = out / "data" / "mix.h5"
    merge_datasets(parts, data)

    checkpoint = out / "rwm.safetensors"
    launcher = (
        [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc_per_node={gpus}", "-m", "rwm_gym.cli"]
        if gpus > 1
        else CLI
    )
    checkpoint.unlink(missing_ok=True)
    stage(
        "train",
        [
            *launcher,
            "train",
            "--data",
            str(data),
            "--out",
            str(checkpoint),
            "--device",
            options.device,
            "--iterations",
            str(options.iterations),
            "--batch-size",
            str(options.batch_size),
            "--seed",
            str(options.seed),
            "--quiet",
        ],
        timings,
        record,
    )
    stage(
        "evaluate",
        [
            *CLI,
            "evaluate",
            "--checkpoint",
            str(checkpoint),
            "--data",
            str(data),
            "--device",
            options.device,
            "--out",
            str(out / "evaluation"),
            "--quiet",
        ],
        timings,
        record,
    )
    ppo = [
        *CLI,
        "ppo",
        "--in",
        "imagination",
        "--checkpoint",
        str(checkpoint),
        "--device",
        options.device,
        "--num-envs",
        str(options.ppo_envs),
        "--timesteps",
        str(options.ppo_timesteps),
        "--seed",
        str(options.seed),
        "--out",
        str(out / "policy.zip"),
    ]
    stage("ppo", ppo + ([] if options.ppo_eval else ["--no-eval"]), timings, record)

    timings["total_s"] = sum(s["wall_s"] for s in timings["stages"].values())
    write_json(record, timings)
    for name, entry in timings["stages"].items():
        print(f"{name:16s} {entry['wall_s']:8.1f} s")
    return timings


if __name__ == "__main__":
    main()

"""Does a world model let a standing robot stand? Zero actions in imagination, from physics episodes of standing.

In physics the zero-action policy never falls (the tracking score's floor: 0 falls in 54 episodes of 20 s). This
collects `--episodes` physics episodes of the robot standing (`rwm-gym collect --policy zero`, small action noise),
restarts imagined episodes from their windows, sends zero actions for `--steps` steps and prints, every few steps,
the share of imagined episodes still running, the mean |joint offset| and the base tilt. A model that drifts on the
simplest behaviour there is ends episodes a policy could have stood through, so PPO learns that standing is fatal.

    python benchmarks/imagined_standing.py [--checkpoint CKPT] [--envs 256] [--steps 100] [--out DIR]
"""

from __future__ import annotations

import argparse
import os
import tempfile
from pathlib import Path

import numpy as np


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", default=None, help="world model (default: the shipped ANYmal D model)")
    parser.add_argument("--episodes", type=int, default=64, help="physics episodes of standing to start from")
    parser.add_argument("--envs", type=int, default=256)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=None, help="folder for standing.json (default: print only)")
    args = parser.parse_args(argv)
    import torch

    torch.set_num_threads(1)
    from rwm_gym.atomic import write_json
    from rwm_gym.data.collect import collect
    from rwm_gym.imagination.core import ImaginationOptions, ImaginedCore

    with tempfile.TemporaryDirectory() as folder:
        standing = collect(
            "AnymalD-MuJoCo-v0",
            "zero",
            args.episodes,
            Path(folder) / "standing.h5",
            seed=args.seed,
            num_envs=min(64, args.episodes),
            max_steps=160,
            action_noise=0.1,
            progress=False,
        )
        core = ImaginedCore(
            args.checkpoint,
            args.envs,
            reset_data=standing,
            options=ImaginationOptions(episode_steps=args.steps + 1, resample_commands=False),
        )
        core.reset(np.arange(args.envs), [args.seed + i for i in range(args.envs)])
    joints, gravity = core.spec.state_slices["joint_pos"], core.spec.state_slices["projected_gravity"]
    running = np.ones(args.envs, dtype=bool)
    rows = []
    print(f"{'step':>5} {'running':>8} {'|joint offset| rad':>19} {'tilt deg':>9}")
    for step in range(1, args.steps + 1):
        _, _, terminated, _, _ = core.step(np.zeros((args.envs, core.spec.action_dim), dtype=np.float32))
        running &= ~terminated
        if step % 10 == 0 or step == 1:
            alive = core.state[running]
            tilt = np.degrees(np.arccos(np.clip(-alive[:, gravity][:, 2], -1, 1))).mean() if running.any() else np.nan
            row = {
                "step": step,
                "running": float(running.mean()),
                "joint_offset_rad": float(np.abs(alive[:, joints]).mean()) if running.any() else None,
                "tilt_deg": float(tilt),
            }
            rows.append(row)
            print(f"{step:>5} {row['running']:>8.2f} {row['joint_offset_rad'] or float('nan'):>19.3f} {tilt:>9.1f}")
    print(f"load average {os.getloadavg()[0]:.2f}; in physics the standing robot never falls")
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        print(
            write_json(
                args.out / "standing.json",
                {"checkpoint": str(core.checkpoint), "envs": args.envs, "episodes": args.episodes, "rows": rows},
            )
        )


if __name__ == "__main__":
    main()

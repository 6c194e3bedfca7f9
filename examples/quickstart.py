"""Quick start: train a walking policy inside the learned simulator, then test it in physics.

    pip install . && python examples/quickstart.py

PPO (Stable-Baselines3) runs for a few minutes on `RWM-AnymalD-v0`, the shipped ANYmal D world model, with 512
imagined robots stepped in one forward pass; the policy then walks in MuJoCo (`AnymalD-MuJoCo-v0`) on fixed commands.
Printed: the tracking-error table. Written to `quickstart/`: policy.zip (load with `PPO.load`), policy.json (config,
training log, evaluation) and policy.png (commanded vs achieved velocity per command). The same as

    rwm-gym ppo --in imagination --minutes 7 --num-envs 512 --out quickstart/policy.zip
"""

from __future__ import annotations

import argparse
import sys

from rwm_gym.cli import main

if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--minutes", default="7", help="PPO budget in wall-clock minutes (default 7)")
    parser.add_argument("--out", default="quickstart/policy.zip")
    args, rest = parser.parse_known_args()
    sys.exit(main(["ppo", "--in", "imagination", "--minutes", args.minutes, "--num-envs", "512", "--n-steps", "24",
                   "--out", args.out, *rest]))

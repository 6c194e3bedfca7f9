"""Quick start: clone a trot from logged data, improve it with PPO inside the learned simulator, test it in physics.

    pip install . && python examples/quickstart.py

1. Behaviour cloning (warm start): the PPO actor's mean action is regressed onto the actions of the shipped
   demonstrations (`assets/checkpoints/anymal_d_demos.h5`: 64 episodes of the scripted trot, `rwm_gym.policies.gait`, the
   data the world model was trained on). PPO from scratch does not find a walk in the few million imagined steps a
   small CPU affords; the clone starts from one.
2. The cloned actor is evaluated in physics (MuJoCo, `AnymalD-MuJoCo-v0`) on fixed commands.
3. On `RWM-AnymalD-v0`, the shipped ANYmal D world model with 512 imagined robots stepped in one forward pass: the
   critic is fitted to the clone first (actor frozen, 5 rollouts), then PPO (Stable-Baselines3) fine-tunes the actor
   for 13 rollouts (160k imagined steps) in 2 s episodes that restart from real 32-step histories.
4. The PPO policy is evaluated in physics on the same commands and seeds.

Both tables are printed; compare them. Measured on 2 CPU cores: return 6.01 -> 7.86, |dv_xy| 0.272 -> 0.233 m/s,
falls 5 -> 3 of 18 (the +0.5 m/s command went from 0.11 to 0.37 m/s achieved); with `--seed 1` or `--seed 2` the same
run ends below the clone (2.21, 3.45), and `--keep-best` hands the clone back. The budget is short on purpose:
longer PPO on this model exploits its errors (1M imagined steps: the imagined reward kept rising while the policy
fell in all 18 physics episodes). `--keep-best` is the safety net: if PPO made the policy worse in physics, the clone
is kept as policy.zip and the output says so. Written to `quickstart/`: policy_bc.zip (the clone), policy.zip (the
kept policy; load with `PPO.load`), policy_ppo.zip (after PPO, when it was not kept), policy.json (config, cloning and
training logs, both evaluations, `kept`) and policy.png (commanded vs achieved velocity per command). The same as

    rwm-gym ppo --in imagination --timesteps 150000 --critic-warmup-steps 50000 --num-envs 512 --n-steps 24 \\
        --episode-steps 100 --net-arch 512 256 128 --learning-rate 1e-4 \\
        --bc-data <assets>/checkpoints/anymal_d_demos.h5 --bc-steps 6000 --bc-log-std -2.3 \\
        --keep-best --threads 1 --out quickstart/policy.zip
"""

from __future__ import annotations

import argparse
import os
import sys

if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--timesteps", default="150000", help="PPO budget in imagined steps (default 150000)")
    parser.add_argument("--threads", default="1", help="torch CPU threads (default 1: fastest on a small shared CPU)")
    parser.add_argument("--out", default="quickstart/policy.zip")
    args, rest = parser.parse_known_args()
    os.environ.setdefault("OMP_NUM_THREADS", args.threads)  # before torch is imported
    from rwm_gym.cli import main
    from rwm_gym.rl.warm_start import default_demonstrations

    sys.exit(main(["ppo", "--in", "imagination", "--timesteps", args.timesteps, "--critic-warmup-steps", "50000",
                   "--num-envs", "512", "--n-steps", "24", "--episode-steps", "100",
                   "--net-arch", "512", "256", "128", "--learning-rate", "1e-4",
                   "--bc-data", str(default_demonstrations()), "--bc-steps", "6000", "--bc-log-std", "-2.3",
                   "--keep-best", "--threads", args.threads, "--out", args.out, *rest]))

"""Quick start: clone a trot from logged data, improve it with PPO inside the learned simulator, test it in physics.

    pip install . && python examples/quickstart.py

1. Behaviour cloning (warm start): the PPO actor's mean action is regressed onto the actions of the shipped
   demonstrations (`assets/checkpoints/anymal_d_demos.h5`: 64 episodes of the scripted trot, `rwm_gym.data.gait`, the
   data the world model was trained on). PPO from scratch does not find a walk in the few million imagined steps a
   small CPU affords; the clone starts from one.
2. The cloned actor is evaluated in physics (MuJoCo, `AnymalD-MuJoCo-v0`) on fixed commands.
3. PPO (Stable-Baselines3) fine-tunes it for a few minutes on `RWM-AnymalD-v0`, the shipped ANYmal D world model,
   with 512 imagined robots stepped in one forward pass.
4. The PPO policy is evaluated in physics on the same commands and seeds.

Both tables are printed; compare them. PPO in imagination can make the policy worse in physics (it exploits the
world model's errors: on the shipped model, 5 min of PPO took the clone from 5/18 falls to 18/18 while the imagined
return stayed level); `--keep-best` then keeps the clone as policy.zip and says so (a choice made on the physics
evaluation). Written to `quickstart/`: policy_bc.zip (the clone), policy.zip (the kept policy; load with `PPO.load`),
policy_ppo.zip (after PPO, when it was not kept), policy.json (config, cloning and training logs, both evaluations,
`kept`) and policy.png (commanded vs achieved velocity per command of the kept policy). The same as

    rwm-gym ppo --in imagination --minutes 5 --num-envs 512 --n-steps 24 --episode-steps 250 --net-arch 512 256 128 \\
        --learning-rate 1e-4 --bc-data <assets>/checkpoints/anymal_d_demos.h5 --bc-steps 6000 --bc-log-std -2.3 \\
        --keep-best --threads 1 --out quickstart/policy.zip
"""

from __future__ import annotations

import argparse
import os
import sys

if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--minutes", default="5", help="PPO budget in wall-clock minutes (default 5)")
    parser.add_argument("--threads", default="1", help="torch CPU threads (default 1: fastest on a small shared CPU)")
    parser.add_argument("--out", default="quickstart/policy.zip")
    args, rest = parser.parse_known_args()
    os.environ.setdefault("OMP_NUM_THREADS", args.threads)  # before torch is imported
    from rwm_gym.cli import main
    from rwm_gym.imagination.warm_start import default_demonstrations

    sys.exit(main(["ppo", "--in", "imagination", "--minutes", args.minutes, "--num-envs", "512", "--n-steps", "24",
                   "--episode-steps", "250", "--net-arch", "512", "256", "128", "--learning-rate", "1e-4",
                   "--bc-data", str(default_demonstrations()), "--bc-steps", "6000", "--bc-log-std", "-2.3",
                   "--keep-best", "--threads", args.threads, "--out", args.out, *rest]))

"""The Jaco arm learns to reach inside its world model, then reaches in physics.

    python examples/reach_in_imagination.py            # about 25 min on one CPU core

1. Data (`rwm-gym collect`): random actions, and the scripted reach (`rwm_gym.policies.reach`) at five levels of
   action noise, so the data hold clean reaches, hovering and misses.
2. A world model (`rwm-gym train`): RWM with 5 ensemble heads on that mix.
3. PPO from scratch inside it (`rwm-gym ppo`): 256 imagined arms restarting from real histories, 4-s episodes. The
   imagined env integrates the arm's predicted joint velocities and places its hand by forward kinematics
   (`ImaginationOptions.kinematics`); the target stays where the history put it. No physics sample is used.
4. The policy judged in physics: success (the pinch site within the target's 5 cm at the last of 250 steps) over 100
   episodes, beside random actions.

Every stage keeps its output under `--out` and is skipped when it exists: run the command again after an
interruption. docs/guides/manipulation.md has the measured figures.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

ENV = "DMC-Jaco-ReachSite-v0"
NOISE = (0.0, 0.1, 0.2, 0.3, 0.5)
"""Action noise of the scripted reach's episodes: clean reaches to misses (`rwm-gym collect --policy reach`)."""
REACHES = 0.80
"""Success rate at which the policy reaches."""


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, default=Path("reach"))
    parser.add_argument("--random-episodes", type=int, default=256)
    parser.add_argument("--reach-episodes", type=int, default=192, help="scripted reaches per noise level")
    parser.add_argument("--iterations", type=int, default=2000, help="world-model gradient steps")
    parser.add_argument("--timesteps", type=int, default=1_500_000, help="PPO's imagined steps")
    parser.add_argument("--num-envs", type=int, default=256)
    parser.add_argument("--eval-episodes", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", default="1", help="torch CPU threads")
    args = parser.parse_args(argv)
    os.environ.setdefault("OMP_NUM_THREADS", args.threads)  # before torch is imported

    import rwm_gym
    from rwm_gym.cli import main as rwm

    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    parts = [_collect(rwm, out / "random.h5", ["--policy", "random", "--episodes", str(args.random_episodes)], 0)]
    for k, sigma in enumerate(NOISE, start=1):  # other seeds than the random episodes': other targets
        flags = ["--policy", "reach", "--action-noise", str(sigma), "--episodes", str(args.reach_episodes)]
        parts.append(_collect(rwm, out / f"reach_{sigma}.h5", flags, 10_000 * k))
    data = out / "mix.h5"
    if not data.is_file():
        rwm_gym.merge_datasets([str(p) for p in parts], str(data))
    model = out / "model.safetensors"
    if not model.is_file():
        train = ["train", "--data", str(data), "--ensemble-size", "5", "--iterations", str(args.iterations)]
        _run(rwm, [*train, "--seed", str(args.seed), "--out", str(model)])
    policy = out / "policy.zip"
    imagined = ["--episode-steps", "100", "--random-first-episode-length", "--log-std-init", "-1.0"]
    sizes = ["--num-envs", str(args.num_envs), "--n-steps", "32", "--timesteps", str(args.timesteps)]
    run = ["--run-dir", str(out / "run"), "--threads", args.threads, "--seed", str(args.seed), "--out", str(policy)]
    _run(rwm, ["ppo", "--checkpoint", str(model), *imagined, *sizes, *run, "--no-eval"])  # judged below, 100 episodes

    from rwm_gym.rl.evaluate_dmc import evaluate_episodes

    result = evaluate_episodes(str(policy), ENV, seeds=args.eval_episodes)
    floor = evaluate_episodes(_random_actions(args.eval_episodes), ENV, seeds=args.eval_episodes)
    print(f"this policy, in physics: {result.summary()}")
    print(f"random actions:          {floor.summary()}")
    reaches = result.success_rate >= REACHES
    print(
        ("VERDICT: it reaches" if reaches else "VERDICT: it does not reach yet")
        + f" (success {result.success_rate:.2f} over {result.episodes} physics episodes; reaches: >= {REACHES})"
    )
    return 0


def _random_actions(num_envs: int):
    """`rwm-gym collect --policy random`'s correlated random actions, one generator per episode."""
    import numpy as np

    from rwm_gym.policies.factory import make_policy
    from rwm_gym.registration import resolve_spec

    policy = make_policy("random", resolve_spec(ENV), num_envs)
    policy.reset(np.arange(num_envs), [np.random.default_rng(k) for k in range(num_envs)])
    return policy.act


def _collect(rwm, path: Path, flags: list[str], seed: int) -> Path:
    if not path.is_file():
        _run(rwm, ["collect", "--env", ENV, *flags, "--seed", str(seed), "--out", str(path)])
    return path


def _run(rwm, argv: list[str]) -> None:
    code = rwm(argv)
    if code:
        raise SystemExit(f"rwm-gym {argv[0]} failed (exit code {code})")


if __name__ == "__main__":
    sys.exit(main())

"""The MBPO loop's base buffer: a physics mix of the ANYmal D task's ordinary motions (about 200 k rows, ~1 min).

    python examples/make_base_mix.py --out data/base

The loop (`rwm-gym mbpo --data data/base/mix.h5 ...`, README "Policies") fine-tunes its world model on this mix
plus every episode it collects, so the model keeps what it knew of standing, trotting, random flailing and the
physics teacher at three levels of action noise while it learns the new policy's states. Writes one file per part
(OUT/<name>.h5) and their merge (OUT/mix.h5), with fixed seeds: the same command gives the same rows.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from rwm_gym.data.collect import collect, finished_collection
from rwm_gym.data.dataset import Dataset, DatasetError, merge_datasets
from rwm_gym.resources import assets_dir

TEACHER = str(assets_dir() / "policies" / "anymal_d_ppo_physics.zip")

# (part name, policy, episodes, max steps, action noise, first seed)
PARTS = (
    ("teacher", TEACHER, 96, 400, 0.0, 10_000),
    ("teacher_noise03", TEACHER, 96, 400, 0.3, 20_000),
    ("teacher_noise08", TEACHER, 96, 400, 0.8, 30_000),
    ("random", "random", 128, 300, 0.0, 40_000),
    ("standing", "zero", 64, 400, 0.0, 50_000),
    ("trot", "gait", 96, 400, 0.1, 60_000),
)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("data/base"))
    parser.add_argument("--num-envs", type=int, default=16)
    parser.add_argument("--overwrite", action="store_true", help="replace an existing OUT/mix.h5 and its parts")
    args = parser.parse_args()
    mix = args.out / "mix.h5"
    if mix.exists() and not args.overwrite:
        raise SystemExit(f"{mix} exists (pass --overwrite)")
    args.out.mkdir(parents=True, exist_ok=True)
    parts = []
    for name, policy, episodes, max_steps, noise, seed in PARTS:
        part = args.out / f"{name}.h5"
        try:
            finished = not args.overwrite and finished_collection(
                part, episodes=episodes, seed=seed, what=f"this script's {name} part"
            )
        except DatasetError as error:
            raise SystemExit(f"{error} (pass --overwrite)") from None
        if not finished:
            collect(
                "AnymalD-MuJoCo-v0",
                policy,
                episodes,
                part,
                seed=seed,
                num_envs=args.num_envs,
                action_noise=noise,
                max_steps=max_steps,
                overwrite=True,
            )
        parts.append(part)
        print(f"{name}: {Dataset.load(part).num_steps} rows")
    merge_datasets(parts, mix)
    print(f"{mix}: {Dataset.load(mix).num_steps} rows")


if __name__ == "__main__":
    main()

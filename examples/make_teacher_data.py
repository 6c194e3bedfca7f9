"""World-model data from the physics PPO teacher run: its training experience plus held-out episodes of three stages.

    python examples/make_teacher_data.py --run-dir runs/ppo_physics --out data/teacher

The run (`runs/ppo_physics.sh`, i.e. `rwm-gym ppo --in physics --run-dir ... --record-every 8`) has already written
the episodes of every 8th env to RUN/experience/part_*.h5 while it trained, policies from every stage, with the PPO
rollout of each step as the field `ppo_iteration`. This script:
- merges those parts into OUT/experience.h5 (unfinished episodes of a killed process were never written);
- collects `--episodes` held-out episodes (random commands, the task's own resampling) with an early, a middle and
  the final policy into OUT/heldout_{early,middle,final}.h5, seeds disjoint from training;
- writes OUT/manifest.json: rows, episodes, sizes, the snapshots used and the wall time.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from rwm_gym.atomic import write_json
from rwm_gym.data.collect import collect
from rwm_gym.data.dataset import Dataset, DatasetError, merge_datasets
from rwm_gym.rl.training_run import TrainingRun

HELD_OUT_SEED = 900_000
"""Seeds of held-out episodes start here, far from the training envs' seeds."""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run-dir", type=Path, default=Path("runs/ppo_physics"))
    parser.add_argument("--out", type=Path, default=Path("data/teacher"))
    parser.add_argument("--episodes", type=int, default=16, help="held-out episodes per stage")
    parser.add_argument("--num-envs", type=int, default=16)
    parser.add_argument("--overwrite", action="store_true")
    args = parser.parse_args()
    started = time.monotonic()
    run = TrainingRun(args.run_dir)
    args.out.mkdir(parents=True, exist_ok=True)

    parts = []
    for part in sorted(run.experience.glob("part_*.h5")):
        try:
            if Dataset.load(part).num_episodes:
                parts.append(part)
        except DatasetError as err:  # a process killed before its first episode leaves no episode
            print(f"skipping {part}: {err}")
    if not parts:
        raise SystemExit(f"{run.experience}: no experience episodes (run rwm-gym ppo with --record-every)")
    experience = args.out / "experience.h5"
    if experience.exists() and not args.overwrite:
        raise SystemExit(f"{experience} exists (pass --overwrite)")
    merge_datasets(parts, experience)

    snapshots = run.snapshot_files()
    final = run.latest if run.latest.is_file() else snapshots[-1]
    stages = {
        "early": snapshots[max(1, len(snapshots) // 10)],
        "middle": snapshots[len(snapshots) // 2],
        "final": final,
    }
    manifest = {"run_dir": str(run.folder), "experience_parts": [str(p) for p in parts], "stages": {}}
    for k, (stage, policy) in enumerate(stages.items()):
        path = collect(
            "AnymalD-MuJoCo-v0",
            str(policy),
            args.episodes,
            args.out / f"heldout_{stage}.h5",
            seed=HELD_OUT_SEED + 10_000 * k,
            num_envs=args.num_envs,
            overwrite=args.overwrite,
        )
        data = Dataset.load(path)
        manifest["stages"][stage] = {
            "policy": str(policy),
            "file": str(path),
            "episodes": data.num_episodes,
            "rows": int(data.num_steps),
            "mb": round(path.stat().st_size / 1e6, 1),
        }
    data = Dataset.load(experience)
    manifest["experience"] = {
        "file": str(experience),
        "episodes": data.num_episodes,
        "rows": int(data.num_steps),
        "mb": round(experience.stat().st_size / 1e6, 1),
        "ppo_iterations": [int(data["ppo_iteration"].min()), int(data["ppo_iteration"].max())],
    }
    manifest["wall_s"] = round(time.monotonic() - started, 1)
    write_json(args.out / "manifest.json", manifest)
    print(manifest)


if __name__ == "__main__":
    main()

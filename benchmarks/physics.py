"""Physics throughput of AnymalD-MuJoCo-v0, the shipped model against the previous one, in one run.

    python benchmarks/physics.py [--envs 1024 4096] [--threads 1 2] [--seconds 5] [--out results/physics]

The previous model ("elliptic") is rebuilt from the shipped MJCF by restoring its solver and collision settings: an
elliptic friction cone with impratio 100, MuJoCo's default 100 Newton / 50 line-search iterations, no no-slip pass, and
cylinders where the shipped model has capsules. Masses, inertias, joints and actuators are the same file.

Each row times env-steps/s (policy steps of 4 physics substeps) through the package's SB3 vector env
(`LocomotionSB3VecEnv`, auto-reset included) under two action streams: zero actions (standing) and uniform random
actions in [-1, 1], resampled every step. Both models are timed alternately in the same process, so a ratio is
measured under the same load. Also prints how many of `--stand-seeds` robots stand 20 s with zero action and how far
the base sinks, per model. Writes `<out>.json` and `<out>.md`.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import mujoco
import numpy as np

from rwm_gym.atomic import write_json, write_text
from rwm_gym.physics.locomotion import LocomotionEnv
from rwm_gym.resources import assets_dir
from rwm_gym.spec import load_spec
from rwm_gym.vector.sb3_vec_env import LocomotionSB3VecEnv

SHIPPED = "shipped"
PREVIOUS = "elliptic"


def previous_model_xml(folder: Path) -> Path:
    """The shipped scene with the previous solver and collision settings, written into `folder`."""
    spec = mujoco.MjSpec.from_file(str(assets_dir() / load_spec("anymal_d").model))
    spec.option.cone = mujoco.mjtCone.mjCONE_ELLIPTIC
    spec.option.impratio = 100.0
    spec.option.iterations = 100
    spec.option.ls_iterations = 50
    spec.option.noslip_iterations = 0
    for geom in spec.geoms:
        if geom.type == mujoco.mjtGeom.mjGEOM_CAPSULE and geom.contype:
            geom.type = mujoco.mjtGeom.mjGEOM_CYLINDER
    path = folder / "anymal_d_elliptic_scene.xml"
    path.write_text(spec.to_xml())
    return path


def timed_rate(env: LocomotionSB3VecEnv, actions: np.ndarray, seconds: float) -> float:
    """Env-steps/s of `env` stepping `actions` (k, n, A) in turn for about `seconds`."""
    env.step(actions[0])  # warm-up
    steps, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        env.step(actions[steps % len(actions)])
        steps += 1
    return steps * env.num_envs / (time.perf_counter() - start)


def standing(xml_file: Path | None, seed: int) -> tuple[bool, float]:
    """Whether the robot stands 20 s with zero action, and its base height change from 1 s to the end (m)."""
    env = LocomotionEnv(xml_file=xml_file)
    env.reset(seed=seed)
    z_start = None
    for t in range(env.task_spec.episode_steps):
        if env.step(np.zeros(12))[2]:
            return False, float("nan")
        if t == 49:
            z_start = float(env.unwrapped.data.qpos[2])
    return True, float(env.unwrapped.data.qpos[2]) - z_start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", type=int, nargs="+", default=[1024, 4096])
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--seconds", type=float, default=5.0)
    parser.add_argument("--stand-seeds", type=int, default=5)
    parser.add_argument("--out", type=Path, default=Path("results/physics"))
    args = parser.parse_args()

    with tempfile.TemporaryDirectory() as tmp:
        models = {SHIPPED: None, PREVIOUS: previous_model_xml(Path(tmp))}
        rows = []
        for n in args.envs:
            rng = np.random.default_rng(0)
            streams = {"standing": np.zeros((1, n, 12)), "random": rng.uniform(-1, 1, (16, n, 12))}
            for threads in args.threads:
                envs = {name: LocomotionSB3VecEnv(n, xml_file=xml, nthread=threads) for name, xml in models.items()}
                for env in envs.values():
                    env.seed(0)
                    env.reset()
                for stream, actions in streams.items():
                    rate = {name: timed_rate(env, actions, args.seconds) for name, env in envs.items()}
                    rows.append(
                        {
                            "envs": n,
                            "threads": threads,
                            "actions": stream,
                            **rate,
                            "ratio": rate[SHIPPED] / rate[PREVIOUS],
                            "loadavg": os.getloadavg()[0],
                        }
                    )
                    r = rows[-1]
                    print(
                        f"{n:5d} envs {threads} thr {stream:8s}: {r[SHIPPED]:8,.0f} vs {r[PREVIOUS]:8,.0f} "
                        f"env-steps/s, x{r['ratio']:.2f} (load {r['loadavg']:.2f})",
                        flush=True,
                    )
                for env in envs.values():
                    env.close()
        stand = {name: [standing(xml, seed) for seed in range(args.stand_seeds)] for name, xml in models.items()}

    lines = [
        f"| envs | threads | actions | {SHIPPED} env-steps/s | {PREVIOUS} env-steps/s | ratio | load avg |",
        "|---:|---:|---|---:|---:|---:|---:|",
    ]
    lines += [
        f"| {r['envs']} | {r['threads']} | {r['actions']} | {r[SHIPPED]:,.0f} | {r[PREVIOUS]:,.0f} | "
        f"{r['ratio']:.2f} | {r['loadavg']:.2f} |"
        for r in rows
    ]
    for name, results in stand.items():
        stood = [dz for ok, dz in results if ok]
        sink = f", base height change 1-20 s: {1000 * np.mean(stood):+.1f} mm (mean)" if stood else ""
        lines.append(f"\n{name}: zero action, 20 s: {len(stood)}/{len(results)} seeds stand{sink}")
    table = "\n".join(lines)
    print(table)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_text(args.out.with_suffix(".md"), table + "\n")
    write_json(
        args.out.with_suffix(".json"),
        {"rows": rows, "standing": {k: [{"stands": ok, "base_dz_m": dz} for ok, dz in v] for k, v in stand.items()}},
    )


if __name__ == "__main__":
    main()

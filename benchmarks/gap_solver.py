"""Does the fast MJCF's solver spoil the gap workflow's fits? The fit objective of one effect on a line of values.

Measured data with one hidden effect is made with the MJCF's own solver (`fast`: 4 iterations, as PPO runs it) or
solved to convergence (`converged`: `CONVERGED_SOLVER`), with or without sensor noise; its windows are re-simulated
with either solver at several values of the effect's parameter. Printed: the mean normalised squared residual per
value. A solver that is exact for its own data shows 0 at the true value without noise; the minimum's place and the
residual at the truth with noise show whether the solver biases the fit or amplifies the start state's noise.

    python benchmarks/gap_solver.py --effect joint_friction --true 2.0 --values 1.5 2.0 2.5 3.0 --noise 0 1
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from rwm_gym.data.dataset import Dataset
from rwm_gym.gap.effects import vocabulary
from rwm_gym.gap.measured import SensorNoise, make_measured
from rwm_gym.gap.resim import Resimulator, make_windows, normalised_residual
from rwm_gym.physics.params import CONVERGED_SOLVER, PhysicsParams
from rwm_gym.spec import load_spec

SOLVERS = {"fast": None, "converged": CONVERGED_SOLVER}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--effect", default="joint_friction", help="a one-parameter effect of the vocabulary")
    parser.add_argument("--true", type=float, default=2.0, help="hidden value")
    parser.add_argument("--values", type=float, nargs="+", default=[0.0, 1.5, 2.0, 2.5, 3.0])
    parser.add_argument("--noise", type=float, nargs="+", default=[0.0, 1.0], help="sensor-noise scales")
    parser.add_argument("--episodes", type=int, default=4)
    parser.add_argument("--steps", type=int, default=120)
    parser.add_argument("--horizon", type=int, default=10, help="re-simulated steps per window")
    args = parser.parse_args()
    spec = load_spec("anymal_d")
    effect = vocabulary(spec)[args.effect]
    if len(effect.parameters) != 1:
        parser.error(f"--effect {args.effect} has {len(effect.parameters)} parameters; pick a one-parameter effect")
    with tempfile.TemporaryDirectory() as tmp:
        for noise in args.noise:
            for data_name, data_solver in SOLVERS.items():
                path = make_measured(
                    {args.effect: effect.values_from_magnitude(args.true).tolist()},
                    args.episodes,
                    Path(tmp) / f"{data_name}_{noise}.h5",
                    max_steps=args.steps,
                    noise=SensorNoise(scale=noise),
                    solver=data_solver,
                    progress=False,
                )
                data = Dataset.load(path)
                windows = make_windows(data, np.arange(data.num_episodes), args.horizon, 5)
                for resim_name, resim_solver in SOLVERS.items():
                    resim = Resimulator(spec, solver=resim_solver)
                    costs = []
                    for v in args.values:
                        params = effect.physics(effect.values_from_magnitude(v), PhysicsParams())
                        residual = normalised_residual(spec, resim.rollout(windows, params), windows.target)
                        costs.append(float((residual**2).mean()))
                    print(
                        f"noise {noise:g} data {data_name:9s} resim {resim_name:9s} "
                        + " ".join(f"{v:g}:{c:.5f}" for v, c in zip(args.values, costs)),
                        flush=True,
                    )


if __name__ == "__main__":
    main()

"""The closing-note table of the gap workflow: every effect of the vocabulary hidden in measured data, named or not.

For each effect (at its realistic default magnitude, or at `--scale` times it) and for no effect, make measured data
with the effect hidden, run `rwm-gym gap` on it, and print: effect, true magnitude, named effect, fitted magnitude,
gap before, gap after (held-out, normalised state MSE averaged over horizons 1, 5, 25). Also written as JSON.

    python benchmarks/gap_table.py [--episodes 9] [--steps 150] [--scale 1.0] [--effects joint_friction armature]
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from rwm_gym.atomic import write_json
from rwm_gym.gap.effects import EFFECT_NAMES, vocabulary
from rwm_gym.gap.measured import make_measured
from rwm_gym.gap.workflow import run_gap
from rwm_gym.spec import load_spec


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=9, help="measured episodes (6 leave backlash untested: p > 0.01)")
    parser.add_argument("--steps", type=int, default=150)
    parser.add_argument("--scale", type=float, default=1.0,
                        help="magnitude = nominal + scale * (default - nominal), clipped to the effect's range")
    parser.add_argument("--effects", nargs="*", default=[*EFFECT_NAMES, "none"])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", type=Path, default=Path("gap_table.json"))
    args = parser.parse_args()
    effects = vocabulary(load_spec("anymal_d"))
    rows = []
    header = ("effect", "true", "named", "fitted", "gap before", "gap after", "error")
    print(f"{header[0]:16s} {header[1]:>9s} {header[2]:16s} {header[3]:>9s} {header[4]:>11s} {header[5]:>10s} "
          f"{header[6]:>7s}")
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.effects:
            hidden, true = {}, float("nan")
            if name != "none":
                p = effects[name].parameters[0]
                true = float(np.clip(p.nominal + args.scale * (p.default - p.nominal), p.low, p.high))
                true = round(true / p.step) * p.step if p.step else true  # what the simulator can hold
                hidden = {name: effects[name].values_from_magnitude(true)}
            data = make_measured(hidden, args.episodes, Path(tmp) / f"{name}.h5", max_steps=args.steps,
                                 seed=args.seed, progress=False)
            try:
                report = run_gap("AnymalD-MuJoCo-v0", data, Path(tmp) / name, progress=False)
            except ValueError as err:  # e.g. a magnitude at which the robot falls at once: no windows
                print(f"{name:16s} {true:9.4g} error: {err}", flush=True)
                continue
            fitted = next(iter(report["parameters"].values()), float("nan"))
            error = abs(fitted - true) / abs(true - effects[name].parameters[0].nominal) if name != "none" else 0.0
            row = {"effect": name, "true": true, "named": report["effect"], "fitted": fitted,
                   "gap_before": report["gap_before"], "gap_after": report["gap_after"],
                   "relative_error": error, "parameters": report["parameters"]}
            rows.append(row)
            print(f"{name:16s} {true:9.4g} {report['effect']:16s} {fitted:9.4g} {report['gap_before']:11.4g} "
                  f"{report['gap_after']:10.4g} {error:7.1%}", flush=True)
    write_json(args.json, rows)


if __name__ == "__main__":
    main()

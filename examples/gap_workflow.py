"""The sim-to-real gap workflow end to end on one hidden effect, world model included.

1. Make "measured" data: the ANYmal D simulator with one hidden effect (default: 2 N·m of Coulomb friction in every
   joint) plus sensor noise; nothing in the file says so.
2. Run the workflow against the nominal simulator: it re-simulates measured windows, finds where the gap lives,
   fits every effect of the vocabulary, names the one that explains the held-out gap, and writes the corrected robot.
3. Carry the correction into the world model: regenerate data from the corrected simulator, fine-tune the shipped
   nominal-sim world model on it plus the measured fitting episodes, and compare nominal sim, corrected sim, nominal
   world model and corrected world model on the held-out measured episodes.
4. Show the report.

    python examples/gap_workflow.py [--out gap_example] [--effect joint_friction] [--magnitude 2.0] [--episodes 9]
        [--steps 150] [--world-model none] [--finetune-iterations 300]
"""

import argparse
from pathlib import Path

from rwm_gym.gap.effects import parse_effects
from rwm_gym.gap.measured import make_measured
from rwm_gym.gap.workflow import resolve_world_model, run_gap
from rwm_gym.gap.world_model import WorldModelGapConfig
from rwm_gym.spec import load_spec

SIM = "AnymalD-MuJoCo-v0"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("gap_example"))
    parser.add_argument("--effect", default="joint_friction", help="effect of the vocabulary to hide")
    parser.add_argument("--magnitude", default="2.0", help="its value(s), e.g. 2.0 or 0.7,1.2")
    parser.add_argument("--episodes", type=int, default=9)
    parser.add_argument("--steps", type=int, default=150)
    parser.add_argument("--world-model", default="auto", help="nominal-sim world model (auto: shipped; none: skip)")
    parser.add_argument("--finetune-iterations", type=int, default=WorldModelGapConfig.iterations)
    args = parser.parse_args()

    hidden = parse_effects(load_spec("anymal_d"), [args.effect], [args.magnitude])
    measured = make_measured(hidden, args.episodes, args.out / "measured.h5", max_steps=args.steps, overwrite=True)
    report = run_gap(
        SIM,
        measured,
        args.out / "report",
        world_model=resolve_world_model(args.world_model, SIM, {}),
        wm_config=WorldModelGapConfig(iterations=args.finetune_iterations),
    )
    print((args.out / "report" / "report.md").read_text())
    print(f"hidden: {args.effect} = {args.magnitude}; named: {report['effect']} {report['parameters']}")


if __name__ == "__main__":
    main()

"""Does a policy fine-tuned in the corrected simulator walk better on the measured robot?

For each hidden robot (physical parameters the nominal simulator lacks, solved to convergence as a real robot
would be), the chain a user runs with the package's commands:

1. `rwm-gym make-measured --physics ROBOT`: the robot's "measured" episodes (excitation policy, sensor noise);
2. `rwm-gym gap --measured ... --world-model none`: the named effects, written as `corrected_physics.json`;
3. `rwm-gym ppo --in physics --init-policy NOMINAL --physics SIM`: the nominal policy fine-tuned by PPO for the same
   budget in three simulators: the nominal one (does fine-tuning alone help?), the corrected one, and the true one
   (the robot's own physics: the ceiling);
4. `rwm-gym score --policy P --physics ROBOT`: every policy's tracking score (54 episodes, falls counted) on the
   robot, beside standing still there (zero actions, the same episodes).

The share of the loss recovered is (corrected - before) / (true - before) in tracking on the robot, `before` being the
nominal policy's own score there (above 100 % where the ceiling's fine-tune ends below the corrected one's). Each
stage's output is kept under `--out` and reused when it exists (a killed run continues where it stopped).

    python benchmarks/gap_policy.py --out results/gap_policy                       # every robot, 3 M steps each
    python benchmarks/gap_policy.py --out results/gap_policy --robots weak_leg_delay --timesteps 1000000
    python benchmarks/gap_policy.py --out results/gap_policy --summary-only
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from rwm_gym.atomic import write_json, write_text
from rwm_gym.cli import main as rwm_gym

ROBOTS: dict[str, tuple[str, dict]] = {
    "weak_leg_delay": (
        "left front leg at half strength, 20 ms action delay",
        {"motor_strength": [0.5, 0.5, 0.5] + [1.0] * 9, "action_delay": 0.02},
    ),
    "slip_payload": (
        "10 kg payload on a slippery floor (friction 0.5)",
        {"payload_mass": 10.0, "ground_friction": 0.5},
    ),
    "friction_payload": (
        "3 N·m joint friction, 15 kg payload 0.1 m behind the base",
        {"joint_friction": 3.0, "payload_mass": 15.0, "payload_com": [-0.1, 0.0, 0.0]},
    ),
    "torque_payload": (
        "drives limited to 35 N·m, 10 kg payload",
        {"torque_limit": 35.0, "payload_mass": 10.0},
    ),
}
"""Hidden robots on which the shipped model-free policy degrades (tracking 0.923 on the nominal robot)."""

CONVERGED = {"solver": {"iterations": 100}}
"""The robot is solved to convergence (as `make-measured` does by default); the nominal simulator is the fast MJCF's,
the corrected one what the gap report says (its solver included), the true one the robot's own."""

NOMINAL_POLICY = "assets/policies/anymal_d_ppo_physics.zip"
SIMULATORS = ("nominal", "corrected", "true")


def _run(argv: list[str]) -> None:
    print("$ rwm-gym " + " ".join(argv), flush=True)
    code = rwm_gym(argv)
    if code:
        raise SystemExit(f"rwm-gym {argv[0]} failed with exit code {code}")


def _score(policy: str, robot: dict, out: Path, scoring: list[str]) -> dict:
    if not (out / "score.json").is_file():
        physics = json.dumps({**robot, **CONVERGED})
        _run(["score", "--policy", policy, "--physics", physics, *scoring, "--out", str(out)])
    report = json.loads((out / "score.json").read_text())
    floor = {"tracking": report["floor"]["tracking"], "falls": report["floor"]["falls"]}
    return {"tracking": report["tracking"], "falls": report["falls"], "episodes": report["episodes"], "floor": floor}


def run_robot(name: str, robot: dict, args: argparse.Namespace) -> dict:
    """Every stage for one hidden robot; its row of the table."""
    folder = args.out / name
    folder.mkdir(parents=True, exist_ok=True)
    measured, report = folder / "measured.h5", folder / "gap"
    if not measured.is_file():
        episodes = ["--episodes", str(args.episodes)]
        _run(["make-measured", "--physics", json.dumps(robot), *episodes, "--out", str(measured)])
    if not (report / "corrected_physics.json").is_file():
        _run(["gap", "--measured", str(measured), "--world-model", "none", "--out", str(report)])
    gap = json.loads((report / "report.json").read_text())
    corrected = json.loads((report / "corrected_physics.json").read_text())["physics"]
    sims = {"nominal": {}, "corrected": corrected, "true": {**robot, **CONVERGED}}
    scoring = [] if args.score_steps is None else ["--seeds", "1", "--commands", "0", "--steps", str(args.score_steps)]
    row = {
        "robot": robot,
        "named": [f"{effect['effect']} ({effect['scope']})" for effect in gap["effects"]],
        "verdict": gap["effect"],
        "corrected_physics": corrected,
        "timesteps": args.timesteps,
        "scores": {"before": _score(args.policy, robot, folder / "score_before", scoring)},
    }
    row["standing_still"] = row["scores"]["before"]["floor"]  # zero actions on the same robot, same episodes
    for sim in SIMULATORS:
        tuned = folder / f"tuned_{sim}.zip"
        if not tuned.is_file():
            started = time.monotonic()
            argv = ["ppo", "--in", "physics", "--init-policy", args.policy, "--timesteps", str(args.timesteps)]
            argv += ["--num-envs", str(args.num_envs), "--n-steps", str(args.n_steps), "--seed", str(args.seed)]
            argv += ["--threads", "1", "--no-eval"]
            argv += ["--run-dir", str(folder / f"run_{sim}"), "--out", str(tuned)]
            if sims[sim]:
                argv += ["--physics", json.dumps(sims[sim])]
            _run(argv)
            print(f"{name}: fine-tuned in the {sim} simulator in {time.monotonic() - started:.0f} s")
        row["scores"][sim] = _score(str(tuned), robot, folder / f"score_{sim}", scoring)
    lost = row["scores"]["true"]["tracking"] - row["scores"]["before"]["tracking"]
    gained = row["scores"]["corrected"]["tracking"] - row["scores"]["before"]["tracking"]
    row["recovered"] = gained / lost if lost > 0 else None
    write_json(folder / "row.json", row)
    return row


def table(rows: dict[str, dict]) -> str:
    """Markdown: tracking (falls in 54) on each robot of standing still, of the nominal policy and of its three
    fine-tunes."""
    lines = [
        "| robot | named effects | standing still | nominal policy | fine-tuned: nominal sim | corrected sim "
        "| true sim (ceiling) | loss recovered |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, row in rows.items():
        scores = [row["standing_still"], *(row["scores"][k] for k in ("before", *SIMULATORS))]
        cells = " | ".join(f"{score['tracking']:.3f} ({score['falls']})" for score in scores)
        recovered = "-" if row["recovered"] is None else f"{100 * row['recovered']:.0f} %"
        lines.append(f"| {ROBOTS[name][0]} | {', '.join(row['named']) or 'none'} | {cells} | {recovered} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--robots", nargs="+", choices=sorted(ROBOTS), default=list(ROBOTS))
    parser.add_argument("--policy", default=NOMINAL_POLICY, help="the nominal policy fine-tuned (SB3 zip)")
    parser.add_argument("--timesteps", type=int, default=3_000_000, help="PPO steps of each fine-tune")
    parser.add_argument("--num-envs", type=int, default=1024)
    parser.add_argument("--episodes", type=int, default=16, help="measured episodes per robot")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--n-steps", type=int, default=24, help="PPO steps per env per update")
    parser.add_argument(
        "--score-steps", type=int, default=None, help="a quick look: score 2 commands x 1 episode of this many steps"
    )
    parser.add_argument("--summary-only", action="store_true", help="tabulate the robots already finished")
    args = parser.parse_args(argv)
    rows = {}
    for name in args.robots:
        finished = args.out / name / "row.json"
        if args.summary_only:
            if finished.is_file():
                rows[name] = json.loads(finished.read_text())
            continue
        rows[name] = run_robot(name, ROBOTS[name][1], args)
    write_json(args.out / "summary.json", rows)
    text = table(rows)
    write_text(args.out / "gap_policy.md", text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

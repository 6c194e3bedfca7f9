"""What the commands of the learners that differentiate through a world model share (`rwm-gym shac`, `rwm-gym dreamer`):
the imagination options their stepper implements, the refusal of a spec's own reward functions, and their run log."""

from __future__ import annotations

import csv
import json
from dataclasses import asdict
from pathlib import Path

IMAGINATION_FIELDS = ("episode_steps", "fall_tilt", "torque_halt", "random_first_episode_length", "divergence_bound")
"""The `ImaginationOptions` the differentiable stepper (`rwm_gym.rl.shac.DifferentiableImagination`) implements (flags
generated from their field docstrings)."""


def refuse_entry_points(checkpoint: str | None, command: str = "rwm-gym shac", learner: str = "SHAC") -> None:
    """SHAC (and `rwm-gym dreamer`) differentiate the velocity-tracking reward and the terminations they implement
    themselves: a checkpoint whose spec names its own (`[imagination]` entry points) is refused in one line rather
    than trained on another task's reward."""
    if checkpoint is None:  # the shipped model names none
        return
    from rwm_gym.model.checkpoint import read_meta
    from rwm_gym.task.entry_points import spec_entry_points

    if named := spec_entry_points(read_meta(checkpoint).spec):
        raise SystemExit(
            f"{command}: {checkpoint}'s task spec names its own {' and '.join(named)} function "
            f"({', '.join(named.values())}); {learner} differentiates the velocity-tracking reward it implements, so "
            "it cannot train on them (rwm-gym ppo --trust-entry-points can)"
        )


def append_log_row(path: Path, stats, total_wall_s: float) -> None:
    """One update's statistics (a dataclass) as a row of the run's log.csv, with the run's total wall time."""
    row = {"total_wall_s": round(total_wall_s, 2), **asdict(stats)}
    new = not path.is_file()
    with path.open("a", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(row))
        if new:
            writer.writeheader()
        writer.writerow(row)


def jsonable(value):
    """`value` as it reads back from JSON (tuples as lists, other objects as strings), to compare with a saved state."""
    return json.loads(json.dumps(value, default=str))

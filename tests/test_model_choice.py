"""`rwm_gym.model.choice`: the kind `--model auto` picks from a measured table (nearest data size, nearest budget,
lowest error, the default kept within 10 %), the shipped table's provenance, and `rwm-gym train --model auto`."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from synthetic_dynamics import write_linear_dataset

from rwm_gym.cli import main
from rwm_gym.data.dataset import Dataset
from rwm_gym.model.checkpoint import read_meta
from rwm_gym.model.choice import (
    CANDIDATES,
    TOLERANCE,
    Measurement,
    ModelChoiceError,
    ModelChoiceTable,
    choose_kind,
    shipped_table,
)


def _table(errors: dict[tuple[str, int, float], dict[str, float]]) -> ModelChoiceTable:
    """(robot, rows, CPU-minutes) -> {kind: error}; every kind makes 100 iterations per CPU-minute."""
    return ModelChoiceTable(
        tuple(
            Measurement(robot, rows, minutes, kinds, {k: int(100 * minutes) for k in kinds if k != "no_change"})
            for (robot, rows, minutes), kinds in errors.items()
        ),
        provenance={"command": "synthetic"},
    )


SYNTHETIC = _table(
    {
        ("small", 10_000, 1.0): {"rwm": 0.80, "mlp": 0.50, "rssm": 0.70, "transformer": 0.60, "no_change": 1.0},
        ("small", 10_000, 16.0): {"rwm": 0.52, "mlp": 0.50, "rssm": 0.70, "transformer": 0.60, "no_change": 1.0},
        ("large", 200_000, 1.0): {"rwm": 0.90, "mlp": 0.95, "rssm": 0.40, "transformer": 0.60, "no_change": 1.0},
        ("large", 200_000, 16.0): {"rwm": 0.30, "mlp": 0.95, "rssm": 0.40, "transformer": 0.60, "no_change": 1.0},
    }
)


def test_the_nearest_budget_and_data_size_decide_and_the_lowest_error_wins() -> None:
    assert choose_kind(SYNTHETIC, 12_000, 2.0).kind == "mlp"  # nearest budget 1 (log scale), small data
    assert choose_kind(SYNTHETIC, 150_000, 2.0).kind == "rssm"  # the large robot's data size
    assert choose_kind(SYNTHETIC, 150_000, 10.0).kind == "rwm"  # its 16-minute budget
    choice = choose_kind(SYNTHETIC, 12_000, 3.0)
    assert (choice.cpu_minutes, choice.robots, choice.iterations) == (1.0, ("small",), 300)
    line = choice.reason(3.0, 12_000)
    assert "\n" not in line and "mlp (lowest" in line and "mlp 0.500" in line and "no change 1.000" in line


def test_the_default_is_kept_within_the_tolerance_and_nothing_further_above_the_best_is_picked() -> None:
    choice = choose_kind(SYNTHETIC, 12_000, 16.0)  # rwm 0.52 is 4 % above mlp's 0.50
    assert choice.kind == "rwm" and "the default, within 10% of mlp" in choice.reason(16.0, 12_000)
    rng = np.random.default_rng(0)
    for _ in range(300):
        errors = {
            (f"r{i}", int(rows), float(minutes)): {k: float(rng.uniform(0.2, 1.5)) for k in (*CANDIDATES, "no_change")}
            for i, rows in enumerate(rng.choice([5_000, 20_000, 80_000, 400_000], size=3))
            for minutes in (0.25, 1.0, 4.0)
        }
        table = _table(errors)
        choice = choose_kind(table, int(rng.integers(1_000, 10**6)), float(rng.uniform(0.1, 20.0)))
        best = min(e for k, e in choice.errors.items() if k in CANDIDATES)
        assert choice.errors[choice.kind] <= (1 + TOLERANCE) * best + 1e-12


def test_robots_of_a_similar_data_size_are_pooled_by_geometric_mean() -> None:
    table = _table(
        {
            ("a", 10_000, 1.0): {"rwm": 0.50, "mlp": 400.0},  # the MLP blew up on one robot
            ("b", 12_000, 1.0): {"rwm": 0.60, "mlp": 0.20},
            ("far", 900_000, 1.0): {"rwm": 9.0, "mlp": 0.01},
        }
    )
    choice = choose_kind(table, 11_000, 1.0)
    assert set(choice.robots) == {"a", "b"} and choice.kind == "rwm"
    assert choice.errors["mlp"] == pytest.approx(np.sqrt(400.0 * 0.20))


def test_a_table_of_another_format_or_an_empty_request_is_refused_in_one_line(tmp_path: Path) -> None:
    path = tmp_path / "t.json"
    path.write_text(json.dumps({**SYNTHETIC.to_dict(), "format": "something-else"}))
    with pytest.raises(ModelChoiceError, match="format 'something-else'"):
        ModelChoiceTable.load(path)
    SYNTHETIC.save(path)
    assert ModelChoiceTable.load(path) == SYNTHETIC
    with pytest.raises(ModelChoiceError, match="budget > 0"):
        choose_kind(SYNTHETIC, 1_000, 0.0)


def test_the_shipped_table_says_where_its_numbers_come_from() -> None:
    table = shipped_table()
    provenance = table.provenance
    assert provenance["command"].startswith("python benchmarks/budget_curve.py")
    assert provenance["hardware_start"]["cpu"] and provenance["budgets_cpu_minutes"] and provenance["robots"]
    more = provenance.get("more", [])
    assert all(source["commands"] and source["hardware"] and source["docs"] for source in more)
    robots = set(provenance["robots"]).union(*(source["robots"] for source in more))
    assert {m.robot for m in table.measurements} == robots
    swept = [m for m in table.measurements if m.robot in provenance["robots"]]  # every kind, by budget_curve.py
    assert all(set(CANDIDATES) <= set(m.errors) for m in swept)
    assert all({"rwm", "mlp", "no_change"} <= set(m.errors) for m in table.measurements)
    assert choose_kind(table, 10_000, 1.0).kind in CANDIDATES


def test_the_shipped_table_picks_rwm_for_a_go2_teachers_data_and_mlp_for_a_small_mix() -> None:
    """At 100 steps the MLP diverges on the Go2 teacher's 1.4 M rows (2.41 against RWM's 0.40) and wins on the
    cheetah's 13 k rows at 1 CPU-minute."""
    table = shipped_table()
    assert choose_kind(table, 1_400_000, 12.0).kind == "rwm"
    assert choose_kind(table, 13_000, 1.0).kind == "mlp"


def test_train_model_auto_picks_from_the_shipped_table_and_says_why(tmp_path: Path, capsys) -> None:
    data = write_linear_dataset(tmp_path / "linear.h5")
    out = tmp_path / "auto.safetensors"
    tiny = ["--history", "6", "--forecast", "3", "--batch-size", "8", "--hidden-size", "16", "--head-hidden", "16"]
    tiny += ["--transformer-dim", "16", "--rssm-latent", "4", "--quiet"]
    args = ["train", "--data", str(data), "--out", str(out), "--model", "auto", *tiny]
    assert main([*args, "--cpu-minutes", "0.003"]) == 0
    printed = capsys.readouterr().out.splitlines()
    rows = Dataset.load(data).num_steps
    expected = choose_kind(shipped_table(), rows, 0.003)
    assert printed[0] == expected.reason(0.003, rows)
    meta = read_meta(out)
    assert meta.model_config.kind == expected.kind and meta.train_config.minutes == 0.003
    assert main([*args, "--overwrite"]) == 2  # no budget to pick for
    assert "--cpu-minutes" in capsys.readouterr().err

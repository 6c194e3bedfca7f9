"""benchmarks/budget_curve.py on ANYmal D's shipped data at budgets fixed in iterations (`--seconds-per-iteration`):
continuing a finished budget, or a run killed after its checkpoint, ends at the numbers of one uninterrupted run;
the outputs and the `--model auto` table are written."""

from __future__ import annotations

import json
from pathlib import Path

from script_loader import BENCHMARKS, load_script

from rwm_gym.model.choice import ModelChoiceTable, choose_kind

# 1 CPU-second per iteration: 0.02 and 0.05 CPU-minutes are 1 and 3 iterations on any machine
TINY = ["--robots", "AnymalD-MuJoCo-v0", "--rows", "RWM,no-change", "--seconds-per-iteration", "1"]
TINY += ["--eval-windows", "4"]


def _curves(out: Path) -> dict:
    """Each row's iterations and errors per budget (the CPU time each took is measured, not reproduced)."""
    rows = json.loads((out / "results.json").read_text())["robots"]["AnymalD-MuJoCo-v0"]["rows"]
    return {
        row: {b: (r["iterations"], r["errors"], r["cpu_s"] > 0) for b, r in curve["budgets"].items()}
        for row, curve in rows.items()
    }


def test_resumed_budgets_end_where_one_run_does(tmp_path: Path) -> None:
    budget_curve = load_script(BENCHMARKS / "budget_curve.py", "budget_curve")
    full, steps = tmp_path / "full", tmp_path / "steps"
    recommendation = tmp_path / "choice.json"
    both = ["--budgets", "0.02", "0.05"]
    assert budget_curve.main([*TINY, *both, "--out", str(full), "--write-recommendation", str(recommendation)]) == 0
    assert budget_curve.main([*TINY, "--budgets", "0.02", "--out", str(steps)]) == 0
    assert budget_curve.main([*TINY, *both, "--out", str(steps)]) == 0  # continues the 0.02 model
    assert _curves(steps) == _curves(full)
    assert [_curves(full)["RWM"][b][0] for b in ("0.02", "0.05")] == [1, 3]
    record = steps / "runs" / "AnymalD-MuJoCo-v0" / "RWM.json"
    killed = json.loads(record.read_text())
    del killed["budgets"]["0.05"]  # killed after the checkpoint of 0.05, before its scores were written
    record.write_text(json.dumps(killed))
    assert budget_curve.main([*TINY, *both, "--out", str(steps)]) == 0
    assert _curves(steps) == _curves(full)
    table = (full / "results.md").read_text()
    assert "| AnymalD-MuJoCo-v0 | 0.05 |" in table and "| h=8 | h=32 | h=100 |" in table
    assert (full / "AnymalD-MuJoCo-v0.png").stat().st_size > 0
    choice = ModelChoiceTable.load(recommendation)
    assert choice.provenance["budgets_cpu_minutes"] == [0.02, 0.05]
    assert [m.iterations for m in choice.measurements] == [{"rwm": 1}, {"rwm": 3}]
    assert choose_kind(choice, 15_000, 0.05).kind == "rwm"
    assert budget_curve.main([*TINY, "--budgets", "0.01", "0.05", "--out", str(steps)]) == 2  # below a finished one
    assert budget_curve.main([*TINY, "--robots", "nosuch-task", "--out", str(steps)]) == 2

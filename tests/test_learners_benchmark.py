"""benchmarks/learners.py at a tiny budget: PPO, SHAC and the Dreamer-style learner each train in the same model, are
scored in physics and in the model, and land in one table, one figure and one JSON; the same command continues."""

from __future__ import annotations

import json
from pathlib import Path

from script_loader import BENCHMARKS, load_script


def test_the_learner_table_trains_scores_and_writes_its_table_figure_and_json(tmp_path: Path, capsys) -> None:
    learners = load_script(BENCHMARKS / "learners.py", "learners")
    argv = ["--out", str(tmp_path), "--seeds", "0", "--imagined-steps", "64", "--minutes", "1", "--num-envs", "8"]
    argv += ["--horizon", "4", "--score-seeds", "1", "--score-steps", "10"]
    assert learners.main(argv) == 0
    runs = json.loads((tmp_path / "learners.json").read_text())["runs"]
    assert sorted(r["learner"] for r in runs) == ["dreamer", "ppo", "shac"]
    for run in runs:
        assert run["imagined_steps"] >= 64 and run["physics"]["episodes"] == 18 and run["model"]["episodes"] == 18
        assert isinstance(run["exploited_commands"], list)
        assert (run["actor_grad_norm"] is None) == (run["learner"] == "ppo")  # SB3 does not log PPO's
    table = (tmp_path / "learners.md").read_text()
    assert table.count("\n") == 2 + 3 and "exploited commands" in table
    assert (tmp_path / "learners.png").stat().st_size > 0
    stamp = (tmp_path / "shac_s0" / "scores.json").stat().st_mtime_ns
    assert learners.main([*argv, "--plot"]) == 0  # the table again from the runs, nothing trained or scored
    assert (tmp_path / "shac_s0" / "scores.json").stat().st_mtime_ns == stamp

"""Smoke tests of benchmarks (benchmarks/cross_robot.py, benchmarks/dmc_imagination.py, benchmarks/ppo_seed_curves.py,
benchmarks/trainer.py), tiny budgets."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
from script_loader import BENCHMARKS, load_script


def _script(name: str):
    return load_script(BENCHMARKS / f"{name}.py", name)


@pytest.mark.slow
def test_cross_robot_writes_table_plot_and_json(tmp_path: Path, capsys) -> None:
    cross_robot = _script("cross_robot")
    assert (
        cross_robot.main(
            [
                "--iterations",
                "2",
                "--episodes",
                "2",
                "--episode-steps",
                "140",
                "--out",
                str(tmp_path),
                "--domains",
                "DMC-Finger-Spin-v0,DMC-Hopper-Hop-v0",
                "--eval-windows",
                "8",
            ]
        )
        == 0
    )
    result = json.loads((tmp_path / "results.json").read_text())
    assert set(result["domains"]) == {"DMC-Finger-Spin-v0", "DMC-Hopper-Hop-v0"}
    assert set(result["mean_rank"]) == set(cross_robot.MODELS)
    for domain in result["domains"].values():
        assert all(len(m["errors"]) == 100 and m["iterations"] in (0, 2) for m in domain["models"].values())
    table = (tmp_path / "results.md").read_text()
    assert "| h=8 | h=32 | h=100 |" in table and "mean rank" in table and table in capsys.readouterr().out
    assert (tmp_path / "error_vs_horizon.png").stat().st_size > 0
    saved = json.loads((tmp_path / "domains" / "DMC-Hopper-Hop-v0.json").read_text())
    assert saved["models"] == result["domains"]["DMC-Hopper-Hop-v0"]["models"]
    assert result["wall_s"] == pytest.approx(sum(d["wall_s"] for d in result["domains"].values()))
    saved["models"]["RWM"]["errors"][7] = 123.0  # a finished domain is reused, not recomputed
    (tmp_path / "domains" / "DMC-Hopper-Hop-v0.json").write_text(json.dumps(saved))
    assert (
        cross_robot.main(
            [
                "--iterations",
                "2",
                "--episodes",
                "2",
                "--episode-steps",
                "140",
                "--out",
                str(tmp_path),
                "--domains",
                "DMC-Hopper-Hop-v0",
                "--eval-windows",
                "8",
            ]
        )
        == 0
    )
    assert "| 123.000 |" in (tmp_path / "results.md").read_text()
    with pytest.raises(SystemExit):
        cross_robot.main(["--domains", "DMC-Nope-v0", "--out", str(tmp_path)])


@pytest.mark.slow
@pytest.mark.slow
def test_cross_robot_takes_the_jaco_arm_by_id_and_runs_the_suite_by_default(tmp_path: Path) -> None:
    cross_robot = _script("cross_robot")
    assert "DMC-Jaco-ReachSite-v0" not in cross_robot.Options().domains.split(",")
    assert len(cross_robot.Options().domains.split(",")) == 6
    args = ["--iterations", "1", "--episodes", "2", "--episode-steps", "60", "--horizons", "2,8", "--eval-windows", "4"]
    out = tmp_path / "arm"
    assert (
        cross_robot.main([*args, "--models", "RWM,no-change", "--domains", "DMC-Jaco-ReachSite-v0", "--out", str(out)])
        == 0
    )
    domain = json.loads((out / "results.json").read_text())["domains"]["DMC-Jaco-ReachSite-v0"]
    assert domain["rows"] == 4 * 61 and domain["action_dim"] == 9 and len(domain["models"]["RWM"]["errors"]) == 8


def test_dmc_imagination_trains_both_arms_and_scores_them_in_physics(tmp_path: Path) -> None:
    dmc_imagination = _script("dmc_imagination")
    assert (
        dmc_imagination.main(
            [
                "--env",
                "DMC-Finger-Spin-v0",
                "--wm-iterations",
                "2",
                "--ppo-minutes",
                "0.05",
                "--episodes",
                "2",
                "--episode-steps",
                "60",
                "--num-envs",
                "4",
                "--n-steps",
                "16",
                "--eval-seeds",
                "1",
                "--out",
                str(tmp_path),
            ]
        )
        == 0
    )
    result = json.loads((tmp_path / "DMC-Finger-Spin-v0" / "results.json").read_text())
    assert result["imagined_env"] == "RWM-Finger-v0" and result["data_rows"] == 4 * 61
    for arm in ("imagination", "physics"):
        assert result[arm]["ppo_steps"] > 0 and len(result[arm]["evaluation"]["returns"]) == 1
    assert (tmp_path / "DMC-Finger-Spin-v0" / "ppo_imagination.zip").is_file()
    assert len(result["untrained"]["evaluation"]["returns"]) == 1


def test_ppo_seed_curves_draws_every_run_and_refuses_a_run_without_scores(tmp_path: Path, monkeypatch, capsys) -> None:
    """Several runs' scored snapshots in one figure and one CSV, rows sorted by steps; a run never scored is named."""
    import csv

    script = _script("ppo_seed_curves")
    for seed, rows in enumerate(([(0, 0.23, 0), (3_000_000, 0.5, 4)], [(3_000_000, 0.1, 40), (0, 0.23, 0)])):
        (tmp_path / f"run{seed}" / "curve").mkdir(parents=True)
        with open(tmp_path / f"run{seed}" / "curve" / "curve.csv", "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["timesteps", "wall_s", "tracking", "return", "falls", "episodes", "loadavg"])
            w.writerows([t, t / 1000, s, 0.0, falls, 54, 1.0] for t, s, falls in rows)  # 1000 steps/s
    out = tmp_path / "fig" / "seeds"
    monkeypatch.setattr(
        sys,
        "argv",
        [
            "ppo_seed_curves.py",
            "--runs",
            str(tmp_path / "run0"),
            str(tmp_path / "run1"),
            "--labels",
            "seed 0",
            "seed 1",
            "--out",
            str(out),
        ],
    )
    script.main()
    assert out.with_suffix(".png").stat().st_size > 0
    table = list(csv.DictReader(out.with_suffix(".csv").open()))
    assert [(r["run"], int(r["timesteps"]), float(r["wall_s"]), r["falls"]) for r in table] == [
        ("seed 0", 0, 0.0, "0"),
        ("seed 0", 3_000_000, 3000.0, "4"),
        ("seed 1", 0, 0.0, "0"),
        ("seed 1", 3_000_000, 3000.0, "40"),
    ]
    monkeypatch.setattr(sys, "argv", ["ppo_seed_curves.py", "--runs", str(tmp_path / "missing"), "--out", str(out)])
    with pytest.raises(SystemExit, match=r"missing/curve/curve.csv: no such file"):
        script.main()


def test_trainer_benchmark_writes_throughput_curves_and_tables(tmp_path: Path) -> None:
    """benchmarks/trainer.py end to end on a tiny budget: both arms timed, both curves trained, JSON, table and plot
    written (its JSON write once took the arguments in the wrong order and lost a 20-minute run at the end)."""
    from synthetic_dynamics import write_linear_dataset

    data = write_linear_dataset(tmp_path / "linear.h5")
    trainer = _script("trainer")
    out = tmp_path / "out"
    assert (
        trainer.main(
            [
                "--data",
                str(data),
                "--out",
                str(out),
                "--threads",
                "1",
                "--rounds",
                "1",
                "--steps",
                "1",
                "--minutes",
                "0.005",
                "--val-every",
                "1",
                "--new-branches",
                "4",
                "--new-stride",
                "8",
                "--no-new-warmup-gradients",
            ]
        )
        == 0
    )
    results = json.loads((out / "results.json").read_text())
    assert results["arms"]["new"]["warmup_gradients"] is False and results["arms"]["old"]["warmup_gradients"]
    assert [row["threads"] for row in results["throughput"]] == [1]
    assert set(results["throughput"][0]["windows_per_s"]) == {"old", "new"}
    assert set(results["curves"]) >= {"old", "new"}
    assert (out / "results.md").read_text().count("|") > 10 and (out / "val_vs_minutes.png").stat().st_size > 0

"""Smoke tests of benchmarks (benchmarks/cross_robot.py, benchmarks/dmc_imagination.py, benchmarks/imagined_standing.py,
benchmarks/exploitation.py, benchmarks/ppo_seed_curves.py, benchmarks/trainer.py, benchmarks/trainer_compare.py,
benchmarks/disagreement.py, benchmarks/evaluation_compare.py), tiny budgets."""

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


def test_imagined_standing_counts_running_episodes(tmp_path: Path, capsys) -> None:
    standing = _script("imagined_standing")
    standing.main(["--episodes", "2", "--envs", "4", "--steps", "20", "--out", str(tmp_path)])
    rows = json.loads((tmp_path / "standing.json").read_text())["rows"]
    assert [r["step"] for r in rows] == [1, 10, 20]
    running = [r["running"] for r in rows]
    assert all(0.0 <= r <= 1.0 for r in running) and running == sorted(running, reverse=True)
    assert "running" in capsys.readouterr().out


def test_exploitation_tilt_saturation_and_foresight() -> None:
    """The exploitation benchmark's measures: tilt from projected gravity, the share of rows at the effort limit, and
    the model's open-loop view of the last steps of a physics episode (here a robot standing: no tilt, no fall)."""
    import numpy as np

    from rwm_gym.imagination.core import default_checkpoint
    from rwm_gym.model.checkpoint import load_checkpoint
    from rwm_gym.rl.score import zero_policy

    exploitation = _script("exploitation")
    assert [round(exploitation.tilt(np.array(g)), 6) for g in ((0, 0, -1), (1, 0, 0), (0, -1, 0), (0, 0, 1))] == [
        0.0,
        90.0,
        90.0,
        180.0,
    ]
    model, meta = load_checkpoint(default_checkpoint())
    spec = meta.spec
    states = np.zeros((4, spec.state_dim))
    states[1, spec.state_slices["joint_torque"].start + 5] = -spec.actuator.effort_limit
    assert exploitation.saturated_fraction(spec, states) == 0.25
    states, actions, fell = exploitation.physics_episode(zero_policy, (0.0, 0.0, 0.0), 0, 40)
    assert not fell and states.shape == (41, spec.state_dim) and actions.shape == (40, spec.action_dim)
    assert exploitation.foresight(model, meta, states, actions, 35) is None  # a warm-up of 5 rows is too short
    view = exploitation.foresight(model, meta, states, actions, 12)
    assert view["lead"] == 12 and view["tilt_physics"] < 5 and view["tilt_predicted"] < 10
    assert view["max_termination_probability"] < 0.5


def test_ppo_seed_curves_draws_every_run_and_refuses_a_run_without_scores(tmp_path: Path, monkeypatch, capsys) -> None:
    """Several runs' scored snapshots in one figure and one CSV, rows sorted by steps; a run never scored is named."""
    import csv
    import sys

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


def test_trainer_benchmark_writes_throughput_curves_and_tables(tmp_path: Path, monkeypatch) -> None:
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
    compare = _script("trainer_compare")  # the runs side by side: one row per arm, labelled by its setting
    monkeypatch.setattr(sys, "argv", ["trainer_compare.py", str(out), "--out", str(tmp_path / "cmp")])
    compare.main()
    table = (tmp_path / "cmp.md").read_text()
    assert "| out | old: 64 windows of 32 + 8 rows |" in table
    assert "| out | new: 64 x 4 branches, stride 8, no warm-up gradients |" in table
    assert (tmp_path / "cmp.png").stat().st_size > 0


def test_disagreement_benchmark_measures_the_second_model_against_the_first(tmp_path: Path) -> None:
    """benchmarks/disagreement.py on a tiny budget: per recorded source the model's error, its heads' disagreement and
    a second model's; per policy the same inside the model. A model compared with itself disagrees by exactly 0."""
    from rwm_gym.data.collect import collect
    from rwm_gym.resources import assets_dir

    bench = _script("disagreement")
    data = collect("AnymalD-MuJoCo-v0", "zero", 2, tmp_path / "stand.h5", max_steps=40, num_envs=2, progress=False)
    models = assets_dir() / "checkpoints"
    common = [
        "--checkpoint",
        str(models / "anymal_d_rwm.safetensors"),
        "--data",
        str(data),
        "--history",
        "8",
        "--horizon",
        "4",
        "--windows",
        "6",
        "--steps",
        "12",
        "--seeds",
        "1",
    ]
    bench.main(
        [
            *common,
            "--second",
            str(models / "anymal_d_rwm_mbpo.safetensors"),
            "--policies",
            "zero",
            "random",
            "--out",
            str(tmp_path / "two"),
        ]
    )
    report = json.loads((tmp_path / "two" / "disagreement.json").read_text())
    (row,), (still, moving) = report["data"], report["imagination"]
    assert row["windows"] == 6 and row["error"] > 0 and row["heads"] > 0 and row["second_model"] > 0
    assert [still["policy"], moving["policy"]] == ["zero", "random"] and still["episodes"] == 18
    assert (
        still["second_model_one_step"] > 0 and moving["heads"] > still["heads"]
    )  # random actions: more to disagree on
    bench.main([*common, "--second", str(models / "anymal_d_rwm.safetensors"), "--out", str(tmp_path / "same")])
    same = json.loads((tmp_path / "same" / "disagreement.json").read_text())
    assert same["data"][0]["second_model"] == 0.0 and same["data"][0]["corr_error_second_model"] is None
    assert same["imagination"] == []
    with pytest.raises(SystemExit):
        bench.main(
            [
                *common,
                "--second",
                str(models / "anymal_d_rwm.safetensors"),
                "--steps",
                "8",
                "--out",
                str(tmp_path / "bad"),
            ]
        )


def test_evaluation_compare_puts_models_side_by_side_on_shared_windows(tmp_path: Path, capsys) -> None:
    """benchmarks/evaluation_compare.py: each model's row per source, the floors once, a PNG; a model compared with
    itself gets the same numbers; a folder without evaluation.json is refused in one line."""
    from rwm_gym.cli import main
    from rwm_gym.data.collect import collect
    from rwm_gym.imagination.core import default_checkpoint
    from rwm_gym.model.checkpoint import save_checkpoint
    from rwm_gym.model.factory import build_model, model_config_for
    from rwm_gym.spec import load_spec

    data = collect("AnymalD-MuJoCo-v0", "zero", 2, tmp_path / "stand.h5", max_steps=40, num_envs=2, progress=False)
    spec = load_spec("anymal_d")
    still = save_checkpoint(tmp_path / "still.safetensors", build_model(model_config_for("no_change", spec)), spec)
    for name, ckpt in (("a", default_checkpoint()), ("b", default_checkpoint()), ("still", still)):
        assert (
            main(
                [
                    "evaluate",
                    "--checkpoint",
                    str(ckpt),
                    "--data",
                    str(data),
                    "--out",
                    str(tmp_path / name),
                    "--history",
                    "8",
                    "--horizons",
                    "4",
                    "16",
                    "--max-windows",
                    "8",
                    "--noise",
                    "--quiet",
                ]
            )
            == 0
        )
    compare = _script("evaluation_compare")
    runs = [f"shipped={tmp_path / 'a'}", f"again={tmp_path / 'b'}", f"no-change model={tmp_path / 'still'}"]
    compare.main([*runs, "--out", str(tmp_path / "cmp")])
    rows = (tmp_path / "cmp.md").read_text().splitlines()
    assert rows[0].startswith("**stand** (2 episodes; windows per horizon: N=4: 8, N=16: 8")
    shipped, again, model, floor = (
        next(r for r in rows if r.startswith(f"| {label} |"))
        for label in ("shipped", "again", "no-change model", "*no change*")
    )
    assert shipped.split("|")[2:] == again.split("|")[2:] and shipped != model
    assert model.split("|")[2:] == floor.split("|")[2:]  # the no-change model is the floor, on the same windows
    assert (tmp_path / "cmp.png").read_bytes()[:4] == b"\x89PNG"
    with pytest.raises(SystemExit):
        compare.main([f"x={tmp_path}", "--out", str(tmp_path / "bad")])
    assert "no evaluation.json" in capsys.readouterr().err
    assert (
        main(
            [
                "evaluate",
                "--checkpoint",
                str(still),
                "--data",
                str(data),
                "--out",
                str(tmp_path / "short"),
                "--history",
                "8",
                "--horizons",
                "4",
                "--max-horizon",
                "8",
                "--max-windows",
                "8",
                "--noise",
                "--quiet",
            ]
        )
        == 0
    )
    with pytest.raises(SystemExit):  # other horizons: other windows, so no shared floor
        compare.main([f"shipped={tmp_path / 'a'}", f"short={tmp_path / 'short'}", "--out", str(tmp_path / "bad")])
    assert "stand: the runs were not evaluated on the same windows" in capsys.readouterr().err


def test_evaluation_compare_refuses_runs_on_other_episodes_of_a_file(tmp_path: Path, capsys) -> None:
    """Two evaluations that left out different repeated episodes of one file have the same counts but other windows."""
    from rwm_gym.cli import main
    from rwm_gym.data.collect import collect
    from rwm_gym.data.dataset import Dataset, write_dataset
    from rwm_gym.model.checkpoint import save_checkpoint
    from rwm_gym.model.factory import build_model, model_config_for
    from rwm_gym.spec import load_spec

    data = collect("AnymalD-MuJoCo-v0", "zero", 3, tmp_path / "stand.h5", max_steps=40, num_envs=3, progress=False)
    spec = load_spec("anymal_d")
    still = save_checkpoint(tmp_path / "still.safetensors", build_model(model_config_for("no_change", spec)), spec)
    episodes = Dataset.load(data)
    for i in (0, 1):  # a "training" file holding episode i of the evaluated file
        write_dataset(tmp_path / f"train{i}.h5", episodes.info, [episodes.episode(i)])
        assert (
            main(
                [
                    "evaluate",
                    "--checkpoint",
                    str(still),
                    "--data",
                    str(data),
                    "--out",
                    str(tmp_path / f"run{i}"),
                    "--training-data",
                    str(tmp_path / f"train{i}.h5"),
                    "--history",
                    "8",
                    "--horizons",
                    "4",
                    "--max-horizon",
                    "4",
                    "--max-windows",
                    "8",
                    "--noise",
                    "--quiet",
                ]
            )
            == 0
        )
    compare = _script("evaluation_compare")
    with pytest.raises(SystemExit):
        compare.main([f"a={tmp_path / 'run0'}", f"b={tmp_path / 'run1'}", "--out", str(tmp_path / "bad")])
    assert "windows, episode_ids" in capsys.readouterr().err
    compare.main([f"a={tmp_path / 'run0'}", f"again={tmp_path / 'run0'}", "--out", str(tmp_path / "same")])
    assert (tmp_path / "same.md").is_file()

"""The examples run end to end on tiny budgets (their real budgets are for users, not CI)."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import pytest
import torch
from script_loader import BENCHMARKS, EXAMPLES, load_script


def load_example(name: str):
    return load_script(EXAMPLES / f"{name}.py", f"example_{name}")


SCRIPTS = sorted([*EXAMPLES.glob("*.py"), *BENCHMARKS.glob("*.py")])


@pytest.mark.parametrize("script", SCRIPTS, ids=[f"{p.parent.name}/{p.name}" for p in SCRIPTS])
def test_every_example_and_benchmark_imports(script: Path):
    """The slow or GPU-only scripts are not run by the default suite; their imports still must resolve (three
    once imported a helper from a module it had left)."""
    module = load_script(script, f"script_{script.parent.name}_{script.stem}")
    assert callable(getattr(module, "main", None)), f"{script.name} has no main()"


def test_cleanrl_ppo_trains_on_the_imagined_vector_env(tmp_path):
    from safetensors.torch import load_file

    example = load_example("cleanrl_ppo")
    args = example.parse_args(
        [
            "--num-envs",
            "4",
            "--num-steps",
            "8",
            "--total-steps",
            "96",
            "--episode-steps",
            "10",
            "--out",
            str(tmp_path / "actor.safetensors"),
        ]
    )
    result = example.main(args)
    assert result["steps"] == 96 and len(result["mean_step_reward"]) == 3
    assert all(math.isfinite(r) for r in result["mean_step_reward"])
    weights = load_file(tmp_path / "actor.safetensors")
    last = max(k for k in weights if k.endswith(".weight"))
    assert weights[last].shape == (12, 128)  # ANYmal D: 12 joint-position actions
    policy = example.load_actor(tmp_path / "actor.safetensors")  # the saved actor acts as the trained one
    obs = torch.randn(5, 48) * 3
    agent = example.Agent(weights["obs_mean"].tolist(), weights["obs_std"].tolist(), 12)
    agent.actor.load_state_dict({k.removeprefix("actor."): v for k, v in weights.items() if k.startswith("actor.")})
    actions = policy(obs.numpy())
    assert actions.shape == (5, 12) and abs(actions).max() <= 1.0
    assert torch.allclose(torch.as_tensor(actions), agent.mean_action(obs))


def test_cleanrl_ppo_adapts_its_learning_rate_to_the_kl(tmp_path):
    """rsl_rl's schedule: every update whose KL is above twice the target divides lr by 1.5, below half multiplies."""
    example = load_example("cleanrl_ppo")
    base = [
        "--num-envs",
        "4",
        "--num-steps",
        "8",
        "--total-steps",
        "96",
        "--episode-steps",
        "10",
        "--learning-rate",
        "1e-3",
        "--out",
        str(tmp_path / "actor.safetensors"),
    ]
    assert example.main(example.parse_args([*base, "--target-kl", "1e-12"]))["lr"] == pytest.approx(1e-3 / 1.5**3)
    assert example.main(example.parse_args([*base, "--target-kl", "100"]))["lr"] == pytest.approx(1e-3 * 1.5**3)
    assert example.main(example.parse_args([*base, "--target-kl", "0"]))["lr"] == 1e-3


def test_cleanrl_ppo_resumes_a_killed_run(tmp_path):
    """A run stopped after 3 updates continues from its resume point to the larger budget (agent, Adam and lr
    restored: its first updates are those of an uninterrupted run), and refuses other settings."""
    example = load_example("cleanrl_ppo")
    base = ["--num-envs", "4", "--num-steps", "8", "--episode-steps", "10", "--save-every", "2"]
    whole = example.main(example.parse_args([*base, "--total-steps", "192", "--out", str(tmp_path / "a.safetensors")]))
    run = ["--run-dir", str(tmp_path / "run"), "--out", str(tmp_path / "b.safetensors")]
    first = example.main(example.parse_args([*base, *run, "--total-steps", "96"]))
    assert first["mean_step_reward"] == whole["mean_step_reward"][:3]
    agent = example.Agent([0.0] * 48, [1.0] * 48, 12)
    adam = torch.optim.Adam(agent.parameters())
    args = example.parse_args([*base, *run, "--total-steps", "96"])
    assert example.load_resume_point(tmp_path / "run" / "resume.safetensors", agent, adam, args)["update"] == 3
    policy = example.load_actor(tmp_path / "b.safetensors")
    obs = torch.randn(3, 48)
    assert torch.equal(agent.mean_action(obs), torch.as_tensor(policy(obs.numpy())))
    assert all(adam.state[p]["exp_avg"].abs().sum() > 0 for p in agent.parameters() if p.requires_grad)
    resumed = example.main(example.parse_args([*base, *run, "--total-steps", "192"]))
    assert resumed["steps"] == 192 and resumed["mean_step_reward"][:3] == first["mean_step_reward"]
    assert len(resumed["mean_step_reward"]) == 6
    with pytest.raises(SystemExit, match="num_steps"):
        example.main(example.parse_args([*base, *run, "--num-steps", "16", "--total-steps", "384"]))


def test_cleanrl_ppo_actor_is_scored_in_physics(tmp_path):
    from rwm_gym.rl.score import score

    example = load_example("cleanrl_ppo")
    example.main(
        example.parse_args(
            [
                "--num-envs",
                "4",
                "--num-steps",
                "8",
                "--total-steps",
                "32",
                "--episode-steps",
                "10",
                "--out",
                str(tmp_path / "actor.safetensors"),
            ]
        )
    )
    evaluation = score(example.load_actor(tmp_path / "actor.safetensors"), seeds=1, steps=5, num_random=0)
    assert evaluation.episodes == 2 and 0.0 <= evaluation.tracking <= 1.0


def test_cleanrl_ppo_takes_the_walking_recipes_settings(tmp_path):
    """The recipe's options reach the env and the loop: a halt below any disagreement ends every imagined episode
    after one step (terminated, so nothing is bootstrapped), and only with the clip are all step rewards >= 0."""
    from rwm_gym.resources import assets_dir

    example = load_example("cleanrl_ppo")
    assert torch.allclose(example.Agent([0.0] * 48, [1.0] * 48, 12, log_std_init=-1.0).log_std, torch.full((12,), -1.0))
    model = assets_dir() / "checkpoints" / "anymal_d_rwm_mbpo.safetensors"
    recipe = [
        "--checkpoint",
        str(model),
        "--num-envs",
        "8",
        "--num-steps",
        "8",
        "--total-steps",
        "64",
        "--uncertainty-penalty",
        "10",
        "--uncertainty-halt",
        "1e-9",
        "--log-std-init",
        "-1",
        "--out",
        str(tmp_path / "actor.safetensors"),
    ]
    clipped = example.main(example.parse_args([*recipe, "--positive-reward-only"]))["mean_step_reward"]
    raw = example.main(example.parse_args(recipe))["mean_step_reward"]
    assert min(clipped) >= 0.0 > min(raw)
    recipe = [*recipe[:-2], "--uncertainty-halt", "0", "--out", str(tmp_path / "actor.safetensors")]  # no u halt
    assert example.main(example.parse_args(recipe))["episodes"] == 0  # 250-step episodes do not end in 64 steps
    halted = example.main(example.parse_args([*recipe, "--torque-halt", "1e-9"]))  # any torque ends an episode
    assert halted["episodes"] == 64


def test_quickstart_trains_from_scratch_in_imagination_scores_in_physics_and_resumes(tmp_path):
    import json
    import os
    import subprocess

    out = tmp_path / "qs"
    tiny = [
        "--timesteps",
        "64",
        "--num-envs",
        "8",
        "--score-seeds",
        "1",
        "--score-steps",
        "20",
        "--no-video",
        "--out",
        str(out),
    ]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    run = subprocess.run(
        [sys.executable, str(EXAMPLES / "quickstart.py"), *tiny], capture_output=True, text=True, env=env, timeout=600
    )
    assert run.returncode == 0, run.stderr[-2000:]
    lines = run.stdout.splitlines()
    assert len(lines) <= 20 and lines[-1].startswith("VERDICT: it does not walk yet")
    assert any(line.startswith("this policy, in physics:  tracking") for line in lines)
    assert any(line.startswith("standing still (floor):   tracking 0.23") for line in lines)
    # the shipped model's whole lineage (docs/concepts/world-model.md), not its last fine-tune's dataset
    assert "physics samples behind the policy: 2,496,757 (7.7 % of N_mf = 32.2 M" in run.stdout
    state = json.loads((out / "run" / "state.json").read_text())
    assert state["timesteps"] >= 64 and (out / "policy.zip").is_file()
    from rwm_gym.resources import assets_dir

    shipped = json.loads((assets_dir() / "policies" / "anymal_d_ppo_quickstart.json").read_text())
    # the quick start's recipe, as its JSON states it (fields added since it was trained at their defaults)
    assert {k: state["ppo"][k] for k in shipped["ppo"]} == {**shipped["ppo"], "num_envs": 8}
    assert not state["ppo"]["symmetry"]
    expected = {k: v for k, v in shipped["env"]["imagination"].items() if v is not None}
    assert state["env"]["imagination"] in (expected, {**expected, "matmul_precision": "bfloat16"})
    # the same command again finds the run finished instead of starting over
    again = subprocess.run(
        [sys.executable, str(EXAMPLES / "quickstart.py"), *tiny], capture_output=True, text=True, env=env, timeout=600
    )
    assert again.returncode == 0, again.stderr[-2000:]
    assert "already has its 64 steps" in again.stdout
    assert json.loads((out / "run" / "state.json").read_text())["timesteps"] == state["timesteps"]


def test_quickstart_robot_go2_trains_in_the_go2_model_from_its_shipped_seed(tmp_path):
    import os
    import subprocess

    tiny = ["--timesteps", "64", "--num-envs", "8", "--score-seeds", "1", "--score-steps", "20", "--no-video"]
    run = subprocess.run(
        [sys.executable, str(EXAMPLES / "quickstart.py"), "--robot", "go2", *tiny, "--out", str(tmp_path / "qs")],
        capture_output=True,
        text=True,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
        timeout=600,
    )
    assert run.returncode == 0, run.stderr[-2000:]
    assert "PPO from scratch in go2_rwm: 8 imagined robots, 64 steps, seed 7," in run.stdout
    # the Go2 model's lineage against the Go2 teacher's N_mf, not ANYmal D's
    assert "physics samples behind the policy: 3,921,261 (7.4 % of N_mf = 53.1 M" in run.stdout
    assert "physics-trained teacher:  tracking 0.837" in run.stdout
    state = json.loads((tmp_path / "qs" / "run" / "state.json").read_text())
    assert state["env"]["checkpoint"].endswith("go2_rwm.safetensors") and state["timesteps"] >= 64


def test_quickstart_refuses_a_recipe_it_cannot_run_in_one_line(tmp_path):
    """--recipe names a shipped from-scratch recipe; anything else (a missing file, an MBPO policy's JSON) stops
    with one line that lists the ones it can run, before any training."""
    import subprocess

    for flag, name in (("--recipe", "no_such_recipe"), ("--recipe", "anymal_d_mbpo_ppo"), ("--robot", "no_such_robot")):
        run = subprocess.run(
            [sys.executable, str(EXAMPLES / "quickstart.py"), flag, name, "--out", str(tmp_path / "qs")],
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert run.returncode == 2 and not (tmp_path / "qs").exists()
        assert f"{flag} {name}: no from-scratch recipe" in run.stderr.splitlines()[-1]
        assert "anymal_d_ppo_quickstart" in run.stderr.splitlines()[-1]


@pytest.mark.slow  # five commands, each a fresh process (about a minute on idle cores)
def test_gpu_pipeline_runs_every_stage_on_the_cpu(tmp_path):
    """The GPU pipeline's logic on tiny budgets with --device cpu (no GPU on CI; the script is written for one)."""
    example = load_example("gpu_pipeline")
    timings = example.main(
        [
            "--device",
            "cpu",
            "--out",
            str(tmp_path),
            "--episodes",
            "4",
            "--episode-steps",
            "80",
            "--num-envs",
            "2",
            "--workers",
            "2",
            "--iterations",
            "4",
            "--batch-size",
            "8",
            "--ppo-timesteps",
            "256",
            "--ppo-envs",
            "8",
            "--no-ppo-eval",
        ]
    )
    assert list(timings["stages"]) == ["collect_gait", "collect_random", "train", "evaluate", "ppo"]
    assert (tmp_path / "rwm.safetensors").is_file() and (tmp_path / "policy.zip").is_file()
    record = json.loads((tmp_path / "timings.json").read_text())
    assert record["stages"].keys() == timings["stages"].keys() and record["machine"]["device"] == "cpu"
    assert record["machine"]["cpu_model"] and record["machine"]["torch_threads"] >= 1 and record["machine"]["torch"]


def test_rsl_rl_example_trains_in_imagination_and_scores_in_physics(tmp_path):
    pytest.importorskip("rsl_rl", reason="rsl-rl-lib is not installed (pip install '.[rsl-rl]')")
    example = load_example("rsl_rl_imagination")
    args = example.parse_args(
        [
            "--num-envs",
            "4",
            "--iterations",
            "1",
            "--episode-steps",
            "10",
            "--log-dir",
            str(tmp_path),
            "--score-steps",
            "10",
        ]
    )
    result = example.main(args)
    assert result["imagined_steps"] == 4 * 24
    assert 0.0 <= result["tracking"] <= 1.0 and 0.0 <= result["floor"] <= 1.0
    assert (tmp_path / "model_0.pt").is_file()  # the runner's own checkpoint


def test_mbpo_samples_counts_the_rows_behind_each_run_against_the_teachers_n_mf(tmp_path, monkeypatch, capsys):
    """Each run's physics samples are its log's plus the `--prior` rows behind its start, as a fraction of the
    shipped teacher's N_mf (its first curve point at tracking >= 0.80 with at most one fall)."""
    import csv
    import json

    module = load_script(BENCHMARKS / "mbpo_samples.py", "bench_mbpo_samples")
    assert module.n_mf(module.MODEL_FREE) == 32_243_712
    run = tmp_path / "run"
    run.mkdir()
    log = [
        {"iteration": 0, "physics_samples": 1000, "tracking": 0.2, "falls": 0},
        {"iteration": 1, "physics_samples": 3000, "tracking": 0.85, "falls": 2},
    ]
    (run / "mbpo.json").write_text(json.dumps({"log": log}))
    monkeypatch.setattr(
        sys, "argv", ["mbpo_samples.py", "--runs", str(run), "--prior", "500", "--out", str(tmp_path / "fig")]
    )
    module.main()
    rows = list(csv.DictReader((tmp_path / "fig.csv").open()))
    assert [int(r["physics_samples"]) for r in rows] == [1500, 3500]
    assert float(rows[1]["fraction_of_n_mf"]) == pytest.approx(3500 / 32_243_712)
    assert (tmp_path / "fig.png").stat().st_size > 0
    assert "best tracking 0.850 (2 falls) at iteration 1, 3,500 physics samples" in capsys.readouterr().out
    monkeypatch.setattr(
        sys, "argv", ["mbpo_samples.py", "--runs", str(run), "--prior", "1", "2", "--out", str(tmp_path / "fig")]
    )
    with pytest.raises(SystemExit):
        module.main()
    # a run whose folder is gone is drawn from the CSV written for it, beside a new one
    monkeypatch.setattr(
        sys,
        "argv",
        [
            "mbpo_samples.py",
            "--runs",
            str(run),
            "--labels",
            "new",
            "--earlier",
            str(tmp_path / "fig.csv"),
            "ru",
            "--out",
            str(tmp_path / "both"),
        ],
    )
    module.main()
    rows = list(csv.DictReader((tmp_path / "both.csv").open()))
    assert [(r["run"], int(r["physics_samples"])) for r in rows] == [
        ("run", 1500),
        ("run", 3500),
        ("new", 1000),
        ("new", 3000),
    ]
    for name in ("B", ""):  # no run, or more than one, named like it
        monkeypatch.setattr(
            sys,
            "argv",
            [
                "mbpo_samples.py",
                "--runs",
                str(run),
                "--earlier",
                str(tmp_path / "both.csv"),
                name,
                "--out",
                str(tmp_path / "x"),
            ],
        )
        with pytest.raises(SystemExit, match=r"no run named|more than one run"):
            module.main()


def test_gap_table_takes_a_version_39_row_for_the_current_version_and_no_other(tmp_path):
    """`--reuse version-39 DIR`: the current settings undo version 40's only change, so a finished row of version 39
    (also one reused there from earlier) is copied with its version kept; a row of version 40 runs again."""
    import argparse

    gap_table = load_script(BENCHMARKS / "gap_table.py", "script_gap_table_reuse")
    args = argparse.Namespace(seed=0, episodes=9, steps=150)
    case = gap_table.CASES["payload_1x"]
    settings = gap_table.settings(args, case)
    for ran_at, reused in ((39, True), (40, False)):
        earlier = tmp_path / f"v{ran_at}.json"
        row = {"case": case.name, "named": [], "settings": {**settings, "version": ran_at}}
        earlier.write_text(json.dumps(row))
        path = tmp_path / f"now{ran_at}.json"
        assert gap_table.reuse_row(earlier, path, args, "version-39") == reused
        assert path.is_file() == reused
    taken = json.loads((tmp_path / "now39.json").read_text())
    assert taken["settings"] == settings and taken["reused_version"] == 39
    assert gap_table.REUSABLE["version-39"]({"settings": {"version": 41}, "reused_version": 39})
    assert gap_table.REUSABLE["version-39"]({"settings": {"version": 39}, "reused_version": 38})  # stood at 39
    assert not gap_table.REUSABLE["version-39"]({"settings": {"version": 40}, "reused_version": 38})


def test_gap_table_oracle_scores_the_simulator_with_the_hidden_effect_set_exactly(tmp_path):
    """`gap_table.py --oracle`: on the case's own measured data, the true simulator removes nearly all of a motor
    strength gap, and what it leaves is sensor noise (not above its own floor)."""
    import argparse

    gap_table = load_script(BENCHMARKS / "gap_table.py", "script_gap_table_oracle")
    case = next(c for c in gap_table.grid() if c.name == "motor_strength_1x")
    row = gap_table.oracle(case, "excitation", argparse.Namespace(seed=0, episodes=4, steps=60), tmp_path)
    assert row["gap_true"] < 0.2 * row["gap_nominal"]
    assert not row["true_rest_above_its_floor"]


def test_gap_table_measures_a_case_on_the_fast_robot_and_compares_like_with_like(tmp_path):
    """`--robots fast`: the case's data come from the package's own physics (the sim env's solver, not a converged
    one), and the fast/converged comparison counts only cases both robots finished."""
    import argparse

    import numpy as np

    from rwm_gym.data.dataset import Dataset

    gap_table = load_script(BENCHMARKS / "gap_table.py", "script_gap_table_robots")
    case = next(c for c in gap_table.grid() if c.name == "payload_1x")
    args = argparse.Namespace(seed=0, episodes=2, steps=20)
    fast, converged = (gap_table.measure(case, "excitation", args, tmp_path, robot) for robot in ("fast", "converged"))
    assert fast.name.startswith("excitation-fast_") and converged.name.startswith("excitation_")
    a, b = Dataset.load(fast), Dataset.load(converged)
    assert not np.allclose(a["state"], b["state"])  # two solvers, two robots
    rows = [
        {"source": "gait", "case": "x", "correct": True},
        {"source": "gait-fast", "case": "x", "correct": False},
        {"source": "gait", "case": "y", "correct": True},  # the fast robot has not run y: left out
    ]
    assert gap_table.fast_vs_converged(rows) == {
        "gait": {"cases": 1, "converged_correct": 1.0, "fast_correct": 0.0, "differ": ["x"]}
    }
    assert "contact_solver_1x" not in {c.name for c in gap_table.grid()}  # no robot hides the simulator's solver
    timed = [{"kind": "single", "wall_s": 120.0}, {"kind": "single", "wall_s": 240.0}, {"kind": "pair", "wall_s": 9e2}]
    assert gap_table.median_minutes(timed) == 4.0 and gap_table.median_minutes(timed[:2]) == 3.0
    assert gap_table.median_minutes([{"kind": "none"}]) is None  # a row reused from before it was timed


def test_gap_table_one_joint_cases_hide_friction_in_that_joint_alone():
    """The one-joint rows: friction at the named joint's index of the per-joint field, nominal in the 11 others, on
    enough episodes for the per-joint scope; one case per (joint, magnitude)."""
    gap_table = load_script(BENCHMARKS / "gap_table.py", "script_gap_table_one_joint")
    cases = {c.name: c for c in gap_table.grid() if c.kind == "joint"}
    expected = {f"friction_{j}_{v:g}" for j, values in gap_table.ONE_JOINT_FRICTION.items() for v in values}
    assert expected | {"friction_LF_KFE_6"} == set(cases)
    joints = list(gap_table.SPEC.actuator.joints)
    for case in cases.values():
        _, _, joint, value = case.per_joint
        (friction,) = gap_table.hidden_physics(case).values()
        assert friction[joints.index(joint)] == value
        assert [f for i, f in enumerate(friction) if i != joints.index(joint)] == [0.0] * (len(joints) - 1)
        assert case.episodes == 12


def test_make_coverage_model_fine_tunes_on_the_policies_episodes_and_resumes(tmp_path):
    """One part per (policy, noise level) from its own seeds in the start model's robot (here the Go2), merged after
    the base; the fine-tune keeps the start model's training settings except budget, lr and seed; the written model
    carries no optimizer state and counts the physics rows behind it; the same command again collects nothing and
    gives the same model."""
    from safetensors.torch import load_file

    from rwm_gym.data.collect import collect
    from rwm_gym.data.dataset import Dataset
    from rwm_gym.model.checkpoint import read_meta
    from rwm_gym.model.config import TrainConfig
    from rwm_gym.model.factory import model_config_for
    from rwm_gym.model.train import train
    from rwm_gym.spec import load_spec

    base = collect("Go2-MuJoCo-v0", "random", 4, tmp_path / "base.h5", seed=0, num_envs=4, max_steps=40, progress=False)
    config = model_config_for("rwm", load_spec("go2"), hidden_size=32, num_layers=1, head_hidden=32)
    start = train(
        base,
        config,
        TrainConfig(history=8, forecast=4, iterations=20, batch_size=16, val_every=20, val_fraction=0.25, lr=1e-3),
        tmp_path / "start.safetensors",
        progress=False,
    ).path
    example = load_example("make_coverage_model")
    out = tmp_path / "cover"
    argv = [
        "--policies",
        "zero",
        "random",
        "--noise",
        "0.0",
        "0.3",
        "--episodes",
        "2",
        "--max-steps",
        "30",
        "--iterations",
        "4",
        "--lr",
        "5e-4",
        "--seed",
        "3",
        "--first-seed",
        "500",
        "--threads",
        "1",
        "--quiet",
        "--base",
        str(base),
        "--checkpoint",
        str(start),
        "--out",
        str(out),
    ]
    model = example.main(argv)

    parts = sorted((out / "own").glob("part_*.h5"))
    assert [Dataset.load(p).info.seed for p in parts] == [500, 600, 700, 800]
    assert {Dataset.load(p).info.env_id for p in parts} == {"Go2-MuJoCo-v0"}  # the start model's robot
    own_rows = sum(Dataset.load(p).num_steps for p in parts)
    assert Dataset.load(out / "buffer.h5").num_steps == Dataset.load(base).num_steps + own_rows
    meta, started = read_meta(model), read_meta(start)
    assert meta.train_config == started.train_config.__class__(
        **{
            **vars(started.train_config),
            "iterations": 4,
            "lr": 5e-4,
            "seed": 3,
            "val_every": 1,
            "checkpoint_every": 100,
            "minutes": 0.0,
            "device": "cpu",
        }
    )
    assert meta.provenance["init_checkpoint"] == str(start) and meta.stats["iterations"] == 4
    rows = meta.extras["physics_rows"]
    assert rows["own"] == own_rows and rows["base"] == Dataset.load(base).num_steps
    assert rows["total"] == rows["start_model"] + own_rows  # the base trained the start model: counted once
    assert not [k for k in load_file(model) if k.startswith(("optim/", "train/"))]
    assert any(k.startswith("optim/") for k in load_file(out / "train.safetensors"))  # the resumable one keeps them

    stamps = [p.stat().st_mtime_ns for p in parts]
    first = load_file(model)
    again = example.main(argv)  # the finished fine-tune is found, not run again
    assert first.keys() == load_file(again).keys()
    assert all(torch.equal(first[k], load_file(again)[k]) for k in first)
    assert read_meta(again).stats["train_loss"] == meta.stats["train_loss"]
    assert [p.stat().st_mtime_ns for p in parts] == stamps
    (out / "own" / "part_1.h5").replace(out / "own" / "part_0.h5")  # a part from another seed is refused
    with pytest.raises(SystemExit, match="is not part 0"):
        example.main(argv)


SIMS = ("nominal", "corrected", "true")


def test_gap_policy_fine_tunes_in_each_simulator_and_scores_on_the_hidden_robot(tmp_path):
    """`gap_policy.py` on tiny budgets, its gap report given: the nominal policy and its three fine-tunes (nominal,
    corrected and true simulator) scored on the robot, the corrected one trained on the report's physics."""
    from rwm_gym.cli import main as rwm_gym

    bench = load_script(BENCHMARKS / "gap_policy.py", "script_gap_policy_chain")
    nominal = tmp_path / "nominal.zip"
    tiny = ["--num-envs", "4", "--n-steps", "16", "--threads", "1", "--no-eval"]
    assert rwm_gym(["ppo", "--in", "physics", "--timesteps", "64", *tiny, "--out", str(nominal)]) == 0
    report = tmp_path / "weak_leg_delay" / "gap"
    report.mkdir(parents=True)
    (report / "corrected_physics.json").write_text(json.dumps({"physics": {"action_delay": 0.02}}))
    named = {"effect": "action_delay", "effects": [{"effect": "action_delay", "scope": "global"}]}
    (report / "report.json").write_text(json.dumps(named))
    argv = ["--out", str(tmp_path), "--robots", "weak_leg_delay", "--policy", str(nominal), "--timesteps", "64"]
    assert bench.main([*argv, "--num-envs", "4", "--n-steps", "16", "--episodes", "2", "--score-steps", "20"]) == 0
    row = json.loads((tmp_path / "summary.json").read_text())["weak_leg_delay"]
    assert set(row["scores"]) == {"before", "nominal", "corrected", "true"}
    assert row["named"] == ["action_delay (global)"]
    scores = {k: v["tracking"] for k, v in row["scores"].items()}
    if scores["true"] > scores["before"]:
        expected = (scores["corrected"] - scores["before"]) / (scores["true"] - scores["before"])
        assert math.isclose(row["recovered"], expected)
    folder = tmp_path / "weak_leg_delay"
    runs = {sim: json.loads((folder / f"run_{sim}" / "state.json").read_text())["env"] for sim in SIMS}
    assert {sim: env.get("physics") for sim, env in runs.items()} == {
        "nominal": None,
        "corrected": {"action_delay": 0.02},
        "true": {**bench.ROBOTS["weak_leg_delay"][1], **bench.CONVERGED},
    }
    assert all(env["init_policy"] == str(nominal) for env in runs.values())
    assert set(row["standing_still"]) == {"tracking", "falls"}  # zero actions on the same robot
    assert "left front leg at half strength" in (tmp_path / "gap_policy.md").read_text()
    assert "| standing still |" in (tmp_path / "gap_policy.md").read_text()


def test_reach_in_imagination_runs_every_stage_and_gives_a_verdict(tmp_path, capsys):
    example = load_example("reach_in_imagination")
    tiny = ["--random-episodes", "2", "--reach-episodes", "1", "--iterations", "3", "--timesteps", "512"]
    assert example.main(["--out", str(tmp_path), *tiny, "--num-envs", "8", "--eval-episodes", "2"]) == 0
    printed = capsys.readouterr().out
    assert "random actions:" in printed and "over 2 episodes of 250 steps" in printed
    assert "VERDICT: it" in printed and (tmp_path / "policy.zip").is_file()
    mix = tmp_path / "mix.h5"
    stamp = mix.stat().st_mtime_ns
    assert example.main(["--out", str(tmp_path), *tiny, "--num-envs", "8", "--eval-episodes", "2"]) == 0
    assert mix.stat().st_mtime_ns == stamp  # a second run reuses what the first one made


def test_gap_table_reuses_only_the_rows_a_versions_change_cannot_reach(tmp_path):
    """`--reuse nothing-named DIR`: a row where step 1 named nothing is copied from the earlier run (keeping the
    version it ran at); one with a named effect, or with other settings than the version, runs again."""
    import argparse
    import json

    gap_table = load_script(BENCHMARKS / "gap_table.py", "script_gap_table_reuse")
    args = argparse.Namespace(seed=0, episodes=9, steps=150)
    case = gap_table.CASES["payload_1x"]
    old = {**gap_table.settings(args, case), "version": 17}
    rows = {
        "none": {"case": case.name, "named": [], "above_floor": False, "settings": old, "episodes": 9},
        "named": {"case": case.name, "named": [["payload", "global"]], "above_floor": True, "settings": old},
        "shorter": {"case": case.name, "named": [], "above_floor": False, "settings": {**old, "steps": 100}},
    }
    for name, row in rows.items():
        (tmp_path / f"{name}.json").write_text(json.dumps(row))
    reused = {
        name: gap_table.reuse_row(tmp_path / f"{name}.json", tmp_path / f"new_{name}.json", args, "nothing-named")
        for name in rows
    }
    assert reused == {"none": True, "named": False, "shorter": False}
    copied = json.loads((tmp_path / "new_none.json").read_text())
    assert copied["settings"] == gap_table.settings(args, case) and copied["reused_version"] == 17
    assert gap_table.reuse_row(tmp_path / "named.json", tmp_path / "x.json", args, "above-floor")
    assert gap_table.reuse_row(tmp_path / "named.json", tmp_path / "y.json", args, "at-most-one-named")
    # one effect of one parameter, what it left at the corrected floor: a step 2 against that floor stops there too
    left = {"named": [["joint_damping", "global"]], "rest_at_floor": True}
    assert gap_table.REUSABLE["one-effect-left-at-its-floor"](left)
    assert not gap_table.REUSABLE["one-effect-left-at-its-floor"]({**left, "rest_at_floor": False})
    assert not gap_table.REUSABLE["one-effect-left-at-its-floor"]({**left, "named": [["payload", "global"]]})
    assert not gap_table.REUSABLE["one-effect-left-at-its-floor"]({**left, "named": [["joint_damping", "leg"]]})
    # a step after a naming that stopped at its floor test fits the candidates now; other stops cannot differ
    below = "held-out gap 0.05 is not above the sensor-noise floor 0.01 (p=0.019 >= 0.01)"
    old_wording = "held-out gap 0.05 is not significantly above the sensor-noise floor 0.01 (ratio 4.3, p=0.019)"
    step_1 = "explains 90% of the gap above the noise floor (p=0.001)"
    reach = gap_table.REUSABLE["cross-fitting-cannot-change"]
    one = {"named": [["payload", "global"]], "reason": f"{step_1}; then: {below}"}
    two = {"named": [["payload", "global"], ["armature", "global"]], "reason": f"named in order: a, b; {below}"}
    assert not reach(one) and not reach(two)
    assert not reach({**one, "reason": f"{step_1}; then: {old_wording}"})  # rows written before the wording changed
    assert reach({**one, "reason": f"{step_1}; then: best candidate armature (global) explains 7%"})
    assert reach({**two, "named": [*two["named"], ["joint_damping", "global"]]})  # no step after the third
    assert reach({"named": [], "reason": below})
    # step 1 called a gap unexplained whose best candidate explained enough and failed only its held-out test
    failed = "best candidate torque_limit (global) explains 89% of the gap above the noise floor (p=0.034; needs 30%"
    assert not reach({"named": [], "verdict": "unexplained", "reason": failed})
    assert reach({"named": [], "verdict": "unexplained", "reason": failed.replace("89%", "21%")})
    # a change to some cases' measured data: those run again on their own data, every other row is taken
    sparse = gap_table.CASES["torque_speed_limit_1x"]
    assert gap_table.settings(args, sparse)["steps"] == gap_table.LONGER_DATA["steps"] > args.steps
    for name, value in (("payload_1x", True), ("torque_speed_limit_1x", False)):
        row = {"case": name, "named": [], "episodes": 9, "settings": {**old, "version": 22}}
        (tmp_path / f"{name}.json").write_text(json.dumps(row))
        taken = gap_table.reuse_row(
            tmp_path / f"{name}.json", tmp_path / f"v23_{name}.json", args, "same-measured-data"
        )
        assert taken == value, name
    # versions 26-28 reach a named row of version 25, an ambiguous one before 27, an `unexplained` one, every one of 24
    settled = gap_table.REUSABLE["neither-ambiguous-nor-unexplained"]
    named = {"named": [["payload", "global"]], "verdict": "payload", "reason": step_1, "settings": {"version": 26}}
    assert settled(named) and settled({**named, "reused_version": 27})
    assert not settled({**named, "settings": {"version": 25}})
    assert settled({**named, "named": [], "verdict": "none", "settings": {"version": 25}})
    assert not settled({**named, "named": [], "verdict": "none", "settings": {"version": 24}})
    ambiguous = {**named, "reason": f"{step_1}; then: ambiguous: armature (9%) and joint_damping (9%) explain"}
    assert not settled(ambiguous) and settled({**ambiguous, "settings": {"version": 27}})
    assert not settled({**named, "named": [], "verdict": "unexplained", "reason": failed})
    # a change to what the solver check gives the sim env's own solver reaches only rows where it took the converged
    kept = gap_table.REUSABLE["own-solver-kept"]
    assert kept({**named, "solver_taken": "own"})
    assert not kept({**named, "solver_taken": "converged"}) and not kept(named)


def test_gap_table_shards_split_the_grid_by_case():
    """Two shards cover every (case, source, robot) job once, each case's rows in one shard, and both data sources
    in each shard (round-robin over jobs gave one shard every excitation row)."""
    gap_table = load_script(BENCHMARKS / "gap_table.py", "script_gap_table_shards")
    cases, robots, sources = gap_table.grid(), ["converged", "fast"], ["excitation", "gait"]
    shards = [gap_table.shard_jobs(cases, robots, sources, f"{i}/2") for i in range(2)]
    everything = [(c.name, s, r) for c in cases for r in robots for s in sources]
    assert sorted(j for shard in shards for j in [(c.name, s, r) for c, s, r in shard]) == sorted(everything)
    for shard in shards:
        assert {s for _, s, _ in shard} == set(sources)
        names = {c.name for c, _, _ in shard}
        assert len(shard) == len(names) * len(robots) * len(sources)
    assert not {c.name for c, _, _ in shards[0]} & {c.name for c, _, _ in shards[1]}

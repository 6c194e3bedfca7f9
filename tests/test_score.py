"""The tracking score: what it rewards, what it refuses, and that a walking policy beats standing still."""

import numpy as np
import pytest

from rwm_gym.rl.evaluate_policy import evaluate_policy, format_table, scoring_commands, tracking_terms
from rwm_gym.rl.score import resolve_policy, zero_policy
from rwm_gym.spec import load_spec

SPEC = load_spec("anymal_d")


def _state(v_xy, wz):
    state = np.zeros((1, SPEC.state_dim))
    s = SPEC.state_slices
    state[0, s["base_lin_vel"].start : s["base_lin_vel"].start + 2] = v_xy
    state[0, s["base_ang_vel"].start + 2] = wz
    return state


def test_perfect_tracking_scores_one_and_errors_cost_as_the_reward_terms_do():
    command = np.array([[0.7, -0.2, 0.4]])
    assert tracking_terms(SPEC, _state([0.7, -0.2], 0.4), command)[0] == pytest.approx(1.0)
    # standing under that command: exp(-0.53/0.25) for xy (weight 1), exp(-0.16/0.25) for yaw (weight 0.5)
    expected = (np.exp(-0.53 / 0.25) + 0.5 * np.exp(-0.16 / 0.25)) / 1.5
    assert tracking_terms(SPEC, _state([0.0, 0.0], 0.0), command)[0] == pytest.approx(expected)


def test_scoring_commands_are_fixed_and_inside_the_spec_ranges():
    commands = np.array(scoring_commands())
    assert len(commands) == 18
    np.testing.assert_array_equal(commands[:2], [[0, 0, 0], [1, 0, 0]])  # standing, 1 m/s forward
    assert (commands >= np.array(SPEC.command.low)).all() and (commands <= np.array(SPEC.command.high)).all()
    np.testing.assert_array_equal(commands, scoring_commands())


def test_a_trotting_policy_scores_above_standing_still_on_forward_commands():
    from rwm_gym.policies.gait import GaitPolicy

    gait = GaitPolicy(SPEC, 2)
    gait.reset(np.arange(2), [np.random.default_rng(k) for k in range(2)])
    commands = [(0.8, 0.0, 0.0), (0.5, 0.0, 0.0)]
    walking = evaluate_policy(gait.act, commands=commands, seeds=[0], steps=150)
    standing = evaluate_policy(zero_policy, commands=commands, seeds=[0], steps=150)
    assert walking.falls == 0 and standing.falls == 0
    assert walking.commands[0].disagreement is None  # physics has no ensemble
    assert "disagreement" not in format_table(walking)
    assert walking.tracking > standing.tracking + 0.1


def test_scripted_names_resolve_to_seeded_policies_one_stream_per_env():
    """'random' is the datasets' correlated random policy: env k draws from generator k, so two resolutions act alike,
    envs differ, and actions stay in [-1, 1]; 'zero' is the floor."""
    obs = np.zeros((4, 48), dtype=np.float32)
    first, second = resolve_policy("random", 4), resolve_policy("random", 4)
    a, b = first(obs), second(obs)
    np.testing.assert_array_equal(a, b)
    assert a.shape == (4, 12) and np.abs(a).max() <= 1.0 and not np.allclose(a[0], a[1])
    assert not np.allclose(first(obs), a)  # the actions move from step to step
    np.testing.assert_array_equal(resolve_policy("zero", 4)(obs), zero_policy(obs))
    assert not resolve_policy("zero", 4)(obs).any()


def test_a_fall_scores_zero_for_the_rest_of_the_episode():
    def flail(obs):  # full-range alternating targets topple the robot
        return np.where(np.arange(12) % 2 == 0, 1.0, -1.0)[None].repeat(len(obs), 0) * np.sign(obs[:, :1] + 1e-3)

    long = evaluate_policy(flail, commands=[(0.0, 0.0, 0.0)], seeds=[0], steps=400)
    if long.falls == 0:
        pytest.skip("this action pattern did not topple the robot")
    short = evaluate_policy(flail, commands=[(0.0, 0.0, 0.0)], seeds=[0], steps=200)
    # every step after the fall adds 0 while the episode length grows: the mean drops
    assert long.tracking < short.tracking


def test_score_command_refuses_bad_input_in_one_line(tmp_path, capsys):
    from rwm_gym.cli import main

    with pytest.raises(SystemExit, match="no such file"):
        main(["score", "--policy", str(tmp_path / "missing.zip"), "--out", str(tmp_path / "out")])
    assert main(["score", "--policy", "zero", "--seeds", "0", "--out", str(tmp_path / "out")]) == 2
    assert "--seeds: must be >= 1" in capsys.readouterr().err


def test_scoring_in_a_world_model_starts_from_the_given_reset_data(tmp_path, capsys):
    """Imagined episodes continue the histories they start from: with zero actions after histories of the trot the
    robot still moves as it comes to rest (about 0.1 m/s over 1.2 s on the default model), after histories of the
    robot standing it stands and never falls, as in physics."""
    from rwm_gym.cli import main
    from rwm_gym.data.collect import collect
    from rwm_gym.imagination.core import default_checkpoint
    from rwm_gym.rl.score import score

    shipped = str(default_checkpoint())
    standing = collect("AnymalD-MuJoCo-v0", "zero", 4, tmp_path / "stand.h5", max_steps=60, num_envs=4, progress=False)
    trotting = collect("AnymalD-MuJoCo-v0", "gait", 4, tmp_path / "trot.h5", max_steps=60, num_envs=4, progress=False)
    options = dict(seeds=2, steps=60, num_random=4, checkpoint=shipped)
    moving, still = score("zero", reset_data=trotting, **options), score("zero", reset_data=standing, **options)
    assert np.hypot(*moving.commands[0].achieved[:2]) > 0.08 > 0.04 > np.hypot(*still.commands[0].achieved[:2])
    assert still.falls == 0
    # inside a model the RWM-U signal comes with each command's score: the ensemble disagreement, small but not zero
    assert all(0 < c.disagreement < 0.5 for c in moving.commands + still.commands)
    assert "| disagreement" in format_table(still).splitlines()[0]
    with pytest.raises(SystemExit, match="--reset-data applies to --checkpoint"):
        main(["score", "--policy", "zero", "--reset-data", str(standing), "--out", str(tmp_path / "out")])
    with pytest.raises(SystemExit, match=r"missing.h5: no such file"):
        main(
            [
                "score",
                "--policy",
                "zero",
                "--checkpoint",
                shipped,
                "--reset-data",
                str(tmp_path / "missing.h5"),
                "--out",
                str(tmp_path / "out"),
            ]
        )


def test_score_without_env_judges_a_policy_on_the_robot_it_names_and_refuses_an_unknown_one(tmp_path):
    """Go2 and ANYmal D policies have the same sizes and observation scale: the zip names its task, so `rwm-gym
    score` without --env judges it on its own robot."""
    import json

    from rwm_gym.cli import main
    from rwm_gym.policy_zip import load_policy
    from rwm_gym.resources import assets_dir, specs_dir
    from rwm_gym.rl.policy_file import save_policy
    from rwm_gym.rl.ppo import trained_task

    robots = sorted((p.stem for p in specs_dir().glob("*.toml")), key=len, reverse=True)
    for shipped in (assets_dir() / "policies").glob("*.zip"):  # each names the robot its file name starts with
        robot = next(name for name in robots if shipped.name.startswith(name + "_"))
        assert trained_task(load_policy(shipped)) == load_spec(robot).physics_env_id, shipped.name
    go2 = assets_dir() / "policies" / "go2_ppo_quickstart.zip"
    assert main(["score", "--policy", str(go2), "--out", str(tmp_path / "s"), "--seeds", "1", "--steps", "5"]) == 0
    assert json.loads((tmp_path / "s" / "score.json").read_text())["task"] == "Go2"
    other = load_policy(go2)
    other.policy_kwargs["features_extractor_kwargs"]["task"] = "MyRobot-MuJoCo-v0"  # a robot of a user's own spec
    save_policy(other, tmp_path / "own.zip")
    with pytest.raises(SystemExit, match="made for MyRobot-MuJoCo-v0, which is not a registered physics env"):
        main(["score", "--policy", str(tmp_path / "own.zip"), "--out", str(tmp_path / "o")])
    assert not (tmp_path / "o" / "score.json").exists()


FORWARD = (1.0, 0.0, 0.0)


@pytest.mark.parametrize(
    ("name", "spec", "command"),
    [
        ("anymal_d_ppo_physics", "anymal_d", FORWARD),
        ("anymal_d_mbpo_ppo", "anymal_d", FORWARD),
        ("anymal_d_mbpo_ppo_random_data", "anymal_d", FORWARD),
        ("anymal_d_ppo_imagination", "anymal_d", FORWARD),
        ("anymal_d_ppo_quickstart", "anymal_d", FORWARD),
        # the Go2 teacher's own weakest commands are straight ahead; leftward is what its mirrored clone taught it
        ("go2_ppo_physics", "go2", (0.0, 0.5, 0.0)),
    ],
)
def test_shipped_policies_are_small_and_walk_as_their_json_says(name, spec, command):
    """Each shipped policy is under 1 MiB, carries no training-env state, and walks at the command in physics on a
    short episode without falling; its JSON's score sits above the zero-action floor it states."""
    import json

    from stable_baselines3 import PPO

    from rwm_gym.resources import assets_dir

    path = assets_dir() / "policies" / f"{name}.zip"
    meta = json.loads(path.with_suffix(".json").read_text())
    assert path.stat().st_size < 2**20
    assert PPO.load(path, device="cpu")._last_obs is None
    assert meta["score"]["tracking"] > meta["score"]["floor"]["tracking"] + 0.4
    walk = evaluate_policy(str(path), commands=[command], seeds=[0], steps=150, spec=spec)
    assert walk.falls == 0 and walk.tracking > 0.6


@pytest.mark.parametrize("name", ["anymal_d_ppo_imagination", "anymal_d_ppo_quickstart"])
def test_shipped_imagination_policy_names_its_seeds_and_a_shipped_world_model(name):
    """A from-scratch policy's JSON records every seed of its recipe (the shipped one is the best by physics score,
    or for the quick start its default seed 0; each curve ends at that seed's final score) and of the other measured
    recipes, and its world model ships with the reset windows it names."""
    import json

    from rwm_gym.model.checkpoint import read_meta
    from rwm_gym.resources import assets_dir, shipped_file

    meta = json.loads((assets_dir() / "policies" / f"{name}.json").read_text())
    seeds = {run["seed"]: run for run in meta["seeds"]}
    shipped = 0 if name == "anymal_d_ppo_quickstart" else max(seeds, key=lambda s: seeds[s]["tracking"])
    assert len(seeds) >= 3 and meta["seed"] == shipped
    assert seeds[meta["seed"]]["tracking"] == meta["score"]["tracking"]
    others = meta.get("other_recipes", [])
    for run in [*seeds.values(), *(run for other in others for run in other["seeds"])]:
        assert run["curve"][-1]["timesteps"] == run["imagined_steps"]
        assert run["curve"][-1]["falls"] == run["falls"]
    checkpoint = shipped_file(meta["world_model"]["checkpoint"])
    reset = checkpoint.parent / read_meta(checkpoint).extras["reset_data"]
    assert reset.is_file() and meta["env"]["checkpoint"] == meta["world_model"]["checkpoint"]
    with pytest.raises(ValueError, match="not a path under assets/ or envs/"):
        shipped_file("checkpoints/anymal_d_rwm_mbpo.safetensors")


@pytest.mark.parametrize("name", ["anymal_d_ppo_imagination", "anymal_d_ppo_quickstart"])
def test_the_quick_start_passes_the_shipped_recipe_to_rwm_gym_ppo_as_options_it_knows(name):
    """Every option `ppo_options` reads from a recipe JSON the quick start runs is one `rwm-gym ppo` parses to the
    JSON's value: each PPO setting the JSON states (num_envs aside: --num-envs decides), also where it differs from
    PPO's default, and none it does not state (the anneal of a recipe older than it stays unset)."""
    import argparse
    import json

    from script_loader import EXAMPLES, load_script

    from rwm_gym.commands.ppo import add_arguments
    from rwm_gym.resources import assets_dir

    quickstart = load_script(EXAMPLES / "quickstart.py", "example_quickstart")
    meta = json.loads((assets_dir() / "policies" / f"{name}.json").read_text())
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    for anneal in (0.25, 0.0, None):
        changed = {"lr_anneal_fraction": anneal, "n_epochs": 3, "positive_reward_only": False}
        ppo = {k: v for k, v in {**meta["ppo"], **changed}.items() if v is not None}
        args = parser.parse_args(quickstart.ppo_options({**meta, "ppo": ppo}))
        assert args.lr_anneal_fraction == anneal
        for option, value in meta["env"]["imagination"].items():
            assert getattr(args, option) == value, option
        for option, value in ppo.items():
            if option != "num_envs":
                assert getattr(args, option) == value, option


def _numbers(value, path=""):
    """The leaves of a JSON report by path."""
    if isinstance(value, dict):
        return {k: v for key, item in value.items() for k, v in _numbers(item, f"{path}/{key}").items()}
    if isinstance(value, list):
        return {k: v for i, item in enumerate(value) for k, v in _numbers(item, f"{path}/{i}").items()}
    return {path: value}


@pytest.mark.parametrize("policy", ["gait", "assets/policies/anymal_d_ppo_physics.zip"])
def test_two_workers_give_the_figures_of_one(tmp_path, policy):
    """`--workers 2` splits the episodes over two processes; the same seeds give the same figures: exactly for a
    scripted policy, and for an SB3 policy up to the float rounding of a network acting on a smaller batch."""
    import json
    from pathlib import Path

    from rwm_gym.cli import main

    root = Path(__file__).resolve().parents[1]
    policy = policy if policy == "gait" else str(root / policy)
    reports = []
    for workers in (1, 2):
        out = tmp_path / f"workers_{workers}"
        command = ["score", "--policy", policy, "--out", str(out), "--seeds", "2", "--steps", "6", "--commands", "1"]
        assert main([*command, "--workers", str(workers)]) == 0
        report = json.loads((out / "score.json").read_text())
        for evaluation in (report["evaluation"], report["floor_evaluation"]):
            evaluation.pop("wall_s")
        reports.append(_numbers(report))
    assert reports[0]["/episodes"] == 6  # standing, 1 m/s forward and one drawn command, two seeds each
    if policy == "gait":
        assert reports[0] == reports[1]
    else:
        assert reports[0].keys() == reports[1].keys()
        for key, value in reports[0].items():
            assert reports[1][key] == (pytest.approx(value, rel=1e-6, abs=1e-9) if isinstance(value, float) else value)

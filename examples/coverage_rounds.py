"""Coverage rounds: teach a world model the states its own from-scratch policies exploit, one round at a time.

    python examples/coverage_rounds.py --checkpoint runs/go2_mbpo/model_8.safetensors --base base.h5 \\
        --policies a.zip b.zip c.zip --reset-data reset.h5 --out runs/go2_cover --rounds 6 --threads 1

A policy trained from scratch inside a world model finds where the model is wrong; the coverage step
(`examples/make_coverage_model.py`) collects that policy's physics episodes and fine-tunes the model on them; a fresh
policy in the fine-tuned model then finds the next gap. Round k:

1. fine-tunes model k-1 (round 1: --checkpoint) on buffer k-1 (round 1: --base) plus the physics episodes of the
   round's policies (round 1: --policies), collection seeds from 80000 + 1000 k;
2. trains a fresh policy from scratch in model k with the quick start's recipe (`rwm-gym ppo --in imagination` with
   `examples/quickstart.py`'s options, seed k, and one more per --extra-seeds) from the --reset-data windows;
3. scores each in physics on the model's own task (`rwm-gym score`) and appends a row to OUT/rounds.json;
4. hands round k+1 these policies and their PPO snapshots nearest 50 % and 75 % of the budget.

It stops after --rounds rounds, or at the first round where a policy walks (tracking >= 0.80 with at most 2 falls in
54, `quickstart.WALKS`) unless --keep-going. It prints one line per round and policy with the score.

Each round writes OUT/round_k/: make_coverage_model's files (own/part_<i>.h5, buffer.h5, train.safetensors,
model.safetensors), ppo/ (the PPO run folder with snapshots/step_N.zip, policy.zip and its report policy.json),
ppo/score/ (score.json, score.md, score.png), ppo_s<seed>/ the same for each extra seed, and timings.json (each
stage's command, wall seconds and load average after it, `examples/timed_stages.py`). A row of OUT/rounds.json holds
the round's model, the physics rows behind it, seed k's policy's tracking and falls beside the zero-action floor,
every seed's in `runs`, and the stages' wall seconds and load averages. The same command resumes after a kill: a
finished step is skipped, the fine-tune and PPO continue from their resume points.
"""

from __future__ import annotations

import json
import shlex
import sys
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))  # sibling scripts: the coverage step, the quick start's recipe
import make_coverage_model
from quickstart import default_precision, from_scratch, ppo_options, score_text, walking
from timed_stages import cli_stage, timed

from rwm_gym.atomic import write_json
from rwm_gym.model.checkpoint import CheckpointMeta, read_meta
from rwm_gym.options import option, parse_dataclass_args
from rwm_gym.resources import assets_dir
from rwm_gym.rl.training_run import TrainingRun

QUICKSTART_RECIPE = assets_dir() / "policies" / "anymal_d_ppo_quickstart.json"

SNAPSHOT_FRACTIONS = (0.5, 0.75)
"""Where in a round's PPO budget the snapshots handed to the next round stand, beside its final policy."""


@dataclass(frozen=True, kw_only=True)
class Options:
    """Coverage rounds: fine-tune a world model on the physics episodes of policies trained from scratch in it, train
    a fresh policy in the new model, score it in physics; repeat."""

    checkpoint: Path
    """the world model round 1 fine-tunes"""
    base: Path
    """round 1's buffer: the data the checkpoint was trained on, or a base mix (examples/make_base_mix.py)"""
    policies: tuple[str, ...] = option(nargs="+")
    """SB3 zips trained from scratch in --checkpoint (or 'random', 'zero', 'gait') whose physics episodes round 1
    learns"""
    reset_data: Path
    """real history windows every round's imagined episodes start from (rwm_gym.imagination.reset_data)"""
    out: Path
    """folder of the rounds (OUT/round_k) and of rounds.json"""
    rounds: int = option(6, ge=1)
    """rounds at most"""
    keep_going: bool = False
    """run every round, also after one whose policy walks"""
    episodes: int = option(64, ge=1, le=100)
    """physics episodes per policy and action-noise level"""
    max_steps: int = option(400, ge=1)
    """cap on a collected episode's policy steps"""
    iterations: int = option(1500, ge=1)
    """fine-tuning steps per round"""
    mirror: bool = False
    """fine-tune on mirrored windows too (`rwm-gym train --mirror`: a robot whose model is left-right symmetric)"""
    recipe: Path | None = None
    """recipe JSON of PPO in imagination (default: assets/policies/anymal_d_ppo_quickstart.json, the quick start's)"""
    timesteps: int | None = option(None, ge=1)
    """imagined steps of each round's PPO (default: the recipe's)"""
    num_envs: int | None = option(None, ge=1)
    """imagined robots stepped together (default: the recipe's)"""
    score_seeds: int = option(3, ge=1)
    """physics episodes per scoring command"""
    score_steps: int | None = option(None, ge=1)
    """policy steps per scoring episode (default: the task's, 20 s)"""
    score_commands: int = option(16, ge=0)
    """random commands in the scoring set, beside standing and 1 m/s forward"""
    extra_seeds: tuple[int, ...] = option((), nargs="*")
    """PPO seeds trained in every round besides seed k (OUT/round_k/ppo_s<seed>); the next round collects them all"""
    threads: int = option(2, ge=1)
    """torch CPU threads (the same --threads gives the same fine-tuned models)"""
    device: str = "cpu"
    """where PPO and the world model run in imagination (cuda on a GPU); the fine-tune runs on the CPU"""


def ppo_finished(run: Path, timesteps: int) -> bool:
    """Whether the PPO run folder `run` has its `timesteps` and wrote policy.zip's report."""
    return (run / "policy.json").is_file() and TrainingRun(run).state().get("timesteps", 0) >= timesteps


def next_policies(run: Path, timesteps: int) -> list[str]:
    """The PPO run's snapshots nearest `SNAPSHOT_FRACTIONS` of its `timesteps`, then its final policy (each once)."""
    snapshots = TrainingRun(run).snapshot_files()
    nearest = [min(snapshots, key=lambda p: abs(int(p.stem.split("_")[1]) - f * timesteps)) for f in SNAPSHOT_FRACTIONS]
    return list(dict.fromkeys(str(p) for p in [*nearest, run / "policy.zip"]))


def run_round(
    options: Options, k: int, start: Path, buffer: Path, policies: list[str], recipe: dict, timesteps: int
) -> dict:
    """Round k: fine-tune `start` on `buffer` and the physics episodes of `policies`, train PPO for `timesteps` in
    the new model with each of the round's seeds and score each, every stage skipped where its files are complete;
    returns the round's row."""
    folder = options.out / f"round_{k}"
    folder.mkdir(parents=True, exist_ok=True)
    record = folder / "timings.json"
    timings = json.loads(record.read_text()) if record.is_file() else {"stages": {}}
    model = folder / "model.safetensors"
    if not model.is_file():
        argv = [
            *("--checkpoint", str(start), "--base", str(buffer), "--out", str(folder), "--policies", *policies),
            *("--episodes", str(options.episodes), "--max-steps", str(options.max_steps)),
            *("--iterations", str(options.iterations), "--threads", str(options.threads)),
            *("--first-seed", str(80_000 + 1000 * k), "--quiet"),
            *(("--mirror",) if options.mirror else ()),
        ]
        what = shlex.join(["python", "examples/make_coverage_model.py", *argv])
        timed("fine_tune", what, lambda: make_coverage_model.main(argv), timings, record)
    meta = read_meta(model)
    runs = [
        train_and_score(options, run_dir(folder, seed, k), seed, model, meta, recipe, timesteps, timings, record)
        for seed in seeds(options, k)
    ]
    stages = timings["stages"]
    first = runs[0]
    return {
        "round": k,
        "model": str(model),
        "physics_rows": meta.extras["physics_rows"],
        "policies": meta.extras["policies"],
        "policy": first["policy"],
        "timesteps": TrainingRun(Path(first["policy"]).parent).state()["timesteps"],
        **{key: first[key] for key in ("tracking", "falls", "episodes", "floor")},
        "runs": runs,
        "wall_s": {name: stage["wall_s"] for name, stage in stages.items()},
        "loadavg": {name: list(stage["loadavg_after"]) for name, stage in stages.items()},
    }


def seeds(options: Options, k: int) -> list[int]:
    """Round k's PPO seeds: k, then --extra-seeds (each once)."""
    return list(dict.fromkeys([k, *options.extra_seeds]))


def run_dir(folder: Path, seed: int, k: int) -> Path:
    """The PPO run folder of `seed` in round k's `folder`: ppo/ for seed k, ppo_s<seed>/ for an extra seed."""
    return folder / ("ppo" if seed == k else f"ppo_s{seed}")


def train_and_score(
    options: Options,
    run: Path,
    seed: int,
    model: Path,
    meta: CheckpointMeta,
    recipe: dict,
    timesteps: int,
    timings: dict,
    record: Path,
) -> dict:
    """PPO from scratch in `model` with `seed`, then its physics score, each skipped where complete; the run's row."""
    name = run.name.replace("ppo", "")  # "" for seed k, "_s<seed>" for an extra seed: the stages' names
    if not ppo_finished(run, timesteps):
        cli_stage(
            f"ppo{name}",
            [
                *("ppo", "--in", "imagination", *ppo_options(recipe, model), "--reset-data", str(options.reset_data)),
                *("--num-envs", str(options.num_envs or recipe["ppo"]["num_envs"]), "--timesteps", str(timesteps)),
                *("--matmul-precision", default_precision(options.device, meta.model_config.kind)),
                *("--run-dir", str(run), "--save-every", "5", "--snapshot-every", "24", "--device", options.device),
                *("--threads", str(options.threads), "--seed", str(seed), "--no-eval"),
                *("--out", str(run / "policy.zip")),
            ],
            timings,
            record,
        )
    scored = run / "score"
    if not (scored / "score.json").is_file():
        cli_stage(
            f"score{name}",
            [
                *("score", "--policy", str(run / "policy.zip"), "--env", meta.spec.physics_env_id),
                *("--seeds", str(options.score_seeds), "--commands", str(options.score_commands)),
                *(["--steps", str(options.score_steps)] if options.score_steps else []),
                *("--out", str(scored), "--overwrite"),
            ],
            timings,
            record,
        )
    report = json.loads((scored / "score.json").read_text())
    return {
        "seed": seed,
        "policy": str(run / "policy.zip"),
        **{key: report[key] for key in ("tracking", "falls", "episodes", "floor")},
    }


def main(argv: list[str] | None = None) -> list[dict]:
    options = parse_dataclass_args(Options, argv)
    recipe_file = options.recipe or QUICKSTART_RECIPE
    for given in (options.checkpoint, options.base, options.reset_data, recipe_file):
        if not given.is_file():
            raise SystemExit(f"coverage_rounds: {given}: no such file")
    recipe = json.loads(recipe_file.read_text())
    if not from_scratch(recipe):
        raise SystemExit(f"coverage_rounds: --recipe {recipe_file}: not a recipe of PPO from scratch in imagination")
    timesteps = options.timesteps or recipe["imagined_steps"]
    table = options.out / "rounds.json"
    rows = json.loads(table.read_text()) if table.is_file() else []
    model, buffer, policies = options.checkpoint, options.base, list(options.policies)
    for k in range(1, options.rounds + 1):
        if k > len(rows):
            rows.append(run_round(options, k, model, buffer, policies, recipe, timesteps))
            write_json(table, rows)
        row = rows[k - 1]
        runs = row["runs"]
        for run in runs:
            verdict = "walks" if walking(run["tracking"], run["falls"]) else "does not walk"
            print(
                f"round {k}, seed {run['seed']}: {score_text(run['tracking'], run['falls'], run['episodes'])} (floor "
                f"{run['floor']['tracking']:.3f}), {verdict}; {row['physics_rows']['total']:,} physics rows behind "
                f"{row['model']}",
                flush=True,
            )
        if any(walking(run["tracking"], run["falls"]) for run in runs) and not options.keep_going:
            break
        folder = options.out / f"round_{k}"
        model, buffer = folder / "model.safetensors", folder / "buffer.h5"
        policies = [p for seed in seeds(options, k) for p in next_policies(run_dir(folder, seed, k), timesteps)]
    return rows


if __name__ == "__main__":
    main()

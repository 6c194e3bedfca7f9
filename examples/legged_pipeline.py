"""A legged robot from nothing to a policy learnt in imagination, one command: physics teacher -> data -> world model
-> evaluation -> PPO in imagination -> tracking scores, each stage the `rwm-gym` command a user would type, printed
as it runs and timed (run in this process: torch and MuJoCo are imported once). Run from the repository root:

    python examples/legged_pipeline.py                                  # the Unitree G1, legs only, on a GPU machine
    python examples/legged_pipeline.py --env Go2-MuJoCo-v0 --out go2_pipeline   # any legged task: id or spec file

Stages (OUT is --out):
1. teacher: `rwm-gym ppo --in physics --run-dir OUT/teacher --record-every 32`, model-free PPO in physics with the Go2
   teacher's settings (4096 envs x 24 steps); every 32nd env's episodes go to OUT/teacher/experience/part_*.h5.
2. data: `rwm-gym collect --policy random` episodes merged with the teacher's experience into OUT/data/train.h5
   (`merge_datasets`), reset windows for imagination cut from the teacher's experience (`make_reset_data`), and
   held-out episodes of the final teacher (`rwm-gym collect --policy OUT/teacher/final.zip --seed 50000`).
3. model: `rwm-gym train --model rwm --ensemble-size 5` (five heads: the recipe's uncertainty penalty reads them).
4. evaluate: `rwm-gym evaluate --horizons 8 32 100` on the held-out episodes (RWM against no change).
5. imagination: `rwm-gym ppo --in imagination` with the quick start's recipe (assets/policies/
   anymal_d_ppo_quickstart.json: its PPO and imagination settings) from the reset windows; no physics sample.
6. score: `rwm-gym score --env ENV` of the teacher and of the imagination policy (18 commands x 3 seeds x 20 s).

The default budget is a GPU machine's (`--device auto`: cuda where torch sees one): a 100 M-step teacher on 4096
envs (its physics on the CPU cores), a 20,000-iteration world model (batch 1024), 20 M imagined steps on 4096 robots.
It has not been timed on a GPU. On a CPU the same budgets take many hours: the teacher's physics alone is at least 5 h
on 2 cores (the G1 legs step about 3,000 times a second on one core, a third of ANYmal D's rate, in
`benchmarks/robots.py`; an estimate, not a run). Pass smaller budgets there (--teacher-steps, --train-cpu-minutes).

Writes OUT/timings.json atomically after every stage: per stage the command, its wall seconds and the load average
after it; the machine of the latest run (`timed_stages.machine`). Running the command again resumes: a stage whose
outputs are complete is skipped (its earlier timing kept), the PPO runs continue in their run folders, the world
model with --resume; a stage that ran again makes the stages that read its outputs run anew.
"""

from __future__ import annotations

import json
import os
import shutil
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).parent))  # sibling scripts: the stage record, the quick start's recipe
from quickstart import default_precision, ppo_options
from timed_stages import cli_stage, machine, timed

from rwm_gym.data.dataset import Dataset, merge_datasets
from rwm_gym.imagination.reset_data import make_reset_data
from rwm_gym.model.checkpoint import read_meta
from rwm_gym.options import option, parse_dataclass_args
from rwm_gym.resources import assets_dir

STAGES = (
    "teacher",
    "collect_random",
    "merge",
    "collect_heldout",
    "train",
    "evaluate",
    "imagination",
    "score_teacher",
    "score_imagination",
)
"""The stages in the order they run; `READS` says whose outputs each one reads."""

READS = {
    "merge": ("teacher", "collect_random"),
    "collect_heldout": ("teacher",),
    "train": ("merge",),
    "evaluate": ("train", "collect_heldout"),
    "imagination": ("train", "merge"),
    "score_teacher": ("teacher",),
    "score_imagination": ("imagination",),
}


@dataclass(frozen=True)
class Options:
    """Teacher, data, world model, evaluation, PPO in imagination and scores of one legged task, every stage timed."""

    env: str = "envs/g1_legs.toml"
    """The legged task: a physics env id (e.g. Go2-MuJoCo-v0) or a task spec file."""
    out: str = "legged_pipeline"
    """Folder of every stage's output and timings.json."""
    device: str = "auto"
    """torch device of every stage (auto: cuda where torch sees a GPU, else cpu)."""
    seed: int = 0
    teacher_steps: int = option(100_000_000, ge=1)
    """Physics steps of the PPO teacher."""
    teacher_envs: int = option(4096, ge=1)
    """Physics envs the teacher steps together."""
    record_every: int = option(32, ge=1)
    """Every N-th teacher env's episodes are recorded as world-model data."""
    random_episodes: int = option(256, ge=1)
    """Episodes of random actions in the training data."""
    heldout_episodes: int = option(32, ge=1)
    """Held-out episodes of the final teacher the world model is evaluated on."""
    episode_steps: int | None = option(None, ge=1)
    """Cap on the length of collected episodes (default: the task's episode)."""
    collect_envs: int = option(32, ge=1)
    """Simulations per collection and scoring worker."""
    workers: int = option(0, ge=0)
    """Collection and scoring workers (0: one per CPU core)."""
    heldout_seed: int = 50000
    """First seed of the held-out episodes (far from the teacher's and the random episodes')."""
    train_iterations: int = option(20000, ge=1)
    """Gradient steps of the world model."""
    train_cpu_minutes: float | None = option(None, gt=0)
    """Budget of the world model in CPU minutes, in place of --train-iterations."""
    batch_size: int = option(1024, ge=1)
    """Training windows per gradient step."""
    recipe: str = "anymal_d_ppo_quickstart"
    """Recipe in assets/policies whose PPO and imagination settings the policy in imagination trains with."""
    imagined_steps: int = option(20_000_000, ge=1)
    """Imagined steps of PPO in the world model."""
    imagined_envs: int = option(4096, ge=1)
    """Imagined robots stepped together."""
    score_seeds: int = option(3, ge=1)
    """Physics episodes per scoring command."""
    score_steps: int | None = option(None, ge=1)
    """Policy steps per scoring episode (default: the task's, 20 s)."""
    score_commands: int = option(16, ge=0)
    """Random commands in the scoring set, beside standing and 1 m/s forward."""


def ppo_done(run_dir: Path, steps: int) -> bool:
    """Whether a `rwm-gym ppo --run-dir` run has its `steps` and wrote its final policy."""
    state = run_dir / "state.json"
    finished = state.is_file() and (run_dir / "final.json").is_file()
    return finished and json.loads(state.read_text())["timesteps"] >= steps


def model_done(checkpoint: Path, options: Options) -> bool:
    """Whether the checkpoint's run has spent its budget (iterations, or CPU minutes)."""
    if not checkpoint.is_file():
        return False
    stats = read_meta(checkpoint).stats
    if options.train_cpu_minutes is not None:
        return stats["wall_s"] >= 60 * options.train_cpu_minutes
    return stats["iterations"] >= options.train_iterations


def experience_parts(run_dir: Path) -> list[Path]:
    """The teacher's experience files that hold episodes (a run resumed when already finished adds an empty one)."""
    return [p for p in sorted((run_dir / "experience").glob("part_*.h5")) if Dataset.load(p).num_episodes]


def main(argv: list[str] | None = None) -> dict:
    options = parse_dataclass_args(Options, argv)
    device = options.device if options.device != "auto" else "cuda" if torch.cuda.is_available() else "cpu"
    out = Path(options.out)
    (out / "data").mkdir(parents=True, exist_ok=True)
    record = out / "timings.json"
    earlier = json.loads(record.read_text())["stages"] if record.is_file() else {}
    timings = {"options": asdict(options), "machine": machine(device), "stages": earlier}
    workers = str(options.workers or os.cpu_count() or 1)
    capped = [] if options.episode_steps is None else ["--max-steps", str(options.episode_steps)]
    ran: set[str] = set()

    def needed(name: str, done: bool) -> bool:
        """Whether stage `name` runs: its outputs are incomplete or a stage whose outputs it reads ran."""
        if done and not ran & set(READS.get(name, ())):
            print(f"[{name}] done, skipped", flush=True)
            return False
        ran.add(name)
        return True

    def run(name: str, *args: str) -> None:
        cli_stage(name, list(args), timings, record)

    teacher, teacher_policy = out / "teacher", out / "teacher" / "final.zip"
    if needed("teacher", ppo_done(teacher, options.teacher_steps)):
        run(
            "teacher",
            *("ppo", "--in", "physics", "--env", options.env, "--num-envs", str(options.teacher_envs)),
            *("--n-steps", "24", "--timesteps", str(options.teacher_steps), "--run-dir", str(teacher)),
            *("--save-every", "4", "--snapshot-every", "8", "--record-every", str(options.record_every)),
            *("--device", device, "--seed", str(options.seed), "--no-eval", "--out", str(teacher_policy)),
        )
    data = {name: out / "data" / f"{name}.h5" for name in ("random", "train", "reset", "heldout")}
    if needed("collect_random", data["random"].is_file()):
        run(
            "collect_random",
            *("collect", "--env", options.env, "--policy", "random", "--episodes", str(options.random_episodes)),
            *("--num-envs", str(options.collect_envs), "--workers", workers, *capped),
            *("--seed", str(options.seed + 1), "--out", str(data["random"]), "--overwrite"),
        )
    if needed("merge", data["train"].is_file() and data["reset"].is_file()):
        parts = experience_parts(teacher)
        if not parts:
            raise SystemExit(f"{teacher}/experience: no finished episode recorded; give the teacher more steps")

        def merge() -> None:
            merge_datasets([*parts, data["random"]], data["train"])
            make_reset_data(parts[-1], data["reset"], seed=options.seed)

        what = f"merge_datasets({[str(p) for p in [*parts, data['random']]]}, {str(data['train'])!r}); "
        timed("merge", what + f"make_reset_data({str(parts[-1])!r}, {str(data['reset'])!r})", merge, timings, record)
    if needed("collect_heldout", data["heldout"].is_file()):
        run(
            "collect_heldout",
            *("collect", "--env", options.env, "--policy", str(teacher_policy)),
            *("--episodes", str(options.heldout_episodes), "--num-envs", str(options.collect_envs)),
            *("--workers", workers, *capped, "--seed", str(options.heldout_seed)),
            *("--out", str(data["heldout"]), "--overwrite"),
        )
    checkpoint = out / "rwm.safetensors"
    if needed("train", model_done(checkpoint, options)):
        fresh = bool(ran & set(READS["train"])) or not checkpoint.is_file()
        budget = ["--iterations", str(options.train_iterations)]
        if options.train_cpu_minutes is not None:
            budget = ["--cpu-minutes", str(options.train_cpu_minutes)]
        run(
            "train",
            *("train", "--model", "rwm", "--ensemble-size", "5", "--data", str(data["train"]), *budget),
            *("--batch-size", str(options.batch_size), "--device", device, "--seed", str(options.seed)),
            *("--out", str(checkpoint), "--quiet", "--overwrite" if fresh else "--resume"),
        )
    evaluation = out / "evaluation"
    if needed("evaluate", (evaluation / "evaluation.json").is_file()):
        run(
            "evaluate",
            *("evaluate", "--checkpoint", str(checkpoint), "--data", str(data["heldout"])),
            *("--horizons", "8", "32", "100", "--device", device, "--out", str(evaluation), "--quiet", "--overwrite"),
        )
    imagination = out / "imagination"
    if needed("imagination", ppo_done(imagination, options.imagined_steps)):
        if ran & set(READS["imagination"]):
            shutil.rmtree(imagination, ignore_errors=True)  # a run in the earlier model would resume
        recipe = json.loads((assets_dir() / "policies" / f"{options.recipe}.json").read_text())
        run(
            "imagination",
            *("ppo", "--in", "imagination", *ppo_options(recipe, checkpoint), "--reset-data", str(data["reset"])),
            *("--num-envs", str(options.imagined_envs), "--timesteps", str(options.imagined_steps)),
            *("--matmul-precision", default_precision(device), "--run-dir", str(imagination)),
            *("--save-every", "5", "--snapshot-every", "24", "--device", device, "--seed", str(options.seed)),
            *("--no-eval", "--out", str(imagination / "final.zip")),
        )
    for name, policy in (("teacher", teacher_policy), ("imagination", imagination / "final.zip")):
        scores = out / "score" / name
        if needed(f"score_{name}", (scores / "score.json").is_file()):
            run(
                f"score_{name}",
                *("score", "--policy", str(policy), "--env", options.env, "--seeds", str(options.score_seeds)),
                *(["--steps", str(options.score_steps)] if options.score_steps else []),
                *("--commands", str(options.score_commands), "--workers", workers),
                *("--out", str(scores), "--overwrite"),
            )
    for name in STAGES:
        wall_s = timings["stages"].get(name, {}).get("wall_s", float("nan"))
        print(f"{name:18s} {wall_s:10.1f} s" + ("" if name in ran else "  (an earlier run)"))
    return timings


if __name__ == "__main__":
    main()

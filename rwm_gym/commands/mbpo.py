"""`rwm-gym mbpo`: the MBPO-PPO loop (`rwm_gym.rl.mbpo`) in a resumable run folder.

    rwm-gym mbpo --data DATA.h5 --out RUN [--checkpoint CKPT] [loop and imagination flags]
    rwm-gym mbpo --recipe NAME --out RUN [flags that differ from the recipe's]

A recipe (`assets/recipes/NAME.json`, or the path of such a JSON) holds the loop's settings (`mbpo`: the fields of
`MBPOConfig`), how its starting data is collected when no `--data` is given (`start_data`: into RUN/data_0.h5) and how
its starting model is trained when no `--checkpoint` is given (`start_model`: `ModelConfig` and `TrainConfig` fields).
A flag given overrides the recipe's value. The same command continues a stopped run:
the collection keeps its finished episodes, the loop its finished iterations.
"""

from __future__ import annotations

import argparse
import re
from dataclasses import dataclass, replace
from pathlib import Path

from rwm_gym.commands._imagination import add_imagination_options, imagination_from_args
from rwm_gym.commands._options import OverwriteOption, TensorBoardOption, TorchOptions, add_group
from rwm_gym.imagination.options import ImaginationOptions
from rwm_gym.options import (
    add_dataclass_options,
    dataclass_from_args,
)
from rwm_gym.output_guard import OutputError, check_folder, claim, no_empty_folder, resolved
from rwm_gym.rl.mbpo import MBPOConfig, mbpo

RUN_FILES = re.compile(r"(data_\d+\.h5|buffer(_base)?\.h5|model_\d+\.safetensors|policy_\d+\.zip|mbpo\.(json|png))")
"""The files the loop writes in its folder (`--out`)."""


def is_run_folder(folder: Path) -> bool:
    """Whether every file in `folder` is one the loop writes (or a hidden temp file, or a dataset a killed write
    left): the folder of a run, finished or killed, that the same command continues."""
    return all(p.name.startswith(".") or RUN_FILES.fullmatch(p.name.split(".partial-")[0]) for p in folder.iterdir())


def check_run_folder(out: Path, inputs, overwrite: bool = False) -> None:
    """A one-line OutputError for an input that the loop would overwrite in its folder, or the folder itself; for an
    input inside the folder; and for a folder of other files, unless `overwrite`."""
    folder = resolved(out)
    for source in (s for s in inputs if s is not None):
        path = resolved(source)
        if path == folder or (path.parent == folder and RUN_FILES.fullmatch(path.name)):
            raise OutputError(
                f"--out {out}: the run writes {path.name if path != folder else 'into it'}, which is "
                f"the input {source}; copy the input elsewhere first"
            )
    check_folder(out, inputs=inputs, overwrite=overwrite, continues=folder.is_dir() and is_run_folder(folder))


@dataclass(frozen=True)
class RunOptions:
    """The loop's inputs and its run folder."""

    out: Path
    """run folder: models, data, policies and the report; the same command resumes it"""
    data: Path | None = None
    """initial physics dataset (HDF5); default with a --recipe: its start_data, collected into OUT/data_0.h5"""
    recipe: str | None = None
    """a recipe: NAME of assets/recipes/NAME.json or a JSON path; its settings replace the defaults (default: none)"""
    checkpoint: str | None = None
    """world model to start from (default: train one on --data)"""
    model: str = "rwm"
    """world-model kind to (re)train"""
    init_policy: Path | None = None
    """SB3 PPO zip to start from, e.g. a behaviour-cloned actor (default: a fresh policy)"""
    model_free_curve: Path | None = None
    """CSV (timesteps, tracking) of a model-free PPO run, drawn beside the loop's curve, e.g.
    assets/policies/anymal_d_ppo_physics_curve.csv (default: none)"""


OPTIONS = (RunOptions, OverwriteOption, TensorBoardOption, TorchOptions, MBPOConfig, ImaginationOptions)
"""The dataclasses the flags of `rwm-gym mbpo` come from."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `rwm-gym mbpo`: the run's files, then one flag per `MBPOConfig` and `ImaginationOptions` field."""
    for group in (RunOptions, OverwriteOption, TensorBoardOption, TorchOptions):
        add_group(parser, group)
    # every loop flag defaults to None: one left out keeps the --recipe's value (else the field's default)
    add_dataclass_options(parser, MBPOConfig, skip={"imagination"}, defaults_none=True)
    add_imagination_options(
        parser,
        defaults=MBPOConfig().imagination,
        aliases={"episode_steps": ["--imagined-episode-steps"]},
        defaults_none=True,
    )


def run(args: argparse.Namespace) -> int:
    """`rwm-gym mbpo`: refuse a run folder that would overwrite an input, then run (or resume) the loop in it."""
    from rwm_gym.tensorboard import check_tensorboard

    check_tensorboard(args.tensorboard, "rwm-gym mbpo")
    if args.threads:
        import torch

        torch.set_num_threads(args.threads)
    from rwm_gym.model.lineage import share_text

    try:
        recipe = load_recipe(args.recipe) if args.recipe else {}
        config = config_from(args, recipe)
        if args.data is None and "start_data" not in recipe:
            raise ValueError("--data is required (or a --recipe with start_data to collect)")
        curve = args.model_free_curve or _shipped(recipe.get("model_free_curve"))
        inputs = [args.data, args.checkpoint, args.init_policy, curve]
        check_run_folder(args.out, inputs, overwrite=args.overwrite)
        with claim(args.out), no_empty_folder(args.out):
            data = args.data or collect_start_data(recipe, args.out)
            start_train, start_model = start_model_settings(recipe)
            report = mbpo(
                data,
                args.out,
                config,
                checkpoint=args.checkpoint,
                init_policy=args.init_policy,
                model_kind=args.model,
                device=args.device,
                model_free_curve=curve,
                tensorboard=args.tensorboard,
                start_train=start_train,
                start_model=start_model,
            )
    except ValueError as error:
        raise SystemExit(f"rwm-gym mbpo: {error}") from None
    best = report["log"][report["best_iteration"]]
    print(
        f"best physics tracking {report['best_tracking']:.3f} at iteration {report['best_iteration']}, physics samples "
        f"behind it {share_text(best['physics_samples'], report['task'])}; report {args.out / 'mbpo.json'}, curve "
        f"{args.out / 'mbpo.png'}"
    )
    return 0


def load_recipe(name: str) -> dict:
    """The recipe JSON `name` (a path, or a name in assets/recipes); a one-line ValueError if there is none."""
    import json

    from rwm_gym.resources import assets_dir

    folder = assets_dir() / "recipes"
    path = Path(name) if name.endswith(".json") else folder / f"{name}.json"
    if not path.is_file():
        known = ", ".join(sorted(p.stem for p in folder.glob("*.json"))) or "none"
        raise ValueError(f"--recipe {name}: no such recipe (a JSON path, or one of: {known})")
    recipe = json.loads(path.read_text())
    if not isinstance(recipe, dict) or not isinstance(recipe.get("mbpo", {}), dict):
        raise ValueError(f"--recipe {name}: {path} is not an MBPO recipe (a JSON object with an 'mbpo' object)")
    return recipe


def config_from(args: argparse.Namespace, recipe: dict) -> MBPOConfig:
    """The loop's config: the recipe's (else the defaults), with every flag given on top (the flags default to None:
    one left out keeps the recipe's value)."""
    base = MBPOConfig.from_dict(recipe.get("mbpo", {}))
    imagination = imagination_from_args(args, base.imagination)
    return dataclass_from_args(MBPOConfig, args, skip={"imagination"}, base=base, imagination=imagination)


def _shipped(path: str | None) -> Path | None:
    """A file a recipe names by its repository path ("assets/..."), wherever the data folders live."""
    from rwm_gym.resources import shipped_file

    return None if path is None else shipped_file(path)


def collect_start_data(recipe: dict, out: Path) -> Path:
    """The recipe's starting data in OUT/data_0.h5: collected (a killed collection continued), or found finished."""
    from rwm_gym.data.collect import collect, finished_collection

    plan = dict(recipe["start_data"])
    path = Path(out) / "data_0.h5"
    episodes, seed = int(plan.pop("episodes")), int(plan.pop("seed", 0))
    if not finished_collection(path, episodes=episodes, seed=seed, what="this recipe's starting data"):
        collect(plan.pop("env", "AnymalD-MuJoCo-v0"), plan.pop("policy", "random"), episodes, path, seed=seed, **plan)
    return path


def start_model_settings(recipe: dict):
    """The `TrainConfig` and `ModelConfig` fields of the recipe's starting model (None, {} without one)."""
    from rwm_gym.model.config import TrainConfig

    start = recipe.get("start_model")
    if not start:
        return None, {}
    return replace(TrainConfig(), **start.get("train", {})), dict(start.get("model", {}))

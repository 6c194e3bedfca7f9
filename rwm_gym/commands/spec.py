"""`rwm-gym spec`: write a task spec for a dm_control suite task or a legged robot's MJCF.

    rwm-gym spec --from-dmc acrobot-swingup --out acrobot.toml
    rwm-gym spec --mjcf robot.xml [--base BODY] [--feet BODY ...] [--keyframe NAME] --out my_robot.toml

The spec's normalisation comes from its own short random-policy collection; everything the generator chose without
being told is printed and written into the spec's header. An existing file is never replaced without --overwrite.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from rwm_gym.atomic import write_text
from rwm_gym.commands._options import OverwriteOption, add_group
from rwm_gym.options import option


@dataclass(frozen=True, kw_only=True)
class SpecOptions:
    """The model a spec is drafted from (one of --from-dmc and --mjcf), the choices it would guess, and its file."""

    from_dmc: str | None = option(None, metavar="DOMAIN-TASK", one_of="source")
    """a dm_control suite task, e.g. acrobot-swingup"""
    mjcf: Path | None = option(None, one_of="source")
    """MJCF of a legged robot with a free-floating base"""
    out: Path
    """spec to write (.toml); --mjcf also writes the model copy OUT.rwm.xml"""
    base: str | None = None
    """--mjcf: the floating base body (default: the body with the free joint)"""
    feet: tuple[str, ...] | None = option(None, nargs="+")
    """foot bodies (default: --mjcf the leaf bodies of the legs, --from-dmc the colliding bodies named like a foot)"""
    keyframe: str | None = None
    """--mjcf: the standing keyframe, the default pose (default: the file's first)"""
    name: str | None = None
    """--mjcf: task name (default: the model's name); ids are NAME-MuJoCo-v0, RWM-NAME-v0"""
    fast_physics: bool = False
    """--mjcf: give the model copy ANYmal D's fast solver settings (pyramidal cone, few iterations, 5 ms steps), and
    print their speed and accuracy against the file's own solver"""
    episodes: int = option(8, ge=1)
    """random-policy episodes for the normalisation"""
    steps: int = option(200, ge=1)
    """policy steps per normalisation episode (at most)"""
    seed: int = 0


OPTIONS = (SpecOptions, OverwriteOption)
"""The dataclasses the flags of `rwm-gym spec` come from."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `rwm-gym spec`."""
    for group in OPTIONS:
        add_group(parser, group)


def run(args: argparse.Namespace) -> int:
    """`rwm-gym spec`: 0, or 2 with one line on stderr on bad input."""
    from rwm_gym.output_guard import check_output
    from rwm_gym.specgen.draft import fill_normalization

    start = time.perf_counter()
    out = Path(args.out)
    try:
        if out.suffix != ".toml":
            raise ValueError(f"--out {out}: a task spec is a .toml file")
        written = [out]
        if args.from_dmc:
            from rwm_gym.specgen.from_dmc import dmc_draft

            if args.fast_physics or args.keyframe:
                flag = "--fast-physics" if args.fast_physics else "--keyframe"
                raise ValueError(f"{flag} applies to --mjcf (a dm_control task keeps the suite's physics and pose)")
            domain, sep, task = args.from_dmc.partition("-")
            if not sep or not task:
                raise ValueError(f"--from-dmc {args.from_dmc!r}: expected DOMAIN-TASK, e.g. acrobot-swingup")
            draft, model_xml = dmc_draft(domain, task, args.feet), None
        else:
            from rwm_gym.specgen.from_mjcf import legged_draft

            model_xml = out.with_suffix(".rwm.xml").resolve()
            if model_xml == args.mjcf.resolve():
                raise ValueError(f"--out {out}: its model copy {model_xml.name} would replace the --mjcf file")
            written.append(model_xml)
            draft = None
        for path in written:
            check_output(path, inputs=[args.mjcf], overwrite=args.overwrite)
        with tempfile.TemporaryDirectory(prefix="rwm-spec-") as tmp:
            if model_xml is not None:  # the collection runs on a copy: nothing is written before the spec works
                draft, mjcf_text = legged_draft(
                    args.mjcf,
                    base=args.base,
                    feet=args.feet,
                    name=args.name,
                    fast_physics=args.fast_physics,
                    keyframe=args.keyframe,
                )
                trial = Path(tmp) / model_xml.name
                trial.write_text(mjcf_text)
                draft.table("task").values["model"] = str(trial)
            how = fill_normalization(draft, args.episodes, args.steps, args.seed)
        draft.state_tables()[0].note = "World-model state. Normalisation (x - mean) / std per column:\n" + how
        if model_xml is not None:
            draft.table("task").values["model"] = str(model_xml)
            write_text(model_xml, mjcf_text)
        draft.parse()
        write_text(out, draft.text())
    except KeyboardInterrupt:
        return 130
    except (ValueError, FileNotFoundError) as err:
        print(f"rwm-gym spec: {err}", file=sys.stderr)
        return 2
    print(f"wrote {', '.join(str(p) for p in written)} in {time.perf_counter() - start:.1f} s; assumed:")
    for line in draft.assumptions:
        print(f"  - {line}")
    return 0

"""`rwm-gym spec`: write a task spec for a dm_control suite task or a legged robot's MJCF.

    rwm-gym spec --from-dmc acrobot-swingup --out acrobot.toml
    rwm-gym spec --mjcf robot.xml [--base BODY] [--feet BODY ...] --out my_robot.toml

The spec's normalisation comes from its own short random-policy collection; everything the generator chose without
being told is printed and written into the spec's header. An existing file is never replaced without --overwrite.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

from rwm_gym.atomic import write_text


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `rwm-gym spec`."""
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--from-dmc", metavar="DOMAIN-TASK", help="a dm_control suite task, e.g. acrobot-swingup")
    source.add_argument("--mjcf", type=Path, help="MJCF of a legged robot with a free-floating base")
    parser.add_argument(
        "--out", type=Path, required=True, help="spec to write (.toml); --mjcf also writes the model copy OUT.rwm.xml"
    )
    parser.add_argument("--base", help="--mjcf: the floating base body (default: the body with the free joint)")
    parser.add_argument(
        "--feet",
        nargs="+",
        help="foot bodies (default: --mjcf the leaf bodies of the legs, "
        "--from-dmc the colliding bodies named like a foot)",
    )
    parser.add_argument(
        "--name", help="--mjcf: task name (default: the model's name); ids are NAME-MuJoCo-v0, RWM-NAME-v0"
    )
    parser.add_argument("--episodes", type=int, default=8, help="random-policy episodes for the normalisation")
    parser.add_argument("--steps", type=int, default=200, help="policy steps per normalisation episode (at most)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--overwrite", action="store_true", help="replace existing output files")


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
                draft, mjcf_text = legged_draft(args.mjcf, base=args.base, feet=args.feet, name=args.name)
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

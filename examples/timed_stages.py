"""A pipeline's record of where and how long it ran: the machine, then each stage's command, wall seconds and load
average, written atomically to a JSON file after every stage (an interrupted run keeps the stages it finished).
`examples/gpu_pipeline.py` and `examples/legged_pipeline.py` write their `timings.json` with it.

    python examples/timed_stages.py --device cuda      # print what a record says of this machine
"""

from __future__ import annotations

import json
import os
import platform
import shlex
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch

import rwm_gym
from rwm_gym.atomic import write_json
from rwm_gym.options import parse_dataclass_args

CLI = [sys.executable, "-m", "rwm_gym.cli"]
"""`rwm-gym` in this Python (a stage's command starts with it; the record shows it as `rwm-gym`)."""


def cpu_model() -> str:
    """The CPU's model name (Linux: /proc/cpuinfo), else what `platform` knows."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def commit() -> str | None:
    """The checkout's commit, where this runs from a git checkout."""
    done = subprocess.run(
        ["git", "rev-parse", "HEAD"], cwd=Path(__file__).parent, capture_output=True, text=True, check=False
    )
    return done.stdout.strip() or None


def machine(device: str) -> dict:
    """The hardware and software the stages ran on."""
    cuda = torch.device(device).type == "cuda"
    return {
        "device": torch.cuda.get_device_name(0) if cuda else "cpu",
        "gpus": [torch.cuda.get_device_name(i) for i in range(torch.cuda.device_count())] if cuda else [],
        "cpu_model": cpu_model(),
        "cpu_count": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "torch": torch.__version__,
        "cuda": torch.version.cuda,
        "rwm_gym": rwm_gym.__version__,
        "commit": commit(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "loadavg_before": os.getloadavg(),
    }


def shown(command: list[str]) -> str:
    """The command as a user types it: `rwm-gym ...` for a command of this Python's rwm-gym."""
    return shlex.join(["rwm-gym", *command[len(CLI) :]] if command[: len(CLI)] == CLI else command)


def timed(name: str, what: str, call: Callable[[], object], timings: dict, record: Path) -> None:
    """Run `call` (described by `what`), record its wall time and the load average after it under `name`, and write
    the record so far."""
    print(f"[{name}] {what}", flush=True)
    tic = time.perf_counter()
    call()
    timings["stages"][name] = {"command": what, "wall_s": time.perf_counter() - tic, "loadavg_after": os.getloadavg()}
    write_json(record, timings)


def stage(name: str, command: list[str], timings: dict, record: Path) -> None:
    """Run one command, fail loudly, record its wall time and write the record so far."""
    timed(name, shown(command), lambda: subprocess.run(command, check=True), timings, record)


def cli_stage(name: str, args: list[str], timings: dict, record: Path) -> None:
    """Run `rwm-gym ARGS` in this process (torch and MuJoCo imported once for all stages), stop the pipeline with its
    status if it fails, record its wall time and write the record so far."""
    from rwm_gym.cli import main as cli

    def call() -> None:
        if status := cli(args):
            raise SystemExit(status)

    timed(name, shlex.join(["rwm-gym", *args]), call, timings, record)


@dataclass(frozen=True)
class Options:
    """Print what a pipeline's timings.json records of this machine."""

    device: str = "cpu"
    """torch device the stages run on."""


def main(argv: list[str] | None = None) -> dict:
    found = machine(parse_dataclass_args(Options, argv).device)
    print(json.dumps(found, indent=1))
    return found


if __name__ == "__main__":
    main()

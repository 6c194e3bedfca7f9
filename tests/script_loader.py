"""Loading the repository's example and benchmark scripts (not a package) as modules in tests."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

ROOT = Path(__file__).resolve().parent.parent
EXAMPLES, BENCHMARKS = ROOT / "examples", ROOT / "benchmarks"


def load_script(path: Path, name: str) -> ModuleType:
    """Execute the script at `path` as module `name` (registered in sys.modules: dataclasses resolve their
    annotations through it); its `main` is not run."""
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module

"""Imports run one way: every import in `rwm_gym/` (inside functions too) goes from a room to one on a lower floor,
and no modules import each other in a circle. The floors are written down in `docs/reference/architecture.md`."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "rwm_gym"

FLOORS = (
    ("untrusted", "output_guard", "options", "progress", "tensorboard", "workers"),
    ("atomic", "resources", "policy_zip"),
    ("spec",),
    ("task", "registration", "batched_core"),
    ("rwm_gym",),
    ("physics",),
    ("policies",),
    ("data",),
    ("model", "specgen"),
    ("gap", "imagination"),
    ("vector",),
    ("rl",),
    ("commands", "cli"),
)
"""Rooms from the lowest floor up: a subpackage of `rwm_gym`, a top-level module, or `rwm_gym` itself (the package's
`__init__`). A room imports only from rooms on floors below its own."""

FLOOR = {room: floor for floor, rooms in enumerate(FLOORS) for room in rooms}


def _modules() -> dict[str, Path]:
    """Every module of the package by its dotted name (a package by its own name, not `.__init__`)."""
    out = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


MODULES = _modules()


def _imported(name: str, path: Path, node: ast.Import | ast.ImportFrom) -> list[str]:
    """The package's modules an import statement in module `name` (file `path`) loads: `from a.b import c` loads
    `a.b.c` where that is a module, else `a.b`."""
    if isinstance(node, ast.Import):
        return [alias.name for alias in node.names if alias.name in MODULES]
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    base = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
    source = node.module if not node.level else ".".join(filter(None, [base, node.module]))
    out = [f"{source}.{alias.name}" for alias in node.names if f"{source}.{alias.name}" in MODULES]
    if source in MODULES and len(out) < len(node.names):
        out.append(source)
    return out


def _imports() -> dict[str, set[str]]:
    """Module -> the package's modules it imports anywhere in its file (top level, functions, TYPE_CHECKING)."""
    graph: dict[str, set[str]] = {}
    for name, path in MODULES.items():
        nodes = (
            n for n in ast.walk(ast.parse(path.read_text(), str(path))) if isinstance(n, ast.Import | ast.ImportFrom)
        )
        graph[name] = {target for node in nodes for target in _imported(name, path, node)} - {name}
    return graph


def _room(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else parts[0]


def test_every_room_has_a_floor():
    rooms = {_room(m) for m in MODULES}
    assert not rooms - set(FLOOR), (
        f"rooms without a floor (add them to FLOORS and the architecture page): {rooms - set(FLOOR)}"
    )


def test_imports_run_down_the_floors():
    upward = sorted(
        f"{module} ({_room(module)}, floor {FLOOR[_room(module)]}) imports {target} ({_room(target)}, floor "
        f"{FLOOR[_room(target)]})"
        for module, targets in _imports().items()
        for target in targets
        if _room(module) != _room(target) and FLOOR.get(_room(target), -1) >= FLOOR.get(_room(module), -1)
    )
    assert not upward, "imports that do not go to a lower floor:\n" + "\n".join(upward)


def _circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    out: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        for target in sorted(graph[node]):
            if target not in index:
                visit(target)
                low[node] = min(low[node], low[target])
            elif target in stack:
                low[node] = min(low[node], index[target])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                out.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return out


def test_no_modules_import_each_other_in_a_circle():
    circles = _circles(_imports())
    assert not circles, f"modules that import each other in a circle: {circles}"


def test_the_checks_see_imports_inside_functions_and_circles():
    tree = ast.parse("def f():\n    from rwm_gym.gap import select\n    from . import fit\n")
    nodes = [n for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)]
    path = PACKAGE / "gap" / "workflow.py"
    assert [_imported("rwm_gym.gap.workflow", path, n) for n in nodes] == [["rwm_gym.gap.select"], ["rwm_gym.gap.fit"]]
    assert _circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]

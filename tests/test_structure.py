"""The shape issue 22 asks for, read from the source, so that anyone can check it with `pytest`:
no module over 600 lines and no class over 400 in the four packages; `sitl_mock` importing
nothing from `companion` (the mock stands for the autopilot: sharing the companion's code would
hide the companion's bugs from the tests); no import cycle in or across the packages (lazy imports
counted); and the flight state written in one module, the supervisor."""

from __future__ import annotations

import ast
from pathlib import Path

from tests.planner.test_imports import _cycles, _type_checking_nodes

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("companion", "planner_core", "sitl_mock", "demo")
MODULE_LINES = 600
CLASS_LINES = 400


def _files(package: str) -> list[Path]:
    return sorted((ROOT / package).rglob("*.py"))


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = frozenset(_module_name(p) for package in PACKAGES for p in _files(package))


def _imported(path: Path) -> set[str]:
    """Every module named by an import in the file (relative ones resolved), lazy ones too; not
    those under `if TYPE_CHECKING:` (never run)."""
    name = _module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out: set[str] = set()
    tree = ast.parse(path.read_text(encoding="utf-8"))
    skip = _type_checking_nodes(tree)
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(parts + ([node.module] if node.module else []))
            subs = {f"{base}.{a.name}" for a in node.names}
            out.update(subs)
            # `from package import submodule` needs the submodule, not the package's __init__
            # (being imported already when one of its modules is)
            if not subs <= MODULES:
                out.add(base)
    return out


def test_no_module_or_class_over_its_size() -> None:
    over = []
    for package in PACKAGES:
        for path in _files(package):
            src = path.read_text(encoding="utf-8")
            if (n := len(src.splitlines())) > MODULE_LINES:
                over.append(f"{path.relative_to(ROOT)}: {n} lines")
            for node in ast.walk(ast.parse(src)):
                if isinstance(node, ast.ClassDef) and (n := node.end_lineno - node.lineno + 1) > CLASS_LINES:  # type: ignore[operator]
                    over.append(f"{path.relative_to(ROOT)}: class {node.name} {n} lines")
    assert over == []


def test_the_mock_imports_nothing_from_the_companion() -> None:
    found = [f"{p.relative_to(ROOT)}: {m}" for p in _files("sitl_mock") for m in sorted(_imported(p))
             if m == "companion" or m.startswith("companion.")]
    assert found == []


def test_no_import_cycle_in_or_across_the_packages() -> None:
    mods = {_module_name(p): p for package in PACKAGES for p in _files(package)}
    graph = {name: {m for m in _imported(p) if m in mods and m != name} for name, p in mods.items()}
    assert _cycles(graph) == []


def test_the_flight_state_is_written_in_the_supervisor_only() -> None:
    """`FlightState` is frozen; a new one is made by `flight.go` or `replace`, and held in
    `Supervisor._now`. Outside supervisor.py (and flight.py, which defines them) no module
    builds one, moves one, or assigns the supervisor's state."""
    found = []
    for path in _files("companion"):
        if path.name in ("supervisor.py", "flight.py"):
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Call):
                fn = ast.unparse(node.func)
                if fn in ("FlightState", "flight.FlightState", "go", "flight.go"):
                    found.append(f"{path.name}:{node.lineno}: {fn}(...)")
            elif isinstance(node, ast.Assign | ast.AugAssign | ast.AnnAssign):
                targets = node.targets if isinstance(node, ast.Assign) else [node.target]
                for t in targets:
                    if isinstance(t, ast.Attribute) and t.attr in ("_now", "value") and "flight" in ast.unparse(t.value):
                        found.append(f"{path.name}:{node.lineno}: {ast.unparse(t)} = ...")
    assert found == []

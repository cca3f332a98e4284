"""The code's layout as docs/architecture.md states it: lrfsim uses lrfcal only through its public API (lrfcal,
lrfcal.model, lrfcal.io, lrfcal.errors), lrfsim's rooms importing one way, the rooms of lrfcal and the one direction
of the imports between them (no cycle; io/ below the method), the public API importable without heavy modules, and
all of lrfcal type-checked by mypy."""

from __future__ import annotations

import ast
import importlib.util
import itertools
import shutil
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src"
#: what lrfsim (and any code outside lrfcal) may import of lrfcal
PUBLIC = ("lrfcal", "lrfcal.model", "lrfcal.io", "lrfcal.errors")


def _imports(path: Path) -> list[tuple[int, str]]:
    """(line, module) of every import in ``path`` (at the top, in functions, under TYPE_CHECKING), relative ones
    resolved against its package; in a package's ``__init__.py`` also the modules its lazy table names (a dict of
    "name": "lrfcal.module" strings, as lrfcal/__init__.py's PEP 562 facade)."""
    tree = ast.parse(path.read_text(), str(path))
    package = ".".join(path.relative_to(SRC).with_suffix("").parts[:-1])
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Dict) and path.name == "__init__.py":
            found += [(v.lineno, v.value) for v in node.values
                      if isinstance(v, ast.Constant) and isinstance(v.value, str) and v.value.startswith("lrfcal.")]
        elif isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*parts, base] if base else parts)
            found += [(node.lineno, f"{base}.{alias.name}" if _is_module(f"{base}.{alias.name}") else base)
                      for alias in node.names]
    return found


def _is_module(name: str) -> bool:
    rel = Path(*name.split("."))
    return (SRC / rel.with_suffix(".py")).is_file() or (SRC / rel / "__init__.py").is_file()


def test_lrfsim_uses_only_lrfcal_public_api() -> None:
    bad = []
    for path in sorted((SRC / "lrfsim").rglob("*.py")):
        for line, name in _imports(path):
            if (name == "lrfcal" or name.startswith("lrfcal.")) and not any(
                    name == p or name.startswith(p + ".") for p in PUBLIC):
                bad.append(f"{path.relative_to(ROOT)}:{line}: {name}")
    assert not bad, "lrfsim imports lrfcal internals (use lrfcal's public API):\n" + "\n".join(bad)


#: at most this many modules directly in src/lrfsim beside __init__ and cli: the rest live in rooms
MAX_FLAT_LRFSIM = 6


def _lrfsim_part(name: str) -> str | None:
    """The part of lrfsim a module belongs to: its room (a subpackage of lrfsim), else the flat module itself
    (e.g. "cli"); None outside lrfsim."""
    parts = name.split(".")
    if parts[0] != "lrfsim" or len(parts) < 2:
        return None
    return parts[1]


def test_lrfsim_rooms_import_one_way() -> None:
    """lrfsim's rooms (its subpackages) and flat modules import one way: no cycle among them, counting every import
    (inside functions and under TYPE_CHECKING too); each room's __init__ says what it holds and imports nothing (no
    re-exports); no command reaches the test support (lrfsim.testing); at most MAX_FLAT_LRFSIM modules stand
    directly in src/lrfsim beside __init__ and cli."""
    root = SRC / "lrfsim"
    rooms = sorted(p.parent.name for p in root.glob("*/__init__.py"))
    flat = sorted(p.stem for p in root.glob("*.py") if p.stem not in ("__init__", "cli"))
    assert len(flat) <= MAX_FLAT_LRFSIM, f"{len(flat)} flat lrfsim modules (at most {MAX_FLAT_LRFSIM}): {flat}"
    for room in rooms:
        init = root / room / "__init__.py"
        tree = ast.parse(init.read_text(), str(init))
        assert ast.get_docstring(tree), f"src/lrfsim/{room}/__init__.py: no docstring saying what the room holds"
        assert all(isinstance(n, ast.Expr) for n in tree.body), f"src/lrfsim/{room}/__init__.py: more than a docstring"

    edges: dict[str, dict[str, str]] = {}  # part -> {imported part: first site}
    for path in sorted(root.rglob("*.py")):
        rel = path.relative_to(SRC).with_suffix("").parts
        me = _lrfsim_part(".".join(rel[:-1] if rel[-1] == "__init__" else rel))
        for line, name in _imports(path):
            other = _lrfsim_part(name)
            if me is not None and other is not None and other != me:
                edges.setdefault(me, {}).setdefault(other, f"{path.relative_to(ROOT)}:{line}")
    assert "testing" not in {t for part, out in edges.items() if part != "testing" for t in out}, \
        "lrfsim imports its test support (lrfsim.testing): only tests and benchmarks may"

    # a cycle: depth-first search for an edge back to a part on the current path
    state: dict[str, int] = {}  # 1 on the path, 2 done
    path_: list[str] = []

    def visit(part: str) -> list[str] | None:
        state[part] = 1
        path_.append(part)
        for nxt in sorted(edges.get(part, {})):
            if state.get(nxt) == 1:
                return path_[path_.index(nxt):] + [nxt]
            if nxt not in state and (loop := visit(nxt)) is not None:
                return loop
        path_.pop()
        state[part] = 2
        return None

    for part in sorted(edges):
        if part not in state and (loop := visit(part)) is not None:
            sites = [f"{a} -> {b} ({edges[a][b]})" for a, b in itertools.pairwise(loop)]
            raise AssertionError("lrfsim's rooms import in a circle:\n" + "\n".join(sites))


def test_public_api_names_resolve() -> None:
    import lrfcal

    missing = [name for name in lrfcal.__all__ if not hasattr(lrfcal, name)]
    assert not missing
    with pytest.raises(AttributeError):
        _ = lrfcal.no_such_name  # type: ignore[attr-defined]


#: the rooms of lrfcal (its subpackages and the modules directly in src/lrfcal), in an order their imports run down
#: (docs/architecture.md, "The rooms"): each imports only rooms before it
ROOMS = ("errors", "config", "model", "types", "runtime", "result", "io", "estimate", "stages", "pipeline", "report",
         "commands", "terminal", "cli")
#: what io/ (it reads and writes files) must not import: the method and the rooms above it
ABOVE_IO = ("estimate", "stages", "pipeline", "report", "commands", "terminal", "cli")


def _room(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if parts[0] == "lrfcal" and len(parts) > 1 else None


def _room_imports() -> dict[tuple[str, str], list[str]]:
    """(room, a room it imports) -> where ("src/lrfcal/...:line"), for every import of lrfcal (every kind, as
    :func:`_imports`) between two rooms; lrfcal/__init__.py, the public API, stands in no room."""
    arrows: dict[tuple[str, str], list[str]] = defaultdict(list)
    for path in sorted((SRC / "lrfcal").rglob("*.py")):
        here = _room(".".join(path.relative_to(SRC).with_suffix("").parts))
        if here is None or here == "__init__":
            continue
        for line, name in _imports(path):
            there = _room(name)
            if there is not None and there != here:
                arrows[(here, there)].append(f"{path.relative_to(ROOT)}:{line}")
    return arrows


def test_lrfcal_rooms() -> None:
    """src/lrfcal holds the rooms of :data:`ROOMS`, each a subpackage or a module named for what it holds."""
    rooms = {p.parent.name for p in (SRC / "lrfcal").glob("*/__init__.py")}
    rooms |= {p.stem for p in (SRC / "lrfcal").glob("*.py") if p.stem != "__init__"}
    assert sorted(rooms) == sorted(ROOMS)


def test_imports_between_rooms_run_one_way() -> None:
    """The rooms' imports form no cycle: following the arrows from any room never leads back to it (each room imports
    only rooms below it, an order :data:`ROOMS` gives). Every import counts: at the top, in functions, under
    TYPE_CHECKING."""
    arrows = _room_imports()
    graph: dict[str, set[str]] = defaultdict(set)
    for a, b in arrows:
        graph[a].add(b)

    def cycle_from(room: str, path: tuple[str, ...], done: set[str]) -> tuple[str, ...] | None:
        if room in path:
            return path[path.index(room):] + (room,)
        if room in done:
            return None
        for other in sorted(graph[room]):
            found = cycle_from(other, (*path, room), done)
            if found:
                return found
        done.add(room)
        return None

    done: set[str] = set()
    for room in sorted(graph):
        cycle = cycle_from(room, (), done)
        assert cycle is None, "the rooms' imports run in a circle: " + " -> ".join(cycle) + "\n" + "\n".join(
            f"{a} -> {b}: {arrows[(a, b)][0]}" for a, b in zip(cycle, cycle[1:], strict=False))
    order = {room: k for k, room in enumerate(ROOMS)}
    upward = sorted(f"{a} -> {b}: {arrows[(a, b)][0]}" for a, b in arrows if order[a] < order[b])
    assert not upward, "a room imports one above it in ROOMS (reorder ROOMS if the design allows it):\n" + "\n".join(
        upward)


def test_io_imports_nothing_above_it() -> None:
    """io/ reads and writes files: it imports the data types, the model, the result, the errors and the runtime,
    nothing of the method or above it (:data:`ABOVE_IO`)."""
    bad = [f"io -> {b}: {where}" for (a, b), sites in sorted(_room_imports().items()) if a == "io" and b in ABOVE_IO
           for where in sites]
    assert not bad, "io/ imports the method or what stands above it:\n" + "\n".join(bad)


#: the stage modules that may read the whole lrfcal.config.CalibConfig: the two ways (the orchestrator's steps)
WAYS = ("src/lrfcal/stages/markers.py", "src/lrfcal/stages/scene.py")


def test_stages_read_their_configuration_slice() -> None:
    """No stage but the two ways (:data:`WAYS`) and no module of the estimate package names CalibConfig (imported or
    as an attribute, e.g. ``config.CalibConfig``): each reads its own slice, a Protocol of the options it reads."""
    bad = []
    for folder in ("stages", "estimate"):
        for path in sorted((SRC / "lrfcal" / folder).glob("*.py")):
            rel = str(path.relative_to(ROOT))
            if rel in WAYS:
                continue
            for node in ast.walk(ast.parse(path.read_text(), rel)):
                names = ([a.name for a in node.names] if isinstance(node, (ast.Import, ast.ImportFrom))
                         else [node.attr] if isinstance(node, ast.Attribute)
                         else [node.id] if isinstance(node, ast.Name) else [])
                if any(n == "CalibConfig" or n.endswith(".CalibConfig") for n in names):
                    bad.append(f"{rel}:{node.lineno}")
    assert not bad, "stages outside the ways take the whole CalibConfig (give them a slice):\n" + "\n".join(bad)


def test_notes_are_returned_not_appended() -> None:
    """No function of lrfcal takes a list of notes to append to (an out-parameter): a stage returns its notes with
    its result (lrfcal.types.Noted, or a field of the result it returns), and the way and the orchestrator collect
    them into CalibrationResult.notes."""
    bad = []
    for path in sorted((SRC / "lrfcal").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                a = node.args
                for arg in (*a.posonlyargs, *a.args, *a.kwonlyargs):
                    if arg.arg == "notes" and arg.annotation is not None and \
                            ast.unparse(arg.annotation).startswith("list"):
                        bad.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name}({arg.arg})")
    assert not bad, "functions append to a list of notes passed in (return them instead):\n" + "\n".join(bad)


def test_import_lrfcal_is_light() -> None:
    """``import lrfcal`` (and its error types) imports neither numpy's heavy neighbours nor the message types."""
    code = ("import sys, lrfcal; lrfcal.InputError; "
            "print(','.join(m for m in ('scipy', 'mujoco', 'matplotlib', 'rerun', 'rosbags') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == ""


@pytest.mark.skipif(importlib.util.find_spec("mypy") is None and shutil.which("mypy") is None,
                    reason="mypy is not installed (pip install -e '.[test]' installs it)")
def test_mypy_lrfcal() -> None:
    """All of lrfcal type-checks (mypy, the settings in pyproject.toml), and CalibConfig satisfies every stage's
    configuration slice and each way the Way of its steps' types (tests/static_types.py)."""
    proc = subprocess.run([sys.executable, "-m", "mypy", "src/lrfcal", "tests/static_types.py"], cwd=ROOT,
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout[-3000:]

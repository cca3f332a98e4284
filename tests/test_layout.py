"""The code's layout as docs/architecture.md states it: lrfsim uses lrfcal only through its public API (lrfcal,
lrfcal.model, lrfcal.io, lrfcal.errors), lrfsim's rooms importing one way, the rooms of lrfcal, the public API
importable without heavy modules, the rig model and the estimate package type-checked by mypy, and at most five
functions outside the CLIs with more than 8 parameters."""

from __future__ import annotations

import ast
import importlib.util
import itertools
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src"
#: what lrfsim (and any code outside lrfcal) may import of lrfcal
PUBLIC = ("lrfcal", "lrfcal.model", "lrfcal.io", "lrfcal.errors")


def _imports(path: Path) -> list[tuple[int, str]]:
    """(line, module) of every import in ``path``, relative ones resolved against its package."""
    tree = ast.parse(path.read_text(), str(path))
    package = ".".join(path.relative_to(SRC).with_suffix("").parts[:-1])
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
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


def test_lrfcal_rooms() -> None:
    """At most 12 modules directly in src/lrfcal; the rest in subpackages named for what they are."""
    top = sorted(p.name for p in (SRC / "lrfcal").glob("*.py"))
    assert len(top) <= 12, top
    rooms = sorted(p.parent.name for p in (SRC / "lrfcal").glob("*/__init__.py"))
    assert rooms == ["estimate", "io", "model", "report", "runtime", "stages"]


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
def test_mypy_model_and_estimate() -> None:
    """The rig model and the estimate package type-check (mypy, the settings in pyproject.toml), and CalibConfig
    satisfies every stage's configuration slice and each way the Way of its steps' types (tests/static_types.py)."""
    proc = subprocess.run([sys.executable, "-m", "mypy", "src/lrfcal/model", "src/lrfcal/estimate",
                           "tests/static_types.py"], cwd=ROOT,
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout[-3000:]


#: the functions outside the command lines that may take more than 8 parameters: facades over a command's options
#: (docs/architecture.md, "What travels together"); every other function takes what travels together as one object
MANY_PARAMETERS = {"src/lrfcal/io/rig.py:with_overrides", "src/lrfcal/workflow.py:calibrate_folder",
                   "src/lrfcal/io/recording.py:read_recording", "src/lrfsim/trials/study.py:run_trials",
                   "src/lrfsim/trials/study.py:study"}


def test_at_most_five_functions_take_more_than_eight_parameters() -> None:
    """Outside the CLIs (cli.py), no function takes more than 8 parameters (self and cls not counted) but the five
    command facades of MANY_PARAMETERS."""
    many = set()
    for path in sorted(SRC.rglob("*.py")):
        if path.name == "cli.py":
            continue
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                a = node.args
                names = [x.arg for x in (*a.posonlyargs, *a.args, *a.kwonlyargs)]
                k = len(names) + (a.vararg is not None) + (a.kwarg is not None) - (names[:1] in (["self"], ["cls"]))
                if k > 8:
                    many.add(f"{path.relative_to(ROOT)}:{node.name}")
    assert many <= MANY_PARAMETERS and len(MANY_PARAMETERS) <= 5, sorted(many - MANY_PARAMETERS)

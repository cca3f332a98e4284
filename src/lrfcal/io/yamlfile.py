"""Reading a YAML file the user gave: one place for the one-line errors (file, line:column, what is wrong)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from lrfcal.errors import InputError


def read_yaml(path: str | Path, what: str) -> Any:
    """The parsed content of the YAML file ``path`` (``what`` names it in messages: "scenario", "nominal file").

    Raises:
        InputError: a missing or unreadable file, a binary (non-UTF-8) file, or a YAML syntax error with its line
            and column.
    """
    path = Path(path)
    if path.is_dir():
        raise InputError(_folder_given(path, what))
    if not path.is_file():
        raise InputError(f"{path}: {what} not found")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as e:
        raise InputError(f"{path}: not a text (UTF-8) file: byte {e.object[e.start]:#04x} at offset {e.start}; a "
                         f"{what} is a YAML file") from None
    except OSError as e:
        raise InputError(f"{path}: cannot read {what} ({e.strerror})") from None
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f"{path}:{mark.line + 1}:{mark.column + 1}" if mark is not None else str(path)
        problem = getattr(e, "problem", None) or " ".join(str(e).split())
        raise InputError(f"{where}: YAML syntax error: {problem}") from None


#: the file a folder written by the tools holds for each ``what`` of :func:`read_yaml`
_USUAL_NAME = {"scenario": "scenario.yaml", "nominal file": "nominal.yaml", "calibration file": "calibration.yaml",
               "ground truth": "ground_truth.yaml"}


def _folder_given(path: Path, what: str) -> str:
    """The one line for a folder given where a YAML file is expected: the YAML file it holds to give instead (the
    one a recording or output folder names so first), or that it holds none."""
    try:
        found = sorted(p.name for p in path.iterdir() if p.suffix in (".yaml", ".yml") and p.is_file()
                       and not p.name.startswith("."))
    except OSError:
        found = []
    usual = _USUAL_NAME.get(what)
    if usual in found:
        found.remove(usual)
        found.insert(0, usual)
    hint = (f"give the file itself, e.g. {path / found[0]}" if found else
            f"it holds no YAML file; give the {what}'s .yaml file")
    return f"{path}: a folder, not a {what if what.endswith(' file') else what + ' file'}: {hint}"


__all__ = ["read_yaml"]

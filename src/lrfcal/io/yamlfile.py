"""Reading a YAML file the user gave: one place for the one-line errors (file, line:column, what is wrong)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from ..errors import InputError


def read_yaml(path: str | Path, what: str) -> Any:
    """The parsed content of the YAML file ``path`` (``what`` names it in messages: "scenario", "nominal file").

    Raises:
        InputError: a missing or unreadable file, a binary (non-UTF-8) file, or a YAML syntax error with its line
            and column.
    """
    path = Path(path)
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


__all__ = ["read_yaml"]

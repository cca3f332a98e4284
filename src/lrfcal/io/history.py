"""A check's history: one CSV row per `lrfcal check` (``--history FILE``), appended atomically (the file is written
anew beside itself with the row added and renamed into place: a reader never sees half a row, and a failure leaves
the file as it was). The columns (:data:`COLUMNS`): when, the calibration and the recording checked, the verdict,
the test's statistic, degrees of freedom, threshold and false-alarm rate, then per parameter its saved and new value
with their own 1-sigma, the change's sigma, z and whether it was tested (empty where it was not compared), SI units.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from lrfcal.errors import InputError
from lrfcal.io.files import atomic_file
from lrfcal.model.kinematics import DH_NAMES, ESTIMATE_NAMES
from lrfcal.model.unknowns import INTRINSICS

#: the parameters a history has columns for, in order
HISTORY_PARAMETERS: tuple[str, ...] = (*DH_NAMES, "clock_offset", *INTRINSICS, *ESTIMATE_NAMES[:6])
#: per parameter: its columns' suffixes
PER_PARAMETER = ("saved", "saved_sigma", "new", "new_sigma", "change_sigma", "z", "tested", "drifted")
COLUMNS: tuple[str, ...] = ("time", "calibration", "recording", "verdict", "statistic", "dof", "threshold",
                            "false_alarm", *(f"{p}_{k}" for p in HISTORY_PARAMETERS for k in PER_PARAMETER))


def _cell(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, bool):
        return "1" if v else "0"
    if isinstance(v, float):
        return "" if not math.isfinite(v) else f"{v:.12g}"
    return str(v)


def read_history(path: str | Path) -> list[dict[str, str]]:
    """The rows of a history file (none when it does not exist).

    Raises:
        InputError: a file whose header is not a check history's (naming the file and what to do).
    """
    path = Path(path)
    if not path.exists():
        return []
    if path.is_dir():
        raise InputError(f"{path}: --history: a folder; give a CSV file (created at the first check)")
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"{path}: --history: cannot read it as text ({e})") from None
    if not text.strip():
        return []
    reader = csv.DictReader(io.StringIO(text))
    if tuple(reader.fieldnames or ()) != COLUMNS:
        raise InputError(f"{path}: --history: not a check history (its header is not the columns `lrfcal check` "
                         "writes); give a new file name, or the file an earlier check wrote")
    return list(reader)


def append_history(path: str | Path, row: Mapping[str, Any]) -> list[dict[str, str]]:
    """Append one row (column name -> value; missing columns empty) to the history ``path``, atomically; return every
    row, the new one last."""
    path = Path(path)
    rows = read_history(path)
    new = {c: _cell(row.get(c)) for c in COLUMNS}
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=COLUMNS, lineterminator="\n")
    w.writeheader()
    w.writerows([*rows, new])
    with atomic_file(path) as tmp:
        tmp.write_text(buf.getvalue(), encoding="utf-8")
    return [*rows, new]


__all__ = ["COLUMNS", "HISTORY_PARAMETERS", "append_history", "read_history"]

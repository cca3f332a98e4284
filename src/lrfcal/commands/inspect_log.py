"""``lrfcal inspect LOG``: what a scan log holds, and the rig file (``servo:`` and ``log:``) that reads it.

Where the rig file does not describe the log, its layout is guessed from the text (:func:`guess_layout`, marked
as guessed): a first row whose values end in a strictly monotonic, evenly spaced run is a header of beam angles
(degrees beyond 2 pi); of the leading columns a column counting 1, 2, 3, ... is a row number (``ignore``), the
first increasing one the time, the next the motor angle; the time unit from the rows' median spacing (a scanner
turns at 1-100 Hz); ranges in millimetres when their median exceeds 100; range_min_m 0.02 proposed when returns
below 2 cm occur (no scanner measures there: they are error codes, as a Hokuyo URG reports 0-19 mm).
:func:`inspect_path` dispatches: a scan log here, anything else to :func:`lrfcal.commands.inspect_bag.inspect_bag`.

Array shapes: R rows, N beams.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import ValidationError

from lrfcal.commands.inspect_bag import (
    BagInspection,
    ScanGeometry,
    ServoInfo,
    TopicInfo,
    _report_problems,
    inspect_bag,
    proposed_dh,
)
from lrfcal.errors import InputError
from lrfcal.io.rig import rig_snippet, validation_message
from lrfcal.io.scanlog import describe_layout, is_scan_log, load_log, log_servo, numbers, parse_rows, read_scan_log
from lrfcal.stages.timing import covered_scans
from lrfcal.types import LogLayout, ScanSource, ServoSource

#: rows parsed to guess the layout
GUESS_ROWS = 500
#: returns below this are error codes, not distances [m] (no 2D scanner measures closer)
ERROR_CODE_BELOW_M = 0.02


@dataclass(frozen=True)
class LogGuess:
    """A guessed layout: ``log`` and ``servo`` (the rig file's keys, for the snippet), the LogLayout when they make
    one (None without a header row: the scanner's angles cannot be guessed), why, and what is missing."""

    log: dict[str, Any]
    servo: dict[str, Any]
    layout: LogLayout | None
    notes: tuple[str, ...]
    problems: tuple[str, ...]


def _even_run_start(v: np.ndarray) -> int:
    """Index where the strictly monotonic, evenly spaced (within 5 %) run that ends the row starts."""
    d = np.diff(v)
    if d.size < 2:
        return v.size
    med = float(np.median(d[d.size // 2:]))
    if med == 0 or not math.isfinite(med):
        return v.size
    ok = (np.sign(d) == np.sign(med)) & (np.abs(d - med) <= 0.05 * abs(med))
    bad = np.flatnonzero(~ok)
    return 0 if not bad.size else int(bad[-1]) + 1


def _time_unit(period: float) -> str:
    """s, ms, us or ns from the median row spacing (a scanner's period is 0.01-1 s)."""
    for unit, limit in (("s", 3.0), ("ms", 3e3), ("us", 3e6)):
        if period < limit:
            return unit
    return "ns"


def guess_layout(path: str | Path) -> LogGuess:
    """Guess a scan log's layout from its text (module docstring). Raises InputError: unreadable, not numeric."""
    path = Path(path)
    lines, rows, _ = parse_rows(path)
    first = numbers(path, lines[0], rows[0], lambda k: f"value {k + 1}")
    start = _even_run_start(first)
    header = (len(rows) > 1 and first.size - start >= max(8, first.size // 2)
              and float(np.max(np.abs(first[start:]))) <= 360)
    notes: list[str] = []
    problems: list[str] = []
    data_lines, data_rows = (lines[1:], rows[1:]) if header else (lines, rows)
    data_lines, data_rows = data_lines[:GUESS_ROWS], data_rows[:GUESS_ROWS]
    width = len(data_rows[0])
    sample = np.array([numbers(path, ln, r, lambda k: f"value {k + 1}")
                       for ln, r in zip(data_lines, data_rows, strict=True) if len(r) == width])
    log: dict[str, Any] = {}
    if header:
        lead, n = start, first.size - start
        angles = first[start:]
        unit = "deg" if float(np.max(np.abs(angles))) > 2 * math.pi + 0.5 else "rad"
        log.update(header="angles", beam_angle_unit=unit)
        notes.append(f"line {lines[0]}: a header row of {n} beam angles ({angles[0]:g} to {angles[-1]:g} {unit}) after "
                     f"{lead} leading columns")
        if width - lead == 2 * n:
            log["intensities"] = True
        elif width - lead != n:
            problems.append(f"line {data_lines[0]}: {width} columns, the header row {first.size}: check log.columns "
                            f"and log.intensities")
    else:
        counting = sample.shape[0] > 1 and bool(np.all(np.diff(sample[:, 0]) == 1))
        lead, n, unit = (3 if counting else 2), width - (3 if counting else 2), None
        problems.append("no header row of beam angles: give log.angle_min_rad and log.angle_increment_rad (the "
                        "scanner's first beam and step, from its datasheet or driver)")
        log.update(angle_min_rad=None, angle_increment_rad=None)
    columns, note, problem = _leading(sample[:, :lead]) if lead >= 2 else (["time", "angle"], "", "")
    notes += [note] if note else []
    problems += [problem] if problem else []
    if lead < 2:
        problems.append(f"only {lead} column(s) before the ranges: a log needs the time and the motor angle")
    t = sample[:, columns.index("time")] if sample.size else np.zeros(0)
    period = float(np.median(np.diff(t))) if t.size > 1 else 0.0
    time_unit = _time_unit(abs(period))
    ang = sample[:, columns.index("angle")] if sample.size else np.zeros(0)
    if unit is None:
        unit = "deg" if ang.size and float(np.max(np.abs(ang))) > 2 * math.pi + 0.5 else "rad"
    ranges = sample[:, lead:lead + n]
    pos = ranges[np.isfinite(ranges) & (ranges > 0)]
    mm = bool(pos.size) and float(np.median(pos)) > 100.0
    codes = int(np.sum(pos * (1e-3 if mm else 1.0) < ERROR_CODE_BELOW_M))
    log = {"columns": columns, "time_unit": time_unit, **({"range_unit": "mm"} if mm else {}), **log}
    if codes:
        log["range_min_m"] = ERROR_CODE_BELOW_M
        notes.append(f"{codes} returns below {ERROR_CODE_BELOW_M:g} m: no scanner measures there (a Hokuyo URG reports "
                     f"error codes 0-19 mm in place of a distance); range_min_m: {ERROR_CODE_BELOW_M:g} proposed, set "
                     f"your scanner's")
    servo = {"unit": unit, "motion": "step"}
    notes.append(f"motor angle in {unit} (guessed{' from the header' if header else ''}: check servo.unit), time in "
                 f"{time_unit} (rows {abs(period):g} {time_unit} apart), one angle per scan (motion: step)")
    layout = None
    if header and not problems:
        try:
            layout = LogLayout.model_validate(log)
        except ValidationError as err:
            problems.append(validation_message(err, "log"))
    return LogGuess(log, servo, layout, tuple(notes), tuple(problems))


def _leading(cols: np.ndarray) -> tuple[list[str], str, str]:
    """Names of the leading columns: a row number (ignore), then the first increasing column (time), then the
    next (angle); the rest ignore. With a note (a column counting rows) and a problem (no column increasing), each
    "" when there is none."""
    names = ["ignore"] * cols.shape[1]
    d = np.diff(cols, axis=0)
    counting = [bool(d.shape[0] and np.all(d[:, k] == 1)) for k in range(cols.shape[1])]
    rest = [k for k in range(cols.shape[1]) if not counting[k]]
    if len(rest) < 2:
        rest = list(range(cols.shape[1]))
    rising = [k for k in rest if d.shape[0] and np.all(d[:, k] > 0)]
    ti = rising[0] if rising else rest[0]
    problem = "" if rising else f"no leading column increases from row to row: column {ti + 1} taken as the time"
    names[ti] = "time"
    names[next(k for k in rest if k != ti)] = "angle"
    note = f"column {counting.index(True) + 1} counts rows (1, 2, 3, ...): ignored" if any(counting) else ""
    return names, note, problem


def inspect_path(path: str | Path, scan: ScanSource | None = None, servo: ServoSource | None = None,
                 dh: dict[str, float] | None = None, log: LogLayout | None = None, *, propose: bool = True,
                 progress: Callable[[int, int], None] | None = None) -> BagInspection:
    """:func:`inspect_log` for a scan log (lrfcal.io.scanlog.is_scan_log), else
    :func:`lrfcal.commands.inspect_bag.inspect_bag`; ``propose``, ``progress``: the DH proposal
    (lrfcal.stages.propose)."""
    if is_scan_log(path):
        return inspect_log(path, log, servo, dh, propose=propose, progress=progress)
    return inspect_bag(path, scan, servo, dh=dh, propose=propose, progress=progress)


def inspect_log(path: str | Path, layout: LogLayout | None = None, servo: ServoSource | None = None,
                dh: dict[str, float] | None = None, *, propose: bool = True,
                progress: Callable[[int, int], None] | None = None) -> BagInspection:
    """Inspect a scan log: ``layout`` / ``servo`` from a rig file or options (None: guessed); ``dh`` for the
    snippet (when None and ``propose``: proposed from the scene's planes, lrfcal.stages.propose). The result has
    ``ros_version`` 0 and one "topic", the log itself.

    Raises:
        InputError: the log cannot be read or is not numeric.
    """
    path = Path(path)
    guessed: list[str] = []
    notes: list[str] = []
    problems: list[str] = []
    log_keys: dict[str, Any]
    if layout is None:
        g = guess_layout(path)
        layout, log_keys = g.layout, g.log
        notes.extend(g.notes)
        problems.extend(g.problems)
        guessed.append("log")
        if servo is None:
            servo = ServoSource(topic=None, unit=g.servo["unit"], motion="step")
            guessed.append("servo")
    else:
        log_keys = layout.model_dump(exclude_defaults=True)
    src = log_servo(servo)
    shown = ServoSource.model_validate({**src.model_dump(), "topic": "the log's angle column"})
    servo_keys = {k: v for k, v in src.model_dump(exclude_none=True, exclude_defaults=True).items() if k != "topic"}
    servo_keys["motion"] = src.motion
    topics: tuple[TopicInfo, ...] = ()
    geometry = report = servo_info = n_cov = data = None
    duration = 0.0
    if layout is not None:
        try:
            rows = load_log(path, layout)
            data = read_scan_log(path, layout, src, warn=lambda _t: None)
        except InputError as err:
            problems.append(str(err))
        else:
            report, sc, j = data.report, data.scans, data.joints
            duration = float(sc.stamps_s[-1] - sc.stamps_s[0])
            rate = (sc.stamps_s.size - 1) / duration if duration > 0 else None
            topics = (TopicInfo(path.name, describe_layout(layout, sc.mu_rad.shape[1]), report.n_scan_messages, rate,
                                layout.header == "angles", None),)
            a0, inc, dev = rows.evenly_spaced()
            ti = float(sc.time_increment_s[0])
            geometry = ScanGeometry(report.n_scans, (sc.mu_rad.shape[1],) * 2, (a0, a0), (float(rows.mu_rad[-1]),) * 2,
                                    (inc, inc), (ti, ti), (sc.scan_time_s,) * 2, sc.range_min_m, sc.range_max_m,
                                    layout.intensities)
            dt = np.diff(j.stamps_s)
            speed = np.abs(np.diff(j.positions_rad)) / np.where(dt > 0, dt, np.nan)
            servo_info = ServoInfo(int(j.stamps_s.size), float(j.positions_rad.min()), float(j.positions_rad.max()),
                                   rate, float(np.nanmedian(speed)) if speed.size else 0.0)
            n_cov = int(covered_scans(sc, j).sum())
            problems.extend(_report_problems(report))
            if dev > 1e-5:
                notes.append(f"the header's beam angles are not evenly spaced (up to {math.degrees(dev):.4f} deg off "
                             f"a grid): read as given; lrfcal convert needs a grid (a LaserScan has one)")
            span = math.degrees(servo_info.max_rad - servo_info.min_rad)
            if span < 10.0:
                problems.append(f"the motor turns only {span:.2f} deg: the cloud is a wedge, nearly one scan plane; "
                                f"a targetless calibration cannot determine the DH parameters from it")
            if not layout.intensities:
                problems.append("no intensities: reproject and targetless calibration work, markers do not")
    if guessed:
        problems.append(f"guessed: {', '.join(guessed)} (check the snippet, especially columns, time_unit and "
                        f"servo.unit, sign and offset_rad)")
    proposal = proposed_dh(data, dh, propose, progress)
    snippet = rig_snippet(None, None, dh if proposal is None else proposal.values(),
                          comment=None if proposal is None else proposal.comment())
    snippet += _yaml_block({"servo": servo_keys, "log": log_keys})
    if layout is None and "angle_min_rad" in log_keys:
        snippet += "# log.angle_min_rad, log.angle_increment_rad: fill in (rad) from the scanner's datasheet\n"
    return BagInspection(path, 0, duration, topics, None, shown, tuple(guessed), geometry, servo_info, report, n_cov,
                         tuple(problems), snippet, dict(dh or {}), tuple(notes), proposal)


def _yaml_block(data: dict[str, Any]) -> str:
    import yaml

    def plain(v: Any) -> Any:
        if isinstance(v, tuple):
            return [plain(x) for x in v]
        if isinstance(v, dict):
            return {k: plain(x) for k, x in v.items()}
        return v

    return yaml.safe_dump(plain(data), sort_keys=False, default_flow_style=None)


__all__ = ["LogGuess", "guess_layout", "inspect_log", "inspect_path"]

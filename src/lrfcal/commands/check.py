"""Is a calibration still valid for a new recording of the same rig? The use case behind `lrfcal check` (no
command-line code: lrfcal.cli calls it; lrfsim's drift study calls :func:`check_recording` through lrfcal's API).

The new recording is calibrated on the calibration's own path (lrfcal.pipeline.calibrate, one method: the saved
calibration's, markers when the recording has tape distances, else targetless), started from the saved values: the
rig file it is read with is the calibration's own (calibration.yaml's ``rig``: where the bag keeps the scans and the
servo angle; ``--nominal`` replaces it where a driver update moved them), its DH replaced by the saved DH, the clock
offset started from the saved one, the options the saved calibration ran with. Then every parameter of the rig both
calibrations estimated (the DH, the clock offset, the intrinsics; the mount only with ``fixed_mount``) is compared
(lrfcal.estimate.drift): one joint test of "nothing changed" at the stated false-alarm rate.

Outcomes: :attr:`CheckOutcome.drifted` (the command exits 4), still valid (0), or a CalibrationError (exit 3) when
the new recording does not calibrate or determines nothing that can be tested.
"""

from __future__ import annotations

import math
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from lrfcal.config import CalibConfig
from lrfcal.errors import CalibrationError, ClockStartError, InputError
from lrfcal.estimate.drift import DEFAULT_FALSE_ALARM, DriftTest, check_rate, drift_test
from lrfcal.io import files
from lrfcal.io.calibration_yaml import scanner_dict
from lrfcal.io.recording import read_recording
from lrfcal.io.saved_calibration import SavedCalibration, calibration_file, read_saved
from lrfcal.io.scanlog import resolve_recording
from lrfcal.model.kinematics import DH_NAMES, ESTIMATE_NAMES, log_so3
from lrfcal.model.unknowns import BY_NAME, INTRINSICS, wrap_pi
from lrfcal.report.check_report import check_figure, check_markdown, show
from lrfcal.result import CalibrationResult, Observer
from lrfcal.types import Recording

#: the rig's own parameters a check compares, in this order (the mount's only with --fixed-mount)
RIG_PARAMETERS: tuple[str, ...] = (*DH_NAMES, "clock_offset", *INTRINSICS)
MOUNT_PARAMETERS: tuple[str, ...] = ESTIMATE_NAMES[:6]
#: why the mount is not tested by default
MOUNT_WHY = ("the mount: the rig's pose in the marker frame changes whenever the rig is set down elsewhere; "
             "--fixed-mount tests it")


@dataclass(frozen=True)
class CheckOutcome:
    """A check: the saved calibration, the new recording's calibration (``result``), the joint test, the notes
    (what was assumed), and the seconds it took."""

    calibration: Path
    recording: Path
    saved: SavedCalibration
    result: CalibrationResult
    test: DriftTest
    notes: tuple[str, ...]
    seconds: float

    @property
    def drifted(self) -> bool:
        return self.test.drifted

    def line(self) -> str:
        """The verdict in one line: still valid, or drifted naming each parameter that moved (change and z), the
        one that explains most of the test first; the test's numbers; what was not tested."""
        t = self.test
        numbers = (f"chi2 {t.statistic:.2f} {'>' if t.drifted else '<='} {t.threshold:.2f} ({t.dof} dof, false "
                   f"alarm {100 * t.false_alarm:g} %)")
        untested = ", ".join(p.name for p in t.not_tested)
        tail = f"; not tested: {untested}" if untested else ""
        if t.drifted:
            moved = ", ".join(f"{p.name} {show(p.name, p.change, signed=True)} (z {p.z:+.1f})" for p in t.moved)
            return f"drifted: {moved}: {numbers}{tail}"
        return f"still valid: no change in {', '.join(p.name for p in t.tested)} ({numbers}){tail}"

    def to_dict(self) -> dict[str, Any]:
        """check.yaml's content (docs/formats.md, "Outputs of lrfcal check")."""
        sol = self.result.solution
        return {
            "format_version": 1,
            "verdict": "drifted" if self.drifted else "still valid",
            "calibration": str(self.calibration),
            "recording": str(self.recording),
            "method": {"saved": self.saved.method, "new": self.result.method},
            "units": "SI (m, rad, s; scales 1); change = new - saved; sigma from both covariances; z = change / sigma",
            **self.test.to_dict(),
            "new_calibration": {"reduced_chi2": _plain(sol.reduced_chi2), "n_observations": int(sol.n_observations),
                                "checks": [{"name": c.name, "passed": bool(c.passed), "detail": c.detail}
                                           for c in self.result.checks]},
            "notes": list(self.notes),
            "seconds": round(self.seconds, 3),
        }


def _plain(v: float) -> float | None:
    return float(v) if math.isfinite(v) else None


# --- the recording, read as the saved calibration read its own ---------------------------------------------------

def _read(saved: SavedCalibration, recording: Path, *, bag: Path | None, distances: Path | None,
          nominal: Path | None, targetless: bool, warn: Callable[[str], None] | None) -> tuple[Recording, bool,
                                                                                             list[str]]:
    """The new recording, read with the calibration's rig file (or ``nominal``), and whether it is calibrated
    targetless; the notes of what was assumed."""
    notes: list[str] = []
    folder, bag = resolve_recording(recording, bag)
    rec_dir = Path(folder) if folder is not None else None
    tape_path = distances if distances is not None else (rec_dir / "distances.csv" if rec_dir is not None else None)
    has_tape = distances is not None or (tape_path is not None and tape_path.exists())
    is_targetless = targetless or saved.method == "targetless" or not has_tape
    if saved.method == "markers" and is_targetless and not targetless:
        notes.append("the new recording has no tape distances: calibrated targetless, so the mount and the "
                     "marker range bias are not compared")
    with tempfile.TemporaryDirectory(prefix=".lrfcal-check-") as tmp:
        rig_path, from_saved = nominal, False
        if rig_path is None and saved.rig is not None:
            rig_path, from_saved = Path(tmp) / "rig.yaml", True
            rig_path.write_text(yaml.safe_dump(saved.rig.model_dump(mode="json", exclude_none=True)),
                                encoding="utf-8")
        elif rig_path is None:
            notes.append(f"{saved.path} holds no rig file (written before calibrations kept one): the recording is "
                         "read with its own nominal.yaml")
        try:
            rec = read_recording(folder, bag=bag, distances=distances if not is_targetless else None,
                                 nominal=rig_path, warn=warn, require_distances=not is_targetless)
        except InputError as err:
            if not from_saved or not any(k in str(err) for k in ("not in bag", "not found", "not a sensor_msgs")):
                raise
            raise InputError(f"{err}; the recording was read with the rig file of {saved.path} (its rig: "
                             f"scan.topic {saved.rig.scan_source().topic if saved.rig else '?'}): give --nominal "
                             "with a rig file that reads this recording (lrfcal inspect BAG proposes one)") from None
    return rec, is_targetless, notes


#: two scanners' angle_min or angle_increment that differ by more than this are two scanners [rad]
SCANNER_ANGLE_TOL_RAD = 1e-6


def _same_scanner(saved: SavedCalibration, rec: Recording) -> list[str]:
    """Refuse a recording of another scanner than the calibration's (another beam count, angle_increment or
    angle_min); a different frame_id is only noted.

    Raises:
        InputError: naming the calibration, both scanners and what to do.
    """
    if saved.scanner is None:
        return [f"{saved.path} does not say which scanner it saw (written before calibrations did): not checked "
                "that the recording is of the same scanner"]
    was, now = saved.scanner, scanner_dict(rec.scans)

    def describe(s: dict[str, Any]) -> str:
        inc, first = s.get("angle_increment_rad"), s.get("angle_min_rad")
        at = (f", {math.degrees(inc):.4g} deg apart from {math.degrees(first):.4g} deg"
              if isinstance(inc, float) and isinstance(first, float) else "")
        return f"{s.get('beams')} beams{at} (frame {s.get('frame_id')!r})"

    inc_was, inc_now = was.get("angle_increment_rad"), now.get("angle_increment_rad")
    min_was, min_now = was.get("angle_min_rad"), now.get("angle_min_rad")
    differs = was.get("beams") != now["beams"] or any(
        isinstance(a, float) and isinstance(b, float) and abs(a - b) > SCANNER_ANGLE_TOL_RAD
        for a, b in ((inc_was, inc_now), (min_was, min_now)))
    if differs:
        raise InputError(f"{saved.path}: scanner: the calibration's scanner has {describe(was)}, the recording's "
                         f"({rec.scans.source or rec.source}) {describe(now)}: a calibration of another rig; check "
                         "the recording against a calibration of this rig (or calibrate it: lrfcal calibrate)")
    if was.get("frame_id") != now["frame_id"]:
        return [f"the scans' frame_id is {now['frame_id']!r}, the calibration's {was.get('frame_id')!r} (the same "
                "beams and angles: taken as the same scanner)"]
    return []


def _config(saved: SavedCalibration, targetless: bool) -> CalibConfig:
    """The saved calibration's options (those this version knows), started from its clock offset, for the estimate
    alone (no clouds, no tunnel, no paper's baseline, no side-by-side), never forced."""
    known = {k: v for k, v in saved.config.items() if k in CalibConfig.model_fields}
    tau = saved.values.get("clock_offset", 0.0)
    return CalibConfig(**{**known, "force": False, "baseline": False, "clouds": False, "geometry": False,
                          "compare_targetless": False, "targetless": True if targetless else None,
                          "clock_offset_s": tau if math.isfinite(tau) else 0.0})


def _calibrate(rec: Recording, config: CalibConfig, progress: Callable[[str], None] | None
               ) -> tuple[CalibrationResult, list[str]]:
    """The new recording calibrated (lrfcal.pipeline.calibrate); from a clock offset of 0 when the saved one is
    refused as a start (the clock may have moved), saying so.

    Raises:
        CalibrationError: the new recording does not calibrate: nothing can be tested (the reason named).
    """
    from lrfcal.pipeline import calibrate  # the method, once the inputs are read (bad input answered without it)

    try:
        return calibrate(rec, config, Observer(progress)), []
    except CalibrationError as err:
        if isinstance(err, ClockStartError) and config.clock_offset_s != 0.0:
            try:
                note = (f"the saved clock offset {config.clock_offset_s * 1000:+.3g} ms was refused as a start "
                        f"({str(err).split(';')[0]}): started from 0")
                return calibrate(rec, config.replace(clock_offset_s=0.0), Observer(progress)), [note]
            except CalibrationError as again:
                err = again
        raise CalibrationError(f"check: the new recording does not calibrate, so nothing can be tested: {err}"
                               ) from None


# --- the comparison -----------------------------------------------------------------------------------------------

def compare(saved: SavedCalibration, result: CalibrationResult, false_alarm: float, fixed_mount: bool) -> DriftTest:
    """The joint test of every parameter both calibrations estimated (lrfcal.estimate.drift.drift_test); the others
    listed with why they are not tested.

    Raises:
        CalibrationError: nothing to test, naming what the new recording does not determine.
    """
    sol = result.solution
    new_names, new_cov = sol.estimated_covariance()
    values_new: dict[str, float] = {n: float(getattr(sol.params.dh, n)) for n in DH_NAMES}
    values_new["clock_offset"] = float(sol.clock_offset_s)
    values_new.update({n: float(v) for n, (v, _) in sol.intrinsics.items()})
    change = {n: values_new[n] - saved.values[n] for n in values_new if n in saved.values}
    for n in ("alpha", "beta"):
        change[n] = float(wrap_pi(change[n]))
    candidates = list(RIG_PARAMETERS)
    if saved.mount is not None:
        mount = sol.params.mount
        for n in ("x", "y", "z"):
            values_new[n] = float(getattr(mount, n))
            change[n] = values_new[n] - saved.values[n]
        w = log_so3(saved.mount.matrix()[:3, :3].T @ mount.matrix()[:3, :3])  # R_new = R_saved Exp(w), w in M
        for n, v in zip(("rx", "ry", "rz"), w, strict=True):
            values_new[n], change[n] = float(v), float(v)
        candidates = [*MOUNT_PARAMETERS, *candidates]
    held_new = {n: BY_NAME[n].held or "held by this calibration" for n, (_, s) in sol.intrinsics.items()
                if not math.isfinite(s)}
    tested, why = [], {}
    for n in candidates:
        if n in MOUNT_PARAMETERS and not fixed_mount:
            if n == "x":
                why["mount"] = MOUNT_WHY
            continue
        if n not in saved.names:
            if n in saved.values and not (n in INTRINSICS and n in held_new):
                why[n] = f"not estimated by the saved calibration ({saved.held.get(n, 'held')})"
            continue
        if n not in new_names:
            why[n] = f"not determined by the new recording ({held_new.get(n) or _held_why(result, n)})"
            continue
        tested.append(n)
    if not tested:
        raise CalibrationError("check: the new recording determines nothing that can be tested: " + "; ".join(
            f"{n}: {w}" for n, w in why.items()))
    i_new = [new_names.index(n) for n in tested]
    saved_values = dict(saved.values)
    if "mount" in why:
        saved_values.setdefault("mount", math.nan)
    return drift_test(tested, saved_values, values_new, change, saved.covariance_of(tested),
                      new_cov[np.ix_(i_new, i_new)], false_alarm, {n: w for n, w in why.items()})


def _held_why(result: CalibrationResult, name: str) -> str:
    """Why the new calibration did not estimate ``name``: the plane fit's held reason, or the clock's."""
    from lrfcal.result import PlaneEvidence

    if isinstance(result.evidence, PlaneEvidence) and name in result.evidence.plane_fit.held:
        return result.evidence.plane_fit.held_reason
    if name == "clock_offset":
        return "held: the sweep does not go both ways"
    if name in MOUNT_PARAMETERS:
        return "targetless: no world frame"
    return "held"


def check_recording(calibration: str | Path, recording: str | Path, *, bag: Path | None = None,
                    distances: Path | None = None, nominal: Path | None = None,
                    false_alarm: float = DEFAULT_FALSE_ALARM, fixed_mount: bool = False, targetless: bool = False,
                    progress: Callable[[str], None] | None = None,
                    warn: Callable[[str], None] | None = None) -> CheckOutcome:
    """Check ``calibration`` (a calibration folder or its calibration.yaml) against ``recording`` (a recording
    folder, a bag with ``bag``, a scan log), writing nothing (module docstring); ``progress(stage)`` as the new
    calibration's stages start.

    Raises:
        InputError: not a calibration, a calibration of another scanner, a recording the rig file does not read.
        CalibrationError: the saved calibration failed its checks (written with --force), the new recording does not
            calibrate, or determines nothing the check can test.
    """
    t0 = time.perf_counter()
    false_alarm = check_rate(false_alarm)
    saved = read_saved(calibration)
    if saved.failed_checks:
        raise CalibrationError(f"check: {saved.path} was written with --force although its checks "
                               f"{', '.join(saved.failed_checks)} failed: its values and sigmas are not trusted, so "
                               "no change from them can be tested; calibrate a recording of the rig that passes its "
                               "checks and check against that")
    rec, is_targetless, notes = _read(saved, Path(recording), bag=bag, distances=distances, nominal=nominal,
                                      targetless=targetless, warn=warn)
    notes += _same_scanner(saved, rec)
    from dataclasses import replace

    rec = replace(rec, nominal=replace(rec.nominal, dh=saved.dh, mount=saved.mount or rec.nominal.mount))
    result, more = _calibrate(rec, _config(saved, is_targetless), progress)
    test = compare(saved, result, false_alarm, fixed_mount)
    return CheckOutcome(calibration_file(calibration), Path(recording), saved, result, test,
                        (*saved.notes, *notes, *more), time.perf_counter() - t0)


def check_inputs(calibration: Path, recording: Path, out: Path, history: Path | None, *, bag: Path | None,
                 distances: Path | None, nominal: Path | None, overwrite: bool) -> None:
    """Refuse, before any work, outputs that overlap an input: -o, and --history, which must lie neither in the
    calibration folder nor in the recording folder (inputs) nor in -o; an -o that may not be replaced.

    Raises:
        InputError: naming the output, the input and how they overlap.
    """
    cal = Path(calibration)
    # the calibration folder is an input whole: its calibration.yaml given alone counts as the folder when the
    # folder is one a command wrote (it holds the manifest)
    cal_dir = cal if cal.is_dir() or not (cal.parent / files.MANIFEST_NAME).is_file() else cal.parent
    rec = Path(recording)
    inputs = {"calibration": cal_dir, "recording": rec, "bag": bag, "distances": distances, "nominal": nominal}
    files.check_no_overlap({"-o": out}, inputs, may_nest_in=("recording",))
    files.check_no_overlap({"--history": history}, inputs)
    files.check_no_overlap({"--history": history}, {"output folder": out})
    files.check_writable(files.check_replaceable(out, overwrite))


def history_row(outcome: CheckOutcome, when: str) -> dict[str, Any]:
    """The --history row of a check (lrfcal.io.history.COLUMNS), ``when``: its time as text."""
    t = outcome.test
    row: dict[str, Any] = {"time": when, "calibration": str(outcome.calibration), "recording": str(outcome.recording),
                           "verdict": "drifted" if t.drifted else "still valid", "statistic": t.statistic,
                           "dof": t.dof, "threshold": t.threshold, "false_alarm": t.false_alarm}
    for p in t.parameters:
        row.update({f"{p.name}_saved": p.saved, f"{p.name}_new": p.new, f"{p.name}_tested": p.tested})
        if p.tested:
            row.update({f"{p.name}_saved_sigma": p.sigma_saved, f"{p.name}_new_sigma": p.sigma_new,
                        f"{p.name}_change_sigma": p.sigma, f"{p.name}_z": p.z, f"{p.name}_drifted": p.drifted})
    return row


def write_check(outcome: CheckOutcome, out: Path, *, overwrite: bool = False, history: Path | None = None,
                figures: bool = True) -> Path:
    """Write check.yaml, report.md and check.png into the folder ``out`` (atomically: a temporary folder renamed
    into place), and append the check's row to ``history`` first (atomically), so that the figure shows it."""
    import datetime

    rows: list[dict[str, str]] = []
    if history is not None:
        from lrfcal.io.history import append_history

        when = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
        rows = append_history(history, history_row(outcome, when))
    folder = files.check_replaceable(out, overwrite)
    with files.atomic_folder(folder, "lrfcal check") as tmp:
        text = yaml.safe_dump(outcome.to_dict(), sort_keys=False, default_flow_style=None, width=110)
        (tmp / "check.yaml").write_text(text, encoding="utf-8")
        figure = None
        if figures:
            check_figure(outcome.test, tmp / "check.png", rows)
            figure = "check.png"
        checks = [(c.name, bool(c.passed), c.detail) for c in outcome.result.checks]
        md = check_markdown(outcome.test, outcome.line(), str(outcome.calibration), str(outcome.recording),
                            (outcome.saved.method, outcome.result.method), outcome.notes, checks, figure)
        (tmp / "report.md").write_text(md, encoding="utf-8")
    return Path(out)


__all__ = ["MOUNT_WHY", "RIG_PARAMETERS", "CheckOutcome", "check_inputs", "check_recording", "compare", "history_row",
           "write_check"]

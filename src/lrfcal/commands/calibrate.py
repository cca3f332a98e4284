"""Calibrate a recording folder and write the results: the use case behind `lrfcal calibrate` and `lrfsim run`
(no command-line code: lrfcal.cli and lrfsim.loop call it)."""

from __future__ import annotations

import math
import os
import shutil
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from lrfcal.config import CalibConfig
from lrfcal.errors import InputError
from lrfcal.io import files
from lrfcal.io.recording import RIG_FILE, read_nominal, read_recording
from lrfcal.io.scanlog import resolve_recording
from lrfcal.types import Recording

if TYPE_CHECKING:
    from lrfcal.result import CalibrationResult


def calibrate_folder(
    recording_dir: Path,
    out_dir: Path,
    *,
    bag: Path | None = None,
    distances: Path | None = None,
    nominal: Path | None = None,
    config: CalibConfig | None = None,
    overwrite: bool = False,
    truth: Any = None,
    rrd_path: Path | None = None,
    spawn: bool = False,
    scene: Any = None,
    progress: Callable[[str], None] | None = None,
    warn: Callable[[str], None] | None = None,
    options: dict[str, Any] | None = None,
    figures: bool = True,
) -> CalibrationResult:
    """Read, calibrate, write calibration.yaml / rig.urdf / clouds / report / figures atomically; log to rerun.

    ``truth`` (an lrfsim.compare.Truth) adds a truth column to the report and aligns the scene for rerun;
    ``scene`` (an lrfsim.scene.Scene) adds the simulated scene geometry to the rerun recording;
    ``options``: one-off rig-file settings (the keywords of lrfcal.io.rig.with_overrides, e.g. sign=-1);
    ``progress(stage)`` is called as each calibration stage starts (:data:`lrfcal.pipeline.STAGES`), then with
    "figures and report" and "rerun recording" while those are written.
    ``recording_dir`` may be a scan log itself, or a folder holding one instead of ``bag/``
    (:func:`lrfcal.io.scanlog.resolve_recording`).
    ``figures``: draw the report's PNG figures (False: the report says they were not asked for; for scripts).
    ``spawn`` where no viewer can start (see :func:`spawn_unavailable_reason`): ``warn`` is
    called with one line and the recording is saved instead (to ``rrd_path``, default ``out_dir/rerun.rrd``).

    Raises:
        InputError: an output overlaps an input (is, contains or lies inside the bag, distances or nominal file,
            or is or contains the recording folder), the output folder may not be replaced, bad input.
    """
    config = config or CalibConfig()
    recording_dir, bag = resolve_recording(recording_dir, bag)  # type: ignore[assignment]  # a scan log, or a folder with one
    rec = Path(recording_dir) if recording_dir is not None else None
    inputs = {
        "recording folder": rec,
        "bag": bag if bag is not None else (rec / "bag" if rec is not None else None),
        "distances": distances if distances is not None else (rec / "distances.csv" if rec is not None else None),
        "nominal": nominal if nominal is not None else (rec / RIG_FILE if rec is not None else None),
    }
    files.check_no_overlap({"-o": out_dir, "--rrd": rrd_path}, inputs, may_nest_in=("recording folder",))
    files.check_no_overlap({"--rrd": rrd_path}, {"output folder": out_dir})
    files.check_writable(files.check_replaceable(out_dir, overwrite))
    asked = spawn
    spawn = viewer_can_spawn(spawn, rrd_path if rrd_path is not None else Path(out_dir) / "rerun.rrd", warn)
    rrd_inside = "rerun.rrd" if asked and not spawn and rrd_path is None else None
    scan = servo = None
    if options:  # one-off rig-file settings (lrfcal.io.rig.with_overrides keywords) from the command line
        from lrfcal.io.rig import with_overrides

        nom = read_nominal(nominal if nominal is not None else Path(recording_dir) / RIG_FILE)
        scan, servo = with_overrides(nom.scan, nom.servo, **options)
    # without tape distances (no distances.csv and none given) the calibration is targetless (lrfcal.stages.targetless)
    tape_path = inputs["distances"]
    want_tape = not config.targetless and (distances is not None or (tape_path is not None and tape_path.exists()))
    recording = read_recording(recording_dir, bag=bag, distances=distances if want_tape else None, nominal=nominal,
                               scan=scan, servo=servo, warn=warn, require_distances=want_tape)
    if recording.tape is not None and want_tape:
        check_tape_units(recording, Path(inputs["distances"] or "distances.csv"))
    # the method's modules are loaded once the inputs are read: bad input is answered without them (0.7 s of the
    # command's 1.5 s start-up, tests/test_startup.py)
    from lrfcal.commands.calibration_run import calibrate_and_write

    return calibrate_and_write(recording, config, out_dir, overwrite=overwrite, truth=truth, rrd_path=rrd_path,
                               rrd_inside=rrd_inside, spawn=spawn, scene=scene, progress=progress, warn=warn,
                               figures=figures)


def spawn_unavailable_reason() -> str | None:
    """Why a rerun viewer cannot be started here (None when it probably can): no ``rerun`` executable, or no
    display on Linux (neither DISPLAY nor WAYLAND_DISPLAY set). Checked before spawning so that ``--spawn``
    never waits for a viewer that cannot come up."""
    exe = shutil.which("rerun") or shutil.which("rerun", path=os.path.dirname(sys.executable))
    if exe is None:
        return "no 'rerun' executable on PATH"
    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        return "no display (DISPLAY and WAYLAND_DISPLAY are unset)"
    return None


def viewer_can_spawn(spawn: bool, shown: Path, warn: Callable[[str], None] | None) -> bool:
    """``spawn`` unless no rerun viewer can start here (:func:`spawn_unavailable_reason`); then False, and
    ``warn`` is told in one line that the recording is saved to ``shown`` instead."""
    if not spawn:
        return False
    reason = spawn_unavailable_reason()
    if reason is None:
        return True
    if warn is not None:
        warn(f"--spawn: no rerun viewer can start here ({reason}); saved {shown} instead "
             f"(open it with: rerun {shown})")
    return False


#: Median tape distance above which the file is taken to be in mm or cm: the markers of one calibration are
#: seen by one laser (the UTM-30LX-EW reaches 30-60 m), so metres this long are a unit mistake [m].
MAX_MEDIAN_TAPE_M = 50.0
#: Two markers the laser sees are at most twice its longest range apart; tape distances beyond this factor times
#: the longest range in the recording (its 99.9th percentile) are a unit mistake [1].
MAX_TAPE_OVER_RANGE = 2.5


def check_tape_units(recording: Recording, path: Path) -> None:
    """Refuse tape distances that look like millimetres or centimetres: a median above MAX_MEDIAN_TAPE_M, or a
    longest distance above MAX_TAPE_OVER_RANGE x the longest range the laser measured in this recording.

    Raises:
        InputError: naming the file, the offending statistic and the likely unit.
    """
    assert recording.tape is not None, "check_tape_units: a recording without tape distances"
    d = np.asarray(recording.tape.distances_m, dtype=float)
    if d.size == 0:
        return
    med, longest = float(np.median(d)), float(d.max())
    r = np.asarray(recording.scans.ranges_m, dtype=float)
    r = r[np.isfinite(r)]
    seen = float(np.percentile(r, 99.9)) if r.size else math.inf
    if med > MAX_MEDIAN_TAPE_M:
        what = f"median {med:g} m is longer than any marker distance a laser sees"
    elif longest > MAX_TAPE_OVER_RANGE * seen:
        what = (f"the longest distance, {longest:g} m, is more than {MAX_TAPE_OVER_RANGE:g} x the longest range "
                f"in the recording ({seen:.3g} m)")
    else:
        return
    mm, cm = f"millimetres (median {med / 1000:.3g} m)", f"centimetres (median {med / 100:.3g} m)"
    likely = f"{mm} or {cm}" if med >= 500.0 else f"{cm} or {mm}"  # markers are usually 0.2-3 m apart
    raise InputError(f"{path}: distance_m: {what}; the file looks like it is in {likely}: write metres")



"""Calibrate a recording folder and write the results: the use case behind `lrfcal calibrate` and `lrfsim run`
(no command-line code: lrfcal.cli and lrfsim.loop call it)."""

from __future__ import annotations

import contextlib
import math
import os
import shutil
import sys
import tempfile
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from lrfcal.commands.calibration_folder import calibration_folder
from lrfcal.errors import InputError
from lrfcal.io import files
from lrfcal.io.recording import read_nominal, read_recording
from lrfcal.io.scanlog import resolve_recording
from lrfcal.io.truth import truth_dict, truth_frame
from lrfcal.model.kinematics import Params, Pose
from lrfcal.pipeline import CalibConfig, calibrate
from lrfcal.report import figures as figure_writer
from lrfcal.report.markdown import render_report
from lrfcal.result import CalibrationResult
from lrfcal.runtime.forked import Ahead
from lrfcal.types import Recording


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
        "nominal": nominal if nominal is not None else (rec / "nominal.yaml" if rec is not None else None),
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

        nom = read_nominal(nominal if nominal is not None else Path(recording_dir) / "nominal.yaml")
        scan, servo = with_overrides(nom.scan, nom.servo, **options)
    # without tape distances (no distances.csv and none given) the calibration is targetless (lrfcal.stages.targetless)
    tape_path = inputs["distances"]
    want_tape = not config.targetless and (distances is not None or (tape_path is not None and tape_path.exists()))
    recording = read_recording(recording_dir, bag=bag, distances=distances if want_tape else None, nominal=nominal,
                               scan=scan, servo=servo, warn=warn, require_distances=want_tape)
    if recording.tape is not None and want_tape:
        check_tape_units(recording, Path(inputs["distances"] or "distances.csv"))
    tmp_parent = Path(out_dir).parent if Path(out_dir).parent.exists() else None
    with tempfile.TemporaryDirectory(prefix=".figures-", dir=tmp_parent) as tmp, \
            (Ahead(figure_writer.preload, inherit=(recording.scans,)) if figures else contextlib.nullcontext()) \
            as ahead:
        drawer = _Drawer(ahead, Path(tmp), truth)
        result = calibrate(recording, config, progress=progress, fitted=drawer.fitted, outputs=drawer.outputs)
        if progress is not None:
            progress("figures and report")
        drawer.the_rest(result)
        report = render_report(result, truth=None if truth is None else truth_dict(truth))
        with calibration_folder(out_dir, result, overwrite) as folder:
            figs = drawer.drawn()
            written = dict(figs.written)
            if rrd_inside is not None:
                written["rerun"] = Path(tmp) / rrd_inside
                _log_rerun(result, written["rerun"], False, truth, scene, warn)
            folder.finish(report + _figures_section(figs, figures, warn), written)
    if rrd_path is not None or spawn:
        if progress is not None:
            progress("rerun recording")
        _log_rerun(result, rrd_path, spawn, truth, scene, warn)
    return result


class _Drawer:
    """The report's figures, drawn by ``ahead`` (None: no figures), a child forked when the calibration starts that
    imports matplotlib on another core meanwhile and draws each figure into ``folder`` as soon as what it shows is
    there: the intensity image on the association (:meth:`outputs`, while the surface returns are fitted), the
    others once the checks have passed (:meth:`fitted`, while the clouds are made), or on the result with its
    clouds (:meth:`the_rest`: targetless's flatness). The child has the scans already (sent by reference)."""

    def __init__(self, ahead: Ahead | None, folder: Path, truth: Any) -> None:
        self._ahead, self._folder, self._truth = ahead, folder, truth
        self._sent: list[str] = []  # the figures sent so far ("rest": all the others)

    def outputs(self, stage: str, out: Mapping[str, Any]) -> None:
        """lrfcal.pipeline.calibrate's ``outputs``: intensity.png once the association is final."""
        if self._ahead is not None and stage == "solve":
            self._ahead.start(figure_writer.write_intensity, out["scans"],
                              figure_writer.drawn_detections(out["detections"]), out["association"],
                              out["markers"].marker_ids, self._folder)
            self._sent.append("intensity")

    def fitted(self, fit: CalibrationResult) -> None:
        """lrfcal.pipeline.calibrate's ``fitted``: the figures that need no clouds, drawn during the reprojection."""
        if not figure_writer.needs_clouds(fit):
            self.the_rest(fit)

    def the_rest(self, part: CalibrationResult) -> None:
        """The figures not sent yet, once, drawn from ``part`` (a result, with its clouds where they are drawn)."""
        if self._ahead is not None and "rest" not in self._sent:
            self._ahead.start(figure_writer.write_figures, figure_writer.drawn_part(part), self._folder,
                              *_nominal_in_W(part, self._truth), tuple(self._sent))
            self._sent.append("rest")

    def drawn(self) -> figure_writer.Figures:
        """The figures written and those skipped (lrfcal.report.figures.Figures), in the order they were sent."""
        figs = figure_writer.Figures({}, {})
        while self._ahead is not None and self._ahead.started:
            figs = figs | self._ahead.result()
        return figs


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


def _figures_section(figs: figure_writer.Figures, drawn: bool, warn: Callable[[str], None] | None) -> str:
    """The report's "Figures" section for ``figs`` (lrfcal.report.figures.Figures): the figures written, or that none
    were asked for; each figure that could not be drawn is named with its reason (and ``warn`` told)."""
    text = "\n## Figures\n\n" + ("\n\n".join(f"![{name}]({p.name})" for name, p in figs.written.items())
                                  if drawn else "not drawn (--no-figures)")
    for name, why in figs.skipped.items():
        text += f"\n\n{name}.png could not be drawn ({why}); the calibration is not affected"
        if warn is not None:
            warn(f"figure {name}.png skipped: {why}")
    return text + "\n"


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


def _nominal_in_W(result: CalibrationResult, truth: Any) -> tuple[Params | None, str]:
    """The nominal parameters (nominal.yaml) in the marker frame W, for the figures' "before": possible when the
    true marker positions (simulator frame, the frame of the nominal mount) align to the tape's map; otherwise
    (None, label of the default: the calibration's start)."""
    start = (None, "nominal DH, fitted mount")
    nominal = result.recording.nominal
    if truth is None or nominal.mount is None:
        return start
    found = truth_frame(result, truth_dict(truth))
    if found is None:
        return start
    mount_W = Pose.from_matrix(found[0] @ nominal.mount.matrix())
    return Params(mount_W, nominal.dh), "nominal.yaml"


def _log_rerun(result: CalibrationResult, rrd_path: Path | None, spawn: bool, truth: Any, scene: Any,
               warn: Callable[[str], None] | None = None) -> None:
    from lrfcal.model.kinematics import transform_points
    from lrfcal.report import viz, vizscene

    geoms = None
    true_markers_W = None
    if truth is not None:
        found = truth_frame(result, truth_dict(truth))
        if found is not None:
            T_W_sim = found[0]
            true_markers_W = transform_points(T_W_sim, np.array(list(truth.markers.values())))
            if scene is not None:
                geoms = vizscene.scene_geoms_from_mujoco(
                    scene.model, scene.data, skip_body_ids=[scene.body_M_id], is_marker=scene.geom_is_marker,
                    T_W_world=T_W_sim,
                )
    viz.log_calibration(
        result, rrd_path=rrd_path, spawn=spawn, scene_geoms=geoms, truth_markers_W=true_markers_W, warn=warn
    )

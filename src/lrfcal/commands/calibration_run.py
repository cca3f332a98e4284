"""Calibrate a recording that has been read, draw the report's figures meanwhile, and write the calibration folder:
the second half of :func:`lrfcal.commands.calibrate.calibrate_folder` (which reads and checks the inputs first, and
imports this module, the method's, only then)."""

from __future__ import annotations

import contextlib
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from lrfcal.commands.calibration_folder import calibration_folder
from lrfcal.config import CalibConfig
from lrfcal.io.truth import truth_dict, truth_frame
from lrfcal.model.kinematics import Params, Pose
from lrfcal.pipeline import calibrate
from lrfcal.report import figures as figure_writer
from lrfcal.report.markdown import render_report
from lrfcal.result import CalibrationResult, Matched, Observer
from lrfcal.runtime.forked import Ahead
from lrfcal.types import Recording


def calibrate_and_write(recording: Recording, config: CalibConfig, out_dir: Path, *, overwrite: bool, truth: Any,
                        rrd_path: Path | None, rrd_inside: str | None, spawn: bool, scene: Any,
                        progress: Callable[[str], None] | None, warn: Callable[[str], None] | None,
                        figures: bool) -> CalibrationResult:
    """Calibrate ``recording`` and write ``out_dir`` atomically (the keywords as in
    :func:`lrfcal.commands.calibrate.calibrate_folder`; ``rrd_inside``: the name of the rerun recording saved inside
    the folder, None for none)."""
    tmp_parent = Path(out_dir).parent if Path(out_dir).parent.exists() else None
    with tempfile.TemporaryDirectory(prefix=".figures-", dir=tmp_parent) as tmp, \
            (Ahead(figure_writer.preload, inherit=(recording.scans,)) if figures else contextlib.nullcontext()) \
            as ahead:
        drawer = _Drawer(ahead, Path(tmp), truth, progress)
        result = calibrate(recording, config, drawer)
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


class _Drawer(Observer):
    """The calibration's observer (lrfcal.result.Observer): the progress (``progress(stage)``), and the report's
    figures, drawn by ``ahead`` (None: no figures), a child forked when the calibration starts that imports
    matplotlib on another core meanwhile and draws each figure into ``folder`` as soon as what it shows is there: the
    intensity image on the association (:meth:`matched`, while the surface returns are fitted), the others once the
    checks have passed (:meth:`fitted`, while the clouds are made), or on the result with its clouds
    (:meth:`the_rest`: targetless's flatness). The child has the scans already (sent by reference)."""

    def __init__(self, ahead: Ahead | None, folder: Path, truth: Any, progress: Callable[[str], None] | None) -> None:
        super().__init__(progress)
        self._ahead, self._folder, self._truth = ahead, folder, truth
        self._sent: list[str] = []  # the figures sent so far ("rest": all the others)

    def matched(self, matched: Matched) -> None:
        """intensity.png once the association is final."""
        if self._ahead is not None:
            self._ahead.start(figure_writer.write_intensity, matched.scans,
                              figure_writer.drawn_detections(matched.detections), matched.association,
                              matched.markers.marker_ids, self._folder)
            self._sent.append("intensity")

    def fitted(self, result: CalibrationResult) -> None:
        """The figures that need no clouds, drawn during the reprojection."""
        if not figure_writer.needs_clouds(result):
            self.the_rest(result)

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

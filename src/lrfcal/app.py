"""Calibrate a recording folder and write the results: the use case behind `lrfcal calibrate` and `lrfsim run`."""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from .pipeline import CalibConfig, calibrate
from .recording import read_recording
from .types import CalibrationResult


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
) -> CalibrationResult:
    """Read, calibrate, write calibration.yaml / rig.urdf / clouds / report / figures atomically; log to rerun.

    ``truth`` (an lrfsim.compare.Truth) adds a truth column to the report and aligns the scene for rerun;
    ``scene`` (an lrfsim.scene.Scene) adds the simulated scene geometry to the rerun recording.
    """
    from . import figures, output

    config = config or CalibConfig()
    recording = read_recording(recording_dir, bag=bag, distances=distances, nominal=nominal)
    result = calibrate(recording, config)
    truth_values = None if truth is None else output.truth_dict(truth)
    with tempfile.TemporaryDirectory(
        prefix=".figures-", dir=out_dir.parent if out_dir.parent.exists() else None
    ) as tmp:
        figs = figures.write_figures(result, Path(tmp))
        report = output.render_report(result, truth=truth_values)
        report += "\n## Figures\n\n" + "\n\n".join(f"![{name}]({p.name})" for name, p in figs.items()) + "\n"
        output.write_calibration(out_dir, result, report_md=report, figures=figs, overwrite=overwrite)
    if rrd_path is not None or spawn:
        _log_rerun(result, rrd_path, spawn, truth, scene)
    return result


def _log_rerun(result: CalibrationResult, rrd_path: Path | None, spawn: bool, truth: Any, scene: Any) -> None:
    from . import viz
    from .kinematics import transform_points
    from .output import truth_dict, truth_frame

    geoms = None
    true_markers_W = None
    if truth is not None:
        found = truth_frame(result, truth_dict(truth))
        if found is not None:
            T_W_sim = found[0]
            true_markers_W = transform_points(T_W_sim, np.array(list(truth.markers.values())))
            if scene is not None:
                geoms = viz.scene_geoms_from_mujoco(
                    scene.model, scene.data, skip_body_ids=[scene.body_M_id], is_marker=scene.geom_is_marker,
                    T_W_world=T_W_sim,
                )
    viz.log_calibration(
        result, rrd_path=rrd_path, spawn=spawn, scene_geoms=geoms, truth_markers_W=true_markers_W
    )

"""The output folder of a calibration: calibration.yaml, rig.urdf, the ROS 2 files (rig_tf.launch.py,
rig_joints.urdf: lrfcal.io.ros_launch), the clouds (PLY), report.md and the figures.

``write_calibration`` (or :func:`calibration_folder`) builds the whole folder in a temporary folder beside it and
renames it into place when complete (:func:`lrfcal.io.files.atomic_folder`), so a reader never sees a partial
result and a failure leaves nothing behind.
"""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import yaml

from lrfcal.errors import InputError
from lrfcal.io.calibration_yaml import calibration_dict
from lrfcal.io.files import atomic_folder, check_replaceable
from lrfcal.io.ply import write_ply
from lrfcal.io.ros_launch import ros_files
from lrfcal.io.urdf import urdf_snippet
from lrfcal.report.markdown import render_report
from lrfcal.result import CalibrationResult


def write_calibration(
    out_dir: str | Path,
    result: CalibrationResult,
    report_md: str | None = None,
    figures: dict[str, Path] | None = None,
    overwrite: bool = False,
) -> Path:
    """Write calibration.yaml, rig.urdf, rig_tf.launch.py, rig_joints.urdf, cloud_before.ply, cloud_after.ply,
    report.md and the figures.

    Everything is written into a temporary folder beside ``out_dir`` that is renamed into place when complete.
    Args:
        report_md: the report text; default :func:`render_report` (without truth).
        figures: name -> existing file; each is copied into the folder under its file name.
        overwrite: replace an existing non-empty ``out_dir`` that this project wrote (see
            :func:`check_replaceable`); otherwise InputError.
    Returns:
        out_dir.
    """
    with calibration_folder(out_dir, result, overwrite) as folder:
        folder.finish(render_report(result) if report_md is None else report_md, figures or {})
    return Path(out_dir)


class CalibrationFolder:
    """The temporary folder of :func:`calibration_folder`, its data files written; :meth:`finish` adds the
    report and the figures."""

    def __init__(self, tmp: Path) -> None:
        self.tmp = tmp

    def finish(self, report_md: str, figures: dict[str, Path]) -> None:
        """Write report.md and copy each figure (name -> existing file) in under its file name."""
        (self.tmp / "report.md").write_text(report_md, encoding="utf-8")
        for name, src in figures.items():
            src = Path(src)
            if not src.is_file():
                raise InputError(f"{src}: figure {name!r} not found")
            shutil.copyfile(src, self.tmp / src.name)


@contextmanager
def calibration_folder(out_dir: str | Path, result: CalibrationResult,
                       overwrite: bool = False) -> Iterator[CalibrationFolder]:
    """:func:`write_calibration` in two steps: calibration.yaml, rig.urdf and the clouds are written on entry
    (e.g. while the figures are drawn elsewhere), the report and figures by the caller's
    :meth:`CalibrationFolder.finish`; the folder is renamed into place on leaving, or removed on an error."""
    out = check_replaceable(out_dir, overwrite)
    with atomic_folder(out, "lrfcal calibrate") as tmp:
        text = yaml.safe_dump(calibration_dict(result), sort_keys=False, default_flow_style=None, width=110)
        (tmp / "calibration.yaml").write_text(text, encoding="utf-8")
        (tmp / "rig.urdf").write_text(urdf_snippet(result.solution.params), encoding="utf-8")
        for name, text in ros_files(result).items():
            (tmp / name).write_text(text, encoding="utf-8")
        write_ply(tmp / "cloud_before.ply", result.cloud_before_M, result.cloud_intensity)
        after_i = result.cloud_intensity if len(result.cloud_intensity) == len(result.cloud_after_M) else None
        write_ply(tmp / "cloud_after.ply", result.cloud_after_M, after_i)
        folder = CalibrationFolder(tmp)
        yield folder
        if not (tmp / "report.md").exists():
            raise RuntimeError("calibration_folder left without finish(): no report.md written")


__all__ = ["CalibrationFolder", "calibration_folder", "write_calibration"]

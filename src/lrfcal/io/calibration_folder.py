"""The output folder of a calibration: calibration.yaml, rig.urdf, the clouds (PLY), report.md and the figures.

``write_calibration`` builds the whole folder in a temporary folder beside it and renames it into place when
complete (:func:`lrfcal.io.files.atomic_folder`), so a reader never sees a partial result and a failure leaves
nothing behind.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import yaml

from ..errors import InputError
from ..types import CalibrationResult
from .calibration_yaml import calibration_dict
from .files import atomic_folder, check_replaceable
from .ply import write_ply
from .report import render_report
from .urdf import urdf_snippet


def write_calibration(
    out_dir: str | Path,
    result: CalibrationResult,
    report_md: str | None = None,
    figures: dict[str, Path] | None = None,
    overwrite: bool = False,
) -> Path:
    """Write calibration.yaml, rig.urdf, cloud_before.ply, cloud_after.ply, report.md and the figures.

    Everything is written into a temporary folder beside ``out_dir`` that is renamed into place when complete.
    Args:
        report_md: the report text; default :func:`render_report` (without truth).
        figures: name -> existing file; each is copied into the folder under its file name.
        overwrite: replace an existing non-empty ``out_dir`` that this project wrote (see
            :func:`check_replaceable`); otherwise InputError.
    Returns:
        out_dir.
    """
    out = check_replaceable(out_dir, overwrite)
    with atomic_folder(out, "lrfcal calibrate") as tmp:
        text = yaml.safe_dump(calibration_dict(result), sort_keys=False, default_flow_style=None, width=110)
        (tmp / "calibration.yaml").write_text(text, encoding="utf-8")
        (tmp / "rig.urdf").write_text(urdf_snippet(result.solution.params), encoding="utf-8")
        write_ply(tmp / "cloud_before.ply", result.cloud_before_M, result.cloud_intensity)
        after_i = result.cloud_intensity if len(result.cloud_intensity) == len(result.cloud_after_M) else None
        write_ply(tmp / "cloud_after.ply", result.cloud_after_M, after_i)
        report = render_report(result) if report_md is None else report_md
        (tmp / "report.md").write_text(report, encoding="utf-8")
        for name, src in (figures or {}).items():
            src = Path(src)
            if not src.is_file():
                raise InputError(f"{src}: figure {name!r} not found")
            shutil.copyfile(src, tmp / src.name)
    return out


__all__ = ["write_calibration"]

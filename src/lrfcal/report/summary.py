"""The terminal summary of a calibration (``lrfcal calibrate`` and ``lrfsim run`` print it): the estimates with
their 1-sigma, the solver status, the residuals, the clock and range offsets and the checks, as a rich table."""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from rich.console import Console

    from lrfcal.result import CalibrationResult


def print_summary(result: CalibrationResult, console: Console) -> None:
    """The estimated parameters with their 1-sigma, the solver status, the residual RMS and stage timings.

    The sigma vector is in :data:`~lrfcal.model.kinematics.ESTIMATE_NAMES` order: the mount rotation is estimated as a
    small rotation vector (rx, ry, rz), so roll, pitch and yaw are shown without a sigma and the rotation's
    1-sigma gets its own rows.
    """
    import math

    from rich.table import Table

    from lrfcal.model.kinematics import ANGLE_NAMES, ESTIMATE_NAMES, PARAM_NAMES
    from lrfcal.report.markdown import residual_summary
    from lrfcal.result import MarkerEvidence, PlaneEvidence

    sol = result.solution
    table = Table(title="Calibration")
    for h in ("parameter", "start", "estimate", "1-sigma", "paper's method"):
        table.add_column(h, justify="right")
    start, est = result.start.vector(), sol.params.vector()
    sigma = [float(v) for v in sol.sigma]
    held_dh: tuple[str, ...]
    match result.evidence:  # with markers: the paper's method beside; targetless: DH only, some held at nominal
        case MarkerEvidence() as ev:
            targetless, held_dh, baseline = False, (), ev.baseline
        case PlaneEvidence() as ev:
            targetless, held_dh, baseline = True, ev.plane_fit.held, None
    paper = None if baseline is None else baseline.params.vector()

    def shown(name: str, v: float) -> str:
        return f"{math.degrees(v):.3f}" if name in ANGLE_NAMES else f"{v * 1000:.3f}"

    def sigma_of(name: str) -> str:
        i = ESTIMATE_NAMES.index(name) if name in ESTIMATE_NAMES else -1
        if not 0 <= i < len(sigma):
            return "-"  # roll, pitch, yaw: the rotation's sigma is rx, ry, rz's
        return shown(name, sigma[i]) if math.isfinite(sigma[i]) else "held"  # not estimated: no sigma

    for i, n in enumerate(PARAM_NAMES):
        if targetless and i < 6:
            continue  # no world frame: the mount is not estimated
        unit = "deg" if n in ANGLE_NAMES else "mm"
        table.add_row(f"{n} ({unit})", shown(n, start[i]), shown(n, est[i]) + (" (held)" if n in held_dh else ""),
                      sigma_of(n), "-" if paper is None else shown(n, paper[i]))
    for n in ESTIMATE_NAMES:
        if n not in PARAM_NAMES and not targetless:  # rx, ry, rz: the rotation's uncertainty about M's axes
            table.add_row(f"{n} (deg)", "", "", sigma_of(n), "")
    console.print(table)
    if targetless:
        console.print("targetless: DH parameters from the scene's planes; the mount pose is not estimated (no world "
                      "frame without markers)", markup=False)
    else:
        console.print("rx, ry, rz: 1-sigma of the mount rotation about the motor frame's x, y, z axes", markup=False)
    console.print(f"solver: {' '.join(str(sol.status).split())} ({sol.n_iterations} iterations)",
                  markup=False)
    console.print(f"{residual_summary(result)}; stages: "
                  + ", ".join(f"{k} {v:.2f}s" for k, v in result.timings_s.items()), markup=False)
    held = not math.isfinite(sol.clock_offset_sigma_s)
    console.print(f"clock offset (laser - servo): {sol.clock_offset_s * 1000:+.2f} ms"
                  + (" (held, not estimated)" if held else f" +- {sol.clock_offset_sigma_s * 1000:.2f} ms (estimated)"),
                  markup=False)
    if math.isfinite(sol.range_offset_sigma_m):
        console.print(f"range offset {sol.range_offset_m * 1000:+.2f} +- {sol.range_offset_sigma_m * 1000:.2f} mm, "
                      f"marker range bias {sol.marker_range_bias_m * 1000:+.2f} +- "
                      f"{sol.marker_range_bias_sigma_m * 1000:.2f} mm (estimated)", markup=False)
    if result.checks:
        console.print("checks: " + "; ".join(f"{c.name} {'ok' if c.passed else 'FAILED'}" for c in result.checks)
                      + " (numbers in report.md)", markup=False)
    for c in result.checks:
        if not c.passed:
            console.print(f"FAILED check (written because of --force): {c.name}: {c.detail}", markup=False)
    for note in result.notes:
        console.print(f"note: {note}", markup=False)


# --- real rigs' bags: inspect and reproject (issue 8) -------------------------------------------------------


__all__ = ["print_summary"]

"""report.md: the calibration report as Markdown (parameters with sigma, the paper's baseline, the truth when
known, checks, notes, per-marker residuals or the scene's planes, the methods side by side, tunnel geometry,
timings), and the one line on the residuals that the terminal shows too.

Frames: W is the marker frame (from the tape distances), M the motor frame.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np

from lrfcal.io.calibration_yaml import map_sigma, param_sigma
from lrfcal.io.calibration_yaml import plain_float as _f
from lrfcal.io.truth import truth_frame
from lrfcal.model.kinematics import ANGLE_NAMES, DH_NAMES, ESTIMATE_NAMES, MOUNT_NAMES, PARAM_NAMES, Pose
from lrfcal.model.noise import RHO_Z, shown
from lrfcal.result import CalibrationResult, MarkerEvidence, PlaneEvidence
from lrfcal.types import Solution

TUNNEL_KEYS = ("width_m", "height_m", "plate_distance_m")


def _disp(name: str, v: float | None) -> str:
    """Value in display units: mm for lengths, deg for angles."""
    if v is None or not math.isfinite(v):
        return "-"
    return f"{math.degrees(v):.3f}" if name in ANGLE_NAMES else f"{v * 1000:.2f}"


def _sigma_disp(sol: Solution, name: str) -> str:
    """A parameter's 1-sigma in display units; "held" for an estimated kind of parameter that was not estimated
    (no finite sigma), "-" for roll, pitch and yaw (the rotation's sigma is rx, ry, rz's)."""
    sigma = param_sigma(sol, name)
    return "held" if name in ESTIMATE_NAMES and sigma is None else _disp(name, sigma)


def _unit(name: str) -> str:
    return "deg" if name in ANGLE_NAMES else "mm"


def _truth_params(result: CalibrationResult, truth: dict[str, Any]) -> tuple[dict[str, float | None], str]:
    """Truth in PARAM_NAMES, the mount re-expressed in the marker frame W when the truth's markers allow
    aligning the simulator frame to W (else None for the mount); and a note on how (or why not)."""
    out: dict[str, float | None] = dict.fromkeys(PARAM_NAMES)
    dh = truth.get("dh") or {}
    for n in DH_NAMES:
        if n in dh:
            out[n] = float(dh[n])
    mount = truth.get("mount")
    if mount is None:
        return out, ""
    if isinstance(result.evidence, PlaneEvidence):
        return out, "Mount truth not shown: a targetless calibration has no world frame (the mount is not estimated)."
    fit = truth_frame(result, truth)
    if fit is None:
        return out, "Mount truth not shown: the simulator frame could not be aligned to the marker frame W."
    T_W_sim, how = fit
    p = Pose.from_matrix(T_W_sim @ Pose(**{k: float(mount[k]) for k in MOUNT_NAMES}).matrix())
    for n in MOUNT_NAMES:
        out[n] = getattr(p, n)
    return out, (f"Mount truth re-expressed in the marker frame W (true marker positions fitted to the tape map "
                 f"{how}).")


def _tunnel_truth(truth: dict[str, Any] | None) -> dict[str, float | None]:
    t = None if truth is None else truth.get("tunnel")
    if t is None:
        return dict.fromkeys(TUNNEL_KEYS)
    get = t.get if isinstance(t, dict) else (lambda k: getattr(t, k, None))
    return {k: _f(get(k)) for k in TUNNEL_KEYS}


def _angle_err(n: str, est: float, ref: float) -> float:
    d = est - ref
    return (d + math.pi) % (2 * math.pi) - math.pi if n in ANGLE_NAMES else d


def residual_summary(result: CalibrationResult) -> str:
    """One line, the same in the terminal and the report: residual RMS over the marker returns and markers used."""
    sol = result.solution
    match result.evidence:
        case MarkerEvidence() as ev:
            n_markers = int((ev.marker_counts() > 0).sum())
            return (f"residual RMS {sol.residual_rms_m * 1000:.2f} mm over {sol.n_observations} marker returns on "
                    f"{n_markers} of {len(ev.markers.marker_ids)} markers")
        case PlaneEvidence() as ev:
            return (f"plane residual RMS {sol.residual_rms_m * 1000:.2f} mm over {sol.n_surface_returns} returns on "
                    f"{len(ev.plane_fit.planes)} planes of the scene (targetless)")


def _marker_lines(sol: Solution, ev: MarkerEvidence) -> list[str]:
    """The report's summary lines on the markers, blobs and tape."""
    counts = ev.marker_counts()
    markers, ids = ev.markers, ev.markers.marker_ids
    lines = [
        f"- markers used: {int((counts > 0).sum())} of {len(ids)} "
        f"({', '.join(i for i, c in zip(ids, counts, strict=True) if c > 0) or 'none'})",
        f"- blobs detected: {len(ev.detections.blobs)}, matched to markers: {ev.association.n_matched}"
        f"{' (marker map mirrored)' if ev.association.mirrored else ''}",
        f"- marker map from the tape: RMS {markers.rms_m * 1000:.2f} mm, stress {markers.stress:.2g}"
        f"{', coplanar layout' if markers.coplanar else ''}; tape noise "
        f"{markers.tape_sigma_m * 1000:.2f} mm, which through the map makes "
        + ", ".join(f"{n} {_disp(n, v)} {_unit(n)}" for n, v in map_sigma(sol, markers).items())
        + " of the 1-sigma (in variance)",
    ]
    rho, pairs = sol.range_correlation
    if pairs:
        lines.append(f"- range noise along the scan: neighbouring beams correlate {rho:.2f} (from {pairs} pairs of "
                     "marker returns; " + ("held in the covariance)" if shown(rho, pairs) else
                                          f"within {RHO_Z:g} standard errors of 0: taken as 0)"))
    for p in markers.dropped_pairs:
        lines.append(f"- tape pair {p.id_i}-{p.id_j} dropped: measured {p.measured_m:.3f} m, the other pairs put it "
                     f"at {p.predicted_m:.3f} m ({p.error_m * 1000:+.0f} mm); re-measure it")
    if ev.baseline is not None:
        lines.append(f"- baseline (paper method) residual RMS: {ev.baseline.residual_rms_m * 1000:.2f} mm "
                     f"over {ev.baseline.n_observations} returns")
    return lines


def _per_marker_lines(sol: Solution, ev: MarkerEvidence) -> list[str]:
    counts = ev.marker_counts()
    lines = ["", "## Per-marker residuals", "", "| marker | returns | RMS [mm] |", "|---|---|---|"]
    per = np.asarray(sol.per_marker_rms_m, dtype=float).reshape(-1)
    for i, mid in enumerate(ev.markers.marker_ids):
        v = per[i] if i < per.size else float("nan")
        lines.append(f"| {mid} | {int(counts[i])} | {f'{v * 1000:.2f}' if math.isfinite(v) else '-'} |")
    return lines


def _side_by_side_lines(result: CalibrationResult, truth: dict[str, float | None] | None) -> list[str]:
    """The DH estimates of every method run on this recording, with their 1-sigma (and the truth when known)."""
    if len(result.side_by_side) < 3:
        return []
    lines = ["", "## The methods side by side (DH: estimate +- 1-sigma)", "",
             "| method | " + " | ".join(f"{n} [{_unit(n)}]" for n in DH_NAMES) + " |", "|---|---|---|---|---|"]
    for name, sol in result.side_by_side.items():
        est = sol.params.as_dict()
        lines.append(f"| {name} | " + " | ".join(f"{_disp(n, est[n])} +- {_sigma_disp(sol, n)}"
                                                 for n in DH_NAMES) + " |")
    if truth is not None:
        lines.append("| truth | " + " | ".join(_disp(n, truth.get(n)) for n in DH_NAMES) + " |")
    return lines


def _plane_lines(ev: PlaneEvidence) -> list[str]:
    """The scene's planes and their thickness (RMS distance of their returns from their best-fit plane) with
    the nominal and with the calibrated DH parameters."""
    fit = ev.plane_fit
    lines = ["", "## The scene's planes (frame M)", "",
             "| plane | normal | offset [m] | returns | thickness before [mm] | after [mm] |",
             "|---|---|---|---|---|---|"]
    for k, (p, n, b, a) in enumerate(zip(fit.planes, fit.n_returns, fit.rms_before_m, fit.rms_after_m,
                                         strict=True)):
        lines.append(f"| {k} | ({p.normal[0]:+.3f}, {p.normal[1]:+.3f}, {p.normal[2]:+.3f}) | {p.offset_m:.3f} | "
                     f"{int(n)} | {b * 1000:.2f} | {a * 1000:.2f} |")
    from lrfcal.stages.planes import squareness_deg

    sq_b, sq_a = squareness_deg(fit.normals_before), squareness_deg(fit.normals_after)
    if sq_b.size:
        lines += ["", f"Corners (pairs of planes within 20 deg of perpendicular, {sq_b.size}): mean |90 deg - angle| "
                  f"{sq_b.mean():.3f} deg with the nominal DH, {sq_a.mean():.3f} deg calibrated (a box's walls are "
                  "square to within its build)."]
    return lines


class _Way(NamedTuple):
    """The parts of the report that depend on the evidence: the title's suffix, the summary lines, the parameters
    shown, those held at nominal, the paper's baseline, the lines on the frames, and the closing section."""

    title: str
    summary: list[str]
    names: tuple[str, ...]
    held: tuple[str, ...]
    baseline: Solution | None
    frames: list[str]
    closing: list[str]


def _way(result: CalibrationResult) -> _Way:
    """The report's parts that depend on the result's evidence (markers or the scene's planes)."""
    sol = result.solution
    match result.evidence:
        case MarkerEvidence() as ev:
            rot = [param_sigma(sol, n) for n in ("rx", "ry", "rz")]
            frames = ["", "The mount's rotation is estimated on SO(3): its 1-sigma is that of a small rotation vector "
                      "in frame M, (rx, ry, rz) = (" + ", ".join(_disp("rx", v) for v in rot) + ") deg; roll, pitch "
                      "and yaw are the same rotation written as URDF angles (no sigma: theirs would come from the "
                      "Euler angles' singularity)."]
            return _Way("", _marker_lines(sol, ev), PARAM_NAMES, (), ev.baseline, frames, _per_marker_lines(sol, ev))
        case PlaneEvidence() as ev:
            held = ev.plane_fit.held
            summary = ([f"- held at the nominal value (the scene does not determine them): {', '.join(held)}"]
                       if held else [])
            frames = ["", "Without markers there is no world frame: the mount pose is not estimated."]
            return _Way(" (targetless: the scene's planes, no markers)", summary, DH_NAMES, held, None, frames,
                        _plane_lines(ev))


def render_report(result: CalibrationResult, truth: dict[str, Any] | None = None) -> str:
    """The calibration report as Markdown: parameters with sigma (and the paper's baseline, the start values
    and, given ``truth`` as loaded from ground_truth.yaml, the truth and the errors), per-marker residuals or the
    scene's planes, tunnel geometry before/after."""
    sol = result.solution
    est = sol.params.as_dict()
    start = result.start.as_dict()
    way = _way(result)
    base = way.baseline.params.as_dict() if way.baseline is not None else None
    tp, truth_note = _truth_params(result, truth) if truth is not None else (None, "")
    lines = ["# Rotating LRF calibration" + way.title,
             "", f"- status: {sol.status} ({sol.n_iterations} iterations)", f"- {residual_summary(result)}",
             *way.summary]
    lines += ["", "## Parameters", ""]
    head = ["parameter", "unit", "start", "estimate", "sigma"]
    if base is not None:
        head.append("baseline (paper)")
    if tp is not None:
        head += ["truth", "error"] + (["baseline error"] if base is not None else [])
    lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for n in way.names:
        row = [n, _unit(n), _disp(n, start[n]), _disp(n, est[n]) + (" (held)" if n in way.held else ""),
               _sigma_disp(sol, n)]
        if base is not None:
            row.append(_disp(n, base[n]))
        if tp is not None:
            t = tp[n]
            row += [_disp(n, t), _disp(n, None if t is None else _angle_err(n, est[n], t))]
            if base is not None:
                row.append(_disp(n, None if t is None else _angle_err(n, base[n], t)))
        lines.append("| " + " | ".join(row) + " |")
    lines += way.frames
    if math.isfinite(sol.clock_offset_sigma_s):
        lines.append(f"Clock offset (laser stamp - servo stamp): {sol.clock_offset_s * 1000:+.2f} ms, 1-sigma "
                     f"{sol.clock_offset_sigma_s * 1000:.2f} ms (estimated).")
    else:
        lines.append(f"Clock offset (laser stamp - servo stamp): {sol.clock_offset_s * 1000:+.2f} ms (held, not "
                     "estimated).")
    if math.isfinite(sol.range_offset_sigma_m):
        lines.append(f"Range offset (every return): {sol.range_offset_m * 1000:+.2f} +- "
                     f"{sol.range_offset_sigma_m * 1000:.2f} mm; marker-return range bias: "
                     f"{sol.marker_range_bias_m * 1000:+.2f} +- {sol.marker_range_bias_sigma_m * 1000:.2f} mm "
                     "(estimated).")
    if truth_note:
        lines += ["", truth_note]
    if result.checks:
        lines += ["", "## Checks", "", "| check | result | numbers |", "|---|---|---|"]
        lines += [f"| {c.name} | {'passed' if c.passed else '**FAILED**'} | {c.detail} |" for c in result.checks]
    if result.notes:
        lines += ["", "## Notes", ""] + [f"- {n}" for n in result.notes]

    lines += way.closing
    lines += _side_by_side_lines(result, tp)

    g0, g1 = result.geometry_before, result.geometry_after
    if g0 is not None or g1 is not None or (truth is not None and truth.get("tunnel")):
        tt = _tunnel_truth(truth)
        head = ["quantity", "before [m]", "after [m]"]
        if truth is not None:
            head += ["truth [m]", "error before [mm]", "error after [mm]"]
        lines += ["", "## Tunnel geometry (RANSAC planes in the reprojected cloud)", "",
                  "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        for k, label in zip(TUNNEL_KEYS, ("width (wall to wall)", "height (floor to ceiling)",
                                          "distance to the plate"), strict=True):
            b = None if g0 is None else _f(getattr(g0, k))
            a = None if g1 is None else _f(getattr(g1, k))
            row = [label, "-" if b is None else f"{b:.4f}", "-" if a is None else f"{a:.4f}"]
            if truth is not None:
                t = tt[k]
                row.append("-" if t is None else f"{t:.4f}")
                for v in (b, a):
                    row.append("-" if v is None or t is None else f"{(v - t) * 1000:+.1f}")
            lines.append("| " + " | ".join(row) + " |")
    if result.timings_s:
        lines += ["", "## Timings", "", "| stage | s |", "|---|---|"]
        lines += [f"| {k} | {v:.3f} |" for k, v in result.timings_s.items()]
    return "\n".join(lines) + "\n"


__all__ = ["TUNNEL_KEYS", "render_report", "residual_summary"]

"""PNG figures of a calibration a person can look at (the seed paper's Figs. 8/9, 11/12 and residual plots).

matplotlib is imported inside the functions and only its object API is used (``matplotlib.figure.Figure``
rendered by the Agg canvas), so no pyplot state or GUI backend is involved. Every figure is written at
WIDTH_PX x HEIGHT_PX pixels (DPI dots per inch) to a temporary file in the target folder, then renamed.

Residuals are those of :mod:`lrfcal.report.vizdata`: each reprojected marker return to the nearest point of its marker
sphere, with the start parameters ("before") and the calibrated ones ("after").
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from lrfcal.model.kinematics import Params
from lrfcal.report.figintensity import C_MARKER, intensity_figure
from lrfcal.report.figlayout import (
    DPI,
    FONT_SIZE_PT,
    HEIGHT_PX,
    LABEL_EM,
    WIDTH_PX,
    new_figure,
    rc,
    save,
    three_ticks,
    view_frame,
)
from lrfcal.report.vizdata import marker_returns
from lrfcal.result import CalibrationResult, MarkerEvidence, PlaneEvidence
from lrfcal.types import Association, Detections, Scans

FloatArray = NDArray[np.float64]

_C_BEFORE = "#e6781e"
_C_AFTER = "#28aa50"


def _rms_mm(norms_m: FloatArray) -> float:
    return float(np.sqrt(np.mean(norms_m**2)) * 1e3) if norms_m.size else float("nan")


#: At most this many per-marker panels in alignment.png (the markers with the most returns).
MAX_MARKER_PANELS = 35


def alignment_figure(result: CalibrationResult, evidence: MarkerEvidence, path: Path | str,
                     before: Params | None = None, before_label: str = "nominal DH, fitted mount") -> Path:
    """Per-marker close-ups of the reprojected marker returns (``result``'s ``evidence``), before and after
    calibration (paper Figs. 11/12).

    One small panel per marker (the same scale in all, in mm, so the whole layout never projects markers onto
    each other): the returns of that marker reprojected into W with ``before`` (default: the calibration's
    start, i.e. the nominal DH with the mount fitted to the markers) and with the calibrated parameters,
    seen from the motor: coordinates in the plane perpendicular to the ray from the motor origin to the
    marker centre (u to the right, v up), relative to the marker centre; the circle is the marker sphere.
    Lateral offsets there are what the calibration corrects. Returns the written path.
    """
    from matplotlib.lines import Line2D

    markers = np.asarray(evidence.markers.positions_W, dtype=float)
    ids = evidence.markers.marker_ids
    r_mm = float(result.recording.nominal.marker_radius_m) * 1e3
    before = before if before is not None else result.start
    eye = np.asarray(result.solution.params.mount.matrix(), dtype=float)[:3, 3]
    stages = {}
    for name, params in (("before", before), ("after", result.solution.params)):
        p, to_m, mk, _ = marker_returns(result, evidence, params, calibrated=name == "after")
        stages[name] = (p, mk, np.linalg.norm(to_m, axis=1))
    counts = np.bincount(stages["after"][1], minlength=len(ids)) if len(ids) else np.zeros(0, int)
    shown = [int(i) for i in np.argsort(-counts, kind="stable")[:MAX_MARKER_PANELS] if counts[i] > 0]
    shown.sort()
    local: dict[tuple[str, int], FloatArray] = {}
    extent = 2.0 * r_mm
    for m in shown:
        u, v = view_frame(markers[m], eye)
        for name, (p, mk, _) in stages.items():
            d = (p[mk == m] - markers[m]) * 1e3
            q = np.stack([d @ u, d @ v], axis=1)
            local[(name, m)] = q
            if q.size and name == "after":
                extent = max(extent, float(np.percentile(np.abs(q), 98)))
    extent *= 1.3  # zoomed on the calibrated returns; "before" returns beyond it are shown by an arrow
    n = max(len(shown), 1)
    cols = int(np.ceil(np.sqrt(n * WIDTH_PX / HEIGHT_PX)))
    rows = int(np.ceil(n / cols))
    # every panel in one axes, at its own offset (one matplotlib axes per marker cost most of this figure's time:
    # their ticks and frames), in mm; the panels' pitch leaves room for the titles and tick labels
    box = (0.03, 0.12, 0.96, 0.8)  # the axes in the figure (left, bottom, width, height)
    aspect = box[2] * WIDTH_PX / (box[3] * HEIGHT_PX)
    pitch = np.array([max(2.5, aspect * 3.0 * (rows + 0.05) / (cols + 0.2)), 3.0]) * extent  # fills the axes
    C = np.array([(k % cols, -(k // cols)) for k in range(len(shown))], dtype=float).reshape(-1, 2) * pitch
    centres = dict(zip(shown, C, strict=True))  # marker -> its panel's centre (2,) [mm]
    rms = {(name, m): _rms_mm(stages[name][2][stages[name][1] == m]) for name in stages for m in shown}
    titles = {m: f"{ids[m]}: {rms[('before', m)]:.1f} -> {rms[('after', m)]:.1f} mm" for m in shown}
    # the panels fill the axes' width (the pitch above): a title is as wide as its panel's pitch at most
    title_pt = min(FONT_SIZE_PT - 2.0, 0.95 * box[2] / (cols + 0.2) / (LABEL_EM * max(map(len, titles.values()),
                                                                                         default=1)))
    with rc():
        fig = new_figure(constrained=False)
        ax = fig.add_axes(box)
        ax.set_axis_off()
        ax.set_xlim(-0.7 * pitch[0], (cols - 0.5) * pitch[0])
        ax.set_ylim(-(rows - 0.55) * pitch[1], 0.6 * pitch[1])
        ax.set_aspect("equal", adjustable="box")
        _panel_frames(ax, list(C), extent, three_ticks(extent), cols, len(shown))
        if shown:
            ring = np.linspace(0.0, 2.0 * np.pi, 65)
            circle = np.vstack([r_mm * np.c_[np.cos(ring), np.sin(ring)], [np.nan, np.nan]])  # NaN: the pen lifted
            xy = np.vstack([c + circle for c in C])
            ax.plot(xy[:, 0], xy[:, 1], color=C_MARKER, linewidth=1.5)
            ax.plot(C[:, 0], C[:, 1], "+", color=C_MARKER, markersize=6)
        arrows = 0
        for name, color in (("before", _C_BEFORE), ("after", _C_AFTER)):
            pts = [local[(name, m)][(np.abs(local[(name, m)]) <= extent).all(axis=1)] + centres[m] for m in shown]
            xy = np.vstack(pts) if pts else np.zeros((0, 2))
            ax.scatter(xy[:, 0], xy[:, 1], s=6, color=color, alpha=0.7, linewidths=0)
        for m in shown:
            q, c = local[("before", m)], centres[m]
            if len(q) and (np.abs(q) > extent).any(axis=1).sum() > 0.5 * len(q):  # most "before" returns off the panel
                arrows += 1
                mid = np.median(q, axis=0)
                tip = mid / max(float(np.abs(mid).max()), 1e-9) * 0.92 * extent
                ax.annotate("", xy=c + tip, xytext=c + tip * 0.35,
                            arrowprops={"arrowstyle": "-|>", "color": _C_BEFORE, "lw": 1.8})
                ax.text(*(c + tip * 0.3), f"{float(np.linalg.norm(mid)):.0f} mm", color=_C_BEFORE,
                        fontsize=FONT_SIZE_PT - 3, ha="center", va="center",
                        bbox={"fc": "white", "ec": "none", "alpha": 0.7, "pad": 0.5})
            ax.text(c[0], c[1] + 1.08 * extent, titles[m], fontsize=title_pt, ha="center", va="bottom")
        rb, ra = (_rms_mm(stages[k][2]) for k in ("before", "after"))
        handles = [Line2D([], [], ls="", marker="o", color=_C_BEFORE, label=f"before ({before_label}): RMS {rb:.1f} mm"
                          + (" (arrow: towards returns off the panel)" if arrows else "")),
                   Line2D([], [], ls="", marker="o", color=_C_AFTER, label=f"after (calibrated): RMS {ra:.1f} mm"),
                   Line2D([], [], ls="", marker="o", mfc="none", mec=C_MARKER, markersize=9,
                          label=f"marker (r = {r_mm:g} mm)")]
        fig.legend(handles=handles, loc="lower center", bbox_to_anchor=(0.5, 0.0), ncols=3, fontsize=FONT_SIZE_PT - 2,
                   frameon=False)
        fig.suptitle("Returns per marker seen from the motor [mm] (u across the ray, v up; RMS before -> after)",
                     fontsize=FONT_SIZE_PT + 1)
        return save(fig, path)


def _panel_frames(ax: Any, centres: list[FloatArray], extent: float, ticks: list[float], cols: int, n: int) -> None:
    """alignment.png's panels drawn into one axes ``ax``: each a square of half-width ``extent`` [mm] about its
    centre (2,) with grid lines at ``ticks``, the tick labels on the left column and below the last panel of each
    column (``cols`` columns, ``n`` panels)."""
    from matplotlib.collections import LineCollection

    frames, grid = [], []
    for k, c in enumerate(centres):
        lo, hi = c - extent, c + extent
        frames.append([(lo[0], lo[1]), (hi[0], lo[1]), (hi[0], hi[1]), (lo[0], hi[1]), (lo[0], lo[1])])
        for t in ticks:
            grid += [[(c[0] + t, lo[1]), (c[0] + t, hi[1])], [(lo[0], c[1] + t), (hi[0], c[1] + t)]]
        size = FONT_SIZE_PT - 3
        if k % cols == 0:
            for t in ticks:
                ax.text(lo[0] - 0.08 * extent, c[1] + t, f"{t:g}", fontsize=size, ha="right", va="center")
        if k + cols >= n:
            for t in ticks:
                ax.text(c[0] + t, lo[1] - 0.08 * extent, f"{t:g}", fontsize=size, ha="center", va="top")
    ax.add_collection(LineCollection(grid, colors="0.85", linewidths=0.6))
    ax.add_collection(LineCollection(frames, colors="black", linewidths=0.8))


def _plain(v: float, _pos: object = None) -> str:
    """Tick label without powers of ten: 0.5, 2, 10, 200."""
    return f"{v:g}"


def residual_figure(result: CalibrationResult, evidence: MarkerEvidence, path: Path | str,
                    before: Params | None = None, before_label: str = "nominal DH, fitted mount") -> Path:
    """Histogram of residual norms [mm] before/after (log bins) and per-marker RMS [mm] as grouped bars.

    A return inside its marker sphere has residual 0 (see :func:`lrfcal.report.vizdata.marker_returns`); those cannot
    sit
    on a log axis, so they are counted in the legend instead of drawn. ``before`` as in
    :func:`alignment_figure`.
    """
    from matplotlib.ticker import FuncFormatter, LogLocator, MaxNLocator, NullLocator

    def ticks_125(axis: Any, lo: float, hi: float) -> None:
        """A log axis's ticks at 1, 2, 5 x 10^k (over more than 2.5 decades: 10^k), no minor ticks (they were half
        the figure's time)."""
        axis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0) if hi < 10**2.5 * lo else (1.0,)))
        axis.set_minor_locator(NullLocator())
        axis.set_major_formatter(FuncFormatter(_plain))

    ids = evidence.markers.marker_ids
    n = len(ids)
    data = {}
    for name, params in (("before", before if before is not None else result.start),
                         ("after", result.solution.params)):
        _, to_m, mk, _ = marker_returns(result, evidence, params, calibrated=name == "after")
        norms_mm = np.linalg.norm(to_m, axis=1) * 1e3
        per = np.array([_rms_mm(norms_mm[mk == m] / 1e3) for m in range(n)])
        data[name] = (norms_mm, per)
    allv = np.concatenate([d[0] for d in data.values()])
    allv = allv[np.isfinite(allv) & (allv > 0)]
    lo = max(float(allv.min()) if allv.size else 0.01, 1e-3)
    hi = max(float(allv.max()) if allv.size else 1.0, lo * 10)
    bins = np.geomspace(lo / 1.2, hi * 1.2, 40)

    with rc():
        fig = new_figure(constrained=False)  # a fixed layout: constrained layout was half of this figure's time
        rotate = n > 12
        fig.subplots_adjust(left=0.055, right=0.99, bottom=0.15 if rotate else 0.11, top=0.885, wspace=0.15)
        ax_h, ax_b = fig.subplots(1, 2, width_ratios=[1, 1.2])
        for name, (norms_mm, _) in data.items():
            color = _C_BEFORE if name == "before" else _C_AFTER
            finite = norms_mm[np.isfinite(norms_mm)]
            v = finite[finite > 0]
            inside = int(finite.size - v.size)
            med = float(np.median(norms_mm)) if norms_mm.size else float("nan")
            ax_h.hist(v, bins=bins, color=color, alpha=0.6, histtype="stepfilled",
                      label=f"{name}: RMS {_rms_mm(norms_mm / 1e3):.1f}, median {med:.1f} mm; {inside} at 0")
        ax_h.set_xscale("log")
        ticks_125(ax_h.xaxis, bins[0], bins[-1])
        ax_h.yaxis.set_major_locator(MaxNLocator(integer=True))
        ax_h.set_xlabel("distance of a return to its marker sphere [mm] (0: inside, not drawn)")
        ax_h.set_ylabel("number of marker returns")
        ax_h.set_title(f"residual norms (K = {data['after'][0].size} returns)")
        ax_h.legend(loc="upper left", fontsize=FONT_SIZE_PT - 2)
        ax_h.grid(True, alpha=0.3)

        x = np.arange(n)
        w = 0.4
        for k, (name, (_, per)) in enumerate(data.items()):
            color = _C_BEFORE if name == "before" else _C_AFTER
            bars = ax_b.bar(x + (k - 0.5) * w, np.nan_to_num(per), width=w, color=color,
                            label=name if name == "after" else f"before ({before_label})")
            if n <= 16:
                ax_b.bar_label(bars, labels=[f"{v:.1f}" if np.isfinite(v) else "" for v in per],
                               fontsize=FONT_SIZE_PT - 2, padding=2)
        ax_b.set_xticks(x, list(ids), rotation=45 if rotate else 0, ha="right" if rotate else "center")
        ax_b.set_xlabel("marker")
        ax_b.set_ylabel("RMS residual [mm]")
        pos = np.r_[data["before"][1], data["after"][1]]
        pos = pos[np.isfinite(pos) & (pos > 0)]
        if pos.size:
            ax_b.set_yscale("log")
            ax_b.set_ylim(pos.min() / 3.0, pos.max() * 2.0)
            ticks_125(ax_b.yaxis, pos.min() / 3.0, pos.max() * 2.0)
        ax_b.set_title("per-marker RMS (markers without returns: no bar)")
        ax_b.legend(loc="upper right")
        ax_b.grid(True, axis="y", alpha=0.3)
        fig.suptitle("Marker residuals before / after calibration", fontsize=FONT_SIZE_PT + 2)
        return save(fig, path)


def flatness_figure(result: CalibrationResult, evidence: PlaneEvidence, path: Path | str) -> Path:
    """A targetless calibration's figure: each plane's thickness (RMS distance of its returns from their best-fit
    plane) with the nominal and with the calibrated DH parameters (left: one row per plane, the two values joined,
    the axis spanning the values rather than starting at 0, so that a sub-millimetre change shows; the change
    written beside each row), and the calibrated cloud seen along the motor axis (right, frame M). Returns the
    written path."""
    fit = evidence.plane_fit
    before_mm = np.asarray(fit.rms_before_m, dtype=float) * 1e3
    after_mm = np.asarray(fit.rms_after_m, dtype=float) * 1e3
    n = len(fit.planes)
    with rc():
        labels = [f"plane {i} ({int(c)} returns)" for i, c in zip(range(n), fit.n_returns, strict=True)]
        # a fixed layout (constrained layout was most of this figure's time): room on the left for the labels
        fig = new_figure(constrained=False)
        left = min(0.35, 0.025 + LABEL_EM * (FONT_SIZE_PT - 1) * max(map(len, labels), default=0))
        fig.subplots_adjust(left=left, right=0.985, bottom=0.1, top=0.86, wspace=0.22)
        ax, ax2 = fig.subplots(1, 2, width_ratios=(1.2, 1.0))
        k = np.arange(n)
        ax.hlines(k, np.fmin(before_mm, after_mm), np.fmax(before_mm, after_mm), color="0.6", linewidth=2)
        ax.plot(before_mm, k, "o", color=_C_BEFORE, markersize=8, label="nominal DH")
        ax.plot(after_mm, k, "o", color=_C_AFTER, markersize=8, label="calibrated DH")
        values = np.r_[before_mm, after_mm]
        values = values[np.isfinite(values)]
        if values.size:
            lo, hi = float(values.min()), float(values.max())
            pad = max(0.15 * (hi - lo), 0.02 * hi, 1e-3)
            ax.set_xlim(lo - pad, hi + 3 * pad)  # room on the right for the change
        for i in range(n):
            d = after_mm[i] - before_mm[i]
            if np.isfinite(d):
                ax.annotate(f"{d:+.2f} mm", (max(before_mm[i], after_mm[i]), i), xytext=(8, 0),
                            textcoords="offset points", va="center", fontsize=FONT_SIZE_PT - 2,
                            color=_C_AFTER if d < -0.005 else (_C_BEFORE if d > 0.005 else "0.4"))
        ax.set_yticks(k, labels)
        ax.set_ylim(n - 0.5, -0.5)
        ax.set_xlabel("thickness: RMS distance of its returns from the plane [mm]")
        ax.set_title("Flatness of the scene's planes, nominal -> calibrated", pad=28)
        ax.grid(True, axis="x", alpha=0.3)
        ax.legend(loc="lower center", bbox_to_anchor=(0.5, 1.0), ncols=2, frameon=False)
        cloud = _cloud_view(result.cloud_after_M)
        ax2.scatter(cloud[:, 0], cloud[:, 1], s=0.2, c="0.3", rasterized=True)
        ax2.set_aspect("equal")
        ax2.set_xlabel("x_M [m]")
        ax2.set_ylabel("y_M [m]")
        ax2.set_title("Calibrated cloud, seen along\nthe motor axis (frame M)")
        return save(fig, path)


@dataclass(frozen=True)
class Figures:
    """The figures written (name -> path) and those that could not be drawn (name -> reason, for the report)."""

    written: dict[str, Path]
    skipped: dict[str, str]

    def __or__(self, other: Figures) -> Figures:
        return Figures({**self.written, **other.written}, {**self.skipped, **other.skipped})

    @staticmethod
    def of(outcomes: dict[str, tuple[bool, str]]) -> Figures:
        """From each figure's :func:`_attempt` outcome (name -> (drawn, path or reason))."""
        return Figures({n: Path(v) for n, (ok, v) in outcomes.items() if ok},
                       {n: v for n, (ok, v) in outcomes.items() if not ok})


def write_figures(result: CalibrationResult, out_dir: Path | str, before: Params | None = None,
                  before_label: str = "nominal DH, fitted mount", drawn: tuple[str, ...] = ()) -> Figures:
    """Write intensity.png, alignment.png and residuals.png (targetless: flatness.png) into out_dir, but for the
    figures named in ``drawn`` (drawn before, e.g. intensity by :func:`write_intensity`).

    ``before``: the parameters of the "before" views, described by ``before_label`` (default: the calibration's
    start, the nominal DH with the mount fitted to the markers: a nominal mount has no place in W, the tape's frame,
    unless the true marker positions are known, see lrfcal.commands.calibration_run's ``_nominal_in_W``).

    A figure is an aid, the result exists without it: a figure that cannot be drawn (an exception while drawing
    it, whatever the recording) is skipped and its reason returned, never raised after the calibration is done.
    """
    out = Path(out_dir)
    draw: dict[str, Callable[[], Path]]
    match result.evidence:
        case PlaneEvidence() as planes:
            draw = {"flatness": lambda: flatness_figure(result, planes, out / "flatness.png")}
        case MarkerEvidence() as marks:
            draw = {"intensity": lambda: intensity_figure(result.recording.scans, marks.detections, marks.association,
                                                          marks.markers.marker_ids, out / "intensity.png"),
                    "alignment": lambda: alignment_figure(result, marks, out / "alignment.png", before, before_label),
                    "residuals": lambda: residual_figure(result, marks, out / "residuals.png", before, before_label)}
    draw = {n: fn for n, fn in draw.items() if n not in drawn}
    return Figures.of({n: _attempt(fn) for n, fn in draw.items()})


def write_intensity(scans: Scans, detections: Detections, association: Association, marker_ids: Sequence[str],
                    out_dir: Path | str) -> Figures:
    """Write intensity.png (:func:`lrfcal.report.figintensity.intensity_figure`) into out_dir: it needs only the
    detection
    and the association, so it is drawn while the solve goes on. Skipped with its reason as in :func:`write_figures`.
    """
    return Figures.of({"intensity": _attempt(partial(intensity_figure, scans, detections, association, marker_ids,
                                                     Path(out_dir) / "intensity.png"))})


def preload() -> None:
    """Import matplotlib's figure and Agg canvas, e.g. in a child forked while the data are made (forked.Ahead)."""
    import matplotlib.backends.backend_agg  # noqa: F401
    import matplotlib.figure  # noqa: F401


#: points of the calibrated cloud the flatness figure draws at most (a view of the scene's shape)
CLOUD_VIEW_POINTS = 50_000


def _cloud_view(cloud_M: FloatArray) -> FloatArray:
    """(K, 3): the finite points of a (..., 3) cloud, every n-th so that about CLOUD_VIEW_POINTS are left."""
    cloud = np.asarray(cloud_M, dtype=float).reshape(-1, 3)
    cloud = cloud[np.isfinite(cloud).all(1)]
    return cloud[:: max(1, cloud.shape[0] // CLOUD_VIEW_POINTS)]


def needs_clouds(result: CalibrationResult) -> bool:
    """Whether the figures draw ``result``'s clouds (targetless: flatness.png), else they can be drawn before."""
    return isinstance(result.evidence, PlaneEvidence)


def drawn_part(result: CalibrationResult) -> CalibrationResult:
    """``result`` with only what the figures draw of its clouds (none for markers, a view of the calibrated cloud
    for targetless) and of its marker evidence's detections (:func:`drawn_detections`), without the surface returns
    (no figure draws them), to send to a drawing process (lrfcal.runtime.forked.Ahead); its figures are those of
    ``result``."""
    after = _cloud_view(result.cloud_after_M) if needs_clouds(result) else np.zeros((0, 3))
    evidence = result.evidence
    if isinstance(evidence, MarkerEvidence):
        evidence = replace(evidence, detections=drawn_detections(evidence.detections), surface_returns=None)
    return replace(result, cloud_before_M=np.zeros((0, 3)), cloud_after_M=after, cloud_intensity=np.zeros(0),
                   evidence=evidence)


def drawn_detections(det: Detections) -> Detections:
    """``det`` with its label image (S, N) reduced to what the figures draw of it, whether a return is a marker
    candidate (0) or not (-1), as int8: an eighth of the int64 labels (12.7 MB on tunnel_v) to send to a drawing
    process, which otherwise waits on the pipe while the calibration goes on."""
    labels = np.where(det.labels >= 0, 0, -1).astype(np.int8)
    return replace(det, labels=labels)


def _attempt(fn: Callable[[], Path]) -> tuple[bool, str]:
    """(True, the path written) or (False, the reason the figure could not be drawn)."""
    try:
        return True, str(fn())
    except Exception as err:  # noqa: BLE001 - a figure never costs the user the calibration
        return False, f"{type(err).__name__}: {' '.join(str(err).split())}"


__all__ = ["DPI", "HEIGHT_PX", "WIDTH_PX", "Figures", "alignment_figure", "flatness_figure", "intensity_figure",
           "drawn_detections", "drawn_part", "needs_clouds", "residual_figure", "write_figures", "write_intensity"]

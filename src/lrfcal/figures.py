"""PNG figures of a calibration a person can look at (the seed paper's Figs. 8/9, 11/12 and residual plots).

matplotlib is imported inside the functions and only its object API is used (``matplotlib.figure.Figure``
rendered by the Agg canvas), so no pyplot state or GUI backend is involved. Every figure is written at
WIDTH_PX x HEIGHT_PX pixels (DPI dots per inch) to a temporary file in the target folder, then renamed.

Residuals in these figures are computed as in :mod:`lrfcal.viz`: from each reprojected marker return to the
nearest point of its marker sphere (MarkerMap centre, nominal radius), with the start parameters ("before")
and the calibrated parameters ("after").
"""

from __future__ import annotations

import os
import uuid
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .types import CalibrationResult
from .viz import marker_returns

FloatArray = NDArray[np.float64]

WIDTH_PX = 1600
HEIGHT_PX = 900
DPI = 150
FONT_SIZE_PT = 11
#: Rows of the intensity image drawn at most (scans are max-pooled above this).
MAX_FIGURE_ROWS = 1200

_C_BEFORE = "#e6781e"
_C_AFTER = "#28aa50"
_C_MARKER = "#b0209a"


def _new_figure() -> Any:
    from matplotlib.figure import Figure

    return Figure(figsize=(WIDTH_PX / DPI, HEIGHT_PX / DPI), dpi=DPI, layout="constrained")


def _save(fig: Any, path: Path | str) -> Path:
    """Write ``fig`` as PNG at WIDTH_PX x HEIGHT_PX, atomically (temp file in the folder, then rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp")
    try:
        fig.savefig(tmp, format="png", dpi=DPI)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


def _rc() -> Any:
    import matplotlib

    return matplotlib.rc_context({"font.size": FONT_SIZE_PT, "axes.titlesize": FONT_SIZE_PT + 1,
                                  "axes.labelsize": FONT_SIZE_PT, "legend.fontsize": FONT_SIZE_PT - 1,
                                  "xtick.labelsize": FONT_SIZE_PT - 1, "ytick.labelsize": FONT_SIZE_PT - 1})


def _rms_mm(norms_m: FloatArray) -> float:
    return float(np.sqrt(np.mean(norms_m**2)) * 1e3) if norms_m.size else float("nan")


def intensity_figure(result: CalibrationResult, path: Path | str) -> Path:
    """The (S, N) intensity image (paper Figs. 8/9) in log scale, before and after thresholding.

    Left: all intensities, x = beam angle mu [deg], y = scan index, log colour scale with colorbar
    "intensity [counts]", detected blobs outlined. Right: only returns at or above the threshold, blob boxes
    labelled with their marker id and peak returns marked. Returns the written path.
    """
    from matplotlib.colors import LogNorm
    from matplotlib.patches import Rectangle

    sc = result.recording.scans
    inten = np.asarray(sc.intensities, dtype=float)
    S, N = inten.shape
    mu_deg = np.rad2deg(np.asarray(sc.mu_rad, dtype=float)[int(np.argmax(sc.beam_counts))])  # widest scan
    step = float(np.median(np.abs(np.diff(mu_deg)))) if N > 1 else 1.0
    x0, x1 = float(mu_deg.min()) - step / 2, float(mu_deg.max()) + step / 2
    flip = N > 1 and mu_deg[-1] < mu_deg[0]  # negative angle increment: show increasing angle left to right
    img = inten[:, ::-1] if flip else inten
    pool = max(1, int(np.ceil(S / MAX_FIGURE_ROWS)))  # max-pool scans so that thin blobs stay visible
    if pool > 1:
        img = np.vstack([img, np.zeros(((-S) % pool, N))]).reshape(-1, pool, N).max(axis=1)
    positive = img[np.isfinite(img) & (img > 0)]
    vmin = max(float(np.percentile(positive, 1.0)) if positive.size else 1.0, 1.0)
    vmax = max(float(positive.max()) if positive.size else 10.0, vmin * 10)
    thr = float(result.detections.threshold)
    det = result.detections
    ids = result.markers.marker_ids
    b2m = result.association.blob_to_marker

    def beam_x(b: int) -> float:
        return float(mu_deg[b])

    with _rc():
        import matplotlib

        cmap = matplotlib.colormaps["inferno"].with_extremes(bad="black")
        fig = _new_figure()
        axes = fig.subplots(1, 2, sharex=True, sharey=True)
        shown = np.ma.masked_invalid(np.where(img > 0, img, np.nan))
        above = np.ma.masked_where(~(img >= thr), shown)
        kw = {"origin": "lower", "aspect": "auto", "extent": (x0, x1, -0.5, img.shape[0] * pool - 0.5),
              "cmap": cmap,
              "norm": LogNorm(vmin=vmin, vmax=vmax), "interpolation": "nearest"}
        im = axes[0].imshow(shown, **kw)
        axes[1].imshow(above, **kw)
        axes[1].set_facecolor("#202020")
        for j, b in enumerate(det.blobs):
            xs = [beam_x(int(b.beam_idx.min())), beam_x(int(b.beam_idx.max()))]
            lo, hi = min(xs) - step / 2, max(xs) + step / 2
            s0, s1 = float(b.scan_idx.min()) - 0.5, float(b.scan_idx.max()) + 0.5
            # outline with a margin, at least ~1 % of the axes in each direction so that it stays visible
            mx = max(step, 0.005 * (x1 - x0), 0.5 * (0.01 * (x1 - x0) - (hi - lo)))
            my = max(1.0, 0.005 * S, 0.5 * (0.015 * S - (s1 - s0)))
            for ax in axes:
                ax.add_patch(Rectangle((lo - mx, s0 - my), hi - lo + 2 * mx, s1 - s0 + 2 * my, fill=False,
                                       edgecolor="#00d8ff", linewidth=1.0))
            m = int(b2m[j]) if j < b2m.size else -1
            if m >= 0:  # label beside the box, on the side with more room
                right = hi < 0.5 * (x0 + x1)
                axes[1].annotate(ids[m], (hi + mx + step if right else lo - mx - step, 0.5 * (s0 + s1)),
                                 color="white", fontsize=FONT_SIZE_PT - 1, ha="left" if right else "right",
                                 va="center", annotation_clip=True)
        if det.blobs:
            px = [beam_x(b.peak_beam) for b in det.blobs]
            py = [b.peak_scan for b in det.blobs]
            axes[1].plot(px, py, "+", color="#00ff60", markersize=9, markeredgewidth=1.5)
        axes[0].set_xlim(x0, x1)
        axes[0].set_ylim(-0.5, S - 0.5)
        pooled = f", {pool}-scan max" if pool > 1 else ""
        axes[0].set_title(f"all returns ({S} x {N}{pooled})")
        axes[1].set_title(f"above {thr:.0f} counts: {len(det.blobs)} blobs (+ peak)")
        for ax in axes:
            ax.set_xlabel("beam angle mu [deg]")
        axes[0].set_ylabel("scan index")
        fig.colorbar(im, ax=axes, label="intensity [counts]", shrink=0.95)
        fig.suptitle("Marker detection in the (scan, beam) intensity image", fontsize=FONT_SIZE_PT + 2)
        return _save(fig, path)


def _principal_axes(points: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Centroid (3,) and the 3 principal axes (3, 3) (rows, by decreasing spread) of points (n, 3).

    Each axis' largest-magnitude component is made positive so the projection does not flip between runs.
    """
    c = points.mean(axis=0)
    if points.shape[0] < 2:
        return c, np.eye(3)
    _, _, Vt = np.linalg.svd(points - c, full_matrices=True)
    idx = np.argmax(np.abs(Vt), axis=1)
    Vt = Vt * np.sign(Vt[np.arange(3), idx])[:, None]
    return c, Vt


def alignment_figure(result: CalibrationResult, path: Path | str) -> Path:
    """Markers and reprojected marker returns, before and after calibration (paper Figs. 11/12), in W.

    Two panels sharing axes; points are projected on the plane of the two largest principal axes of the
    marker positions (u, v in m, relative to the markers' centroid), residuals drawn as lines to the marker
    surface. Each title gives the 3D residual RMS [mm]. Returns the written path.
    """
    markers = np.asarray(result.markers.positions_W, dtype=float)
    ids = result.markers.marker_ids
    c, V = _principal_axes(markers)

    def proj(p: FloatArray) -> FloatArray:
        return (p - c) @ V[:2].T

    stages = {}
    for name, params in (("before", result.start), ("after", result.solution.params)):
        p, to_m, mk, _ = marker_returns(result, params)
        stages[name] = (p, to_m, mk, np.linalg.norm(to_m, axis=1))
    m2 = proj(markers)
    allpts = np.vstack([m2] + [proj(s[0]) for s in stages.values()])
    allpts = allpts[np.isfinite(allpts).all(axis=1)]
    lo, hi = allpts.min(axis=0), allpts.max(axis=0)
    pad = 0.08 * max(float((hi - lo).max()), 0.05)

    with _rc():
        fig = _new_figure()
        span = (hi - lo) + 2 * pad
        stacked = span[0] > 2.2 * span[1]  # wide layouts use the width better one above the other
        axes = fig.subplots(2 if stacked else 1, 1 if stacked else 2, sharex=True, sharey=True).ravel()
        for ax, (name, (p, to_m, _mk, norms)) in zip(axes, stages.items(), strict=True):
            color = _C_BEFORE if name == "before" else _C_AFTER
            p2, q2 = proj(p), proj(p + to_m)
            if p2.size:
                segs = np.stack([p2, q2], axis=1)
                from matplotlib.collections import LineCollection

                ax.add_collection(LineCollection(segs, colors=color, linewidths=0.8, alpha=0.7,
                                                 label="residual (to marker surface)"))
            ax.scatter(p2[:, 0], p2[:, 1], s=12, color=color, zorder=3,
                       label=f"reprojected marker returns (K = {len(p)})")
            ax.scatter(m2[:, 0], m2[:, 1], s=110, facecolors="none", edgecolors=_C_MARKER, linewidths=1.8,
                       label="markers (MDS from tape)", zorder=4)
            for i, mid in enumerate(ids):
                ax.annotate(mid, m2[i], xytext=(6, 6), textcoords="offset points", fontsize=FONT_SIZE_PT - 1,
                            color=_C_MARKER)
            what = "start parameters" if name == "before" else "calibrated parameters"
            ax.set_title(f"{name} ({what}): residual RMS {_rms_mm(norms):.1f} mm")
            if not stacked or name == "after":
                ax.set_xlabel("u: 1st principal axis of the markers [m]")
            if stacked or name == "before":
                ax.set_ylabel("v: 2nd principal axis [m]")
            ax.set_aspect("equal", adjustable="box")
            ax.grid(True, alpha=0.3)
            ax.legend(loc="center left" if stacked else "upper center",
                      bbox_to_anchor=(1.02, 0.5) if stacked else (0.5, -0.17), ncols=1)
        axes[0].set_xlim(lo[0] - pad, hi[0] + pad)
        axes[0].set_ylim(lo[1] - pad, hi[1] + pad)
        fig.suptitle("Marker returns reprojected into W (projection on the markers' principal plane)",
                     fontsize=FONT_SIZE_PT + 2)
        return _save(fig, path)


def _plain(v: float, _pos: object = None) -> str:
    """Tick label without powers of ten: 0.5, 2, 10, 200."""
    return f"{v:g}"


def residual_figure(result: CalibrationResult, path: Path | str) -> Path:
    """Histogram of residual norms [mm] before/after (log bins) and per-marker RMS [mm] as grouped bars."""
    from matplotlib.ticker import FuncFormatter, MaxNLocator

    ids = result.markers.marker_ids
    n = len(ids)
    data = {}
    for name, params in (("before", result.start), ("after", result.solution.params)):
        _, to_m, mk, _ = marker_returns(result, params)
        norms_mm = np.linalg.norm(to_m, axis=1) * 1e3
        per = np.array([_rms_mm(norms_mm[mk == m] / 1e3) for m in range(n)])
        data[name] = (norms_mm, per)
    allv = np.concatenate([d[0] for d in data.values()])
    allv = allv[np.isfinite(allv) & (allv > 0)]
    lo = max(float(allv.min()) if allv.size else 0.01, 1e-3)
    hi = max(float(allv.max()) if allv.size else 1.0, lo * 10)
    bins = np.geomspace(lo / 1.2, hi * 1.2, 40)

    with _rc():
        fig = _new_figure()
        ax_h, ax_b = fig.subplots(1, 2, width_ratios=[1, 1.2])
        for name, (norms_mm, _) in data.items():
            color = _C_BEFORE if name == "before" else _C_AFTER
            v = np.clip(norms_mm[np.isfinite(norms_mm)], lo, None)
            med = float(np.median(norms_mm)) if norms_mm.size else float("nan")
            ax_h.hist(v, bins=bins, color=color, alpha=0.6,
                      label=f"{name}: RMS {_rms_mm(norms_mm / 1e3):.1f} mm, median {med:.1f} mm")
        ax_h.set_xscale("log")
        ax_h.xaxis.set_major_formatter(FuncFormatter(_plain))
        ax_h.yaxis.set_major_locator(MaxNLocator(integer=True))
        ax_h.set_xlabel("residual norm |return - marker surface| [mm]")
        ax_h.set_ylabel("number of marker returns")
        ax_h.set_title(f"residual norms (K = {data['after'][0].size} returns)")
        ax_h.legend(loc="upper left")
        ax_h.grid(True, alpha=0.3, which="both")

        x = np.arange(n)
        w = 0.4
        for k, (name, (_, per)) in enumerate(data.items()):
            color = _C_BEFORE if name == "before" else _C_AFTER
            bars = ax_b.bar(x + (k - 0.5) * w, np.nan_to_num(per), width=w, color=color, label=name)
            if n <= 16:
                ax_b.bar_label(bars, labels=[f"{v:.1f}" if np.isfinite(v) else "" for v in per],
                               fontsize=FONT_SIZE_PT - 2, padding=2)
        ax_b.set_xticks(x, list(ids), rotation=45 if n > 12 else 0, ha="right" if n > 12 else "center")
        ax_b.set_xlabel("marker")
        ax_b.set_ylabel("RMS residual [mm]")
        pos = np.r_[data["before"][1], data["after"][1]]
        pos = pos[np.isfinite(pos) & (pos > 0)]
        if pos.size:
            ax_b.set_yscale("log")
            ax_b.set_ylim(pos.min() / 3.0, pos.max() * 2.0)
            ax_b.yaxis.set_major_formatter(FuncFormatter(_plain))
            ax_b.yaxis.set_minor_formatter(FuncFormatter(lambda v, _p: _plain(v) if f"{v:g}"[0] in "235" else ""))
        ax_b.set_title("per-marker RMS (markers without returns: no bar)")
        ax_b.legend(loc="upper right")
        ax_b.grid(True, axis="y", alpha=0.3, which="both")
        sol = result.solution
        fig.suptitle(f"Marker residuals before / after calibration (solver: RMS "
                     f"{sol.residual_rms_m * 1e3:.1f} mm, {sol.n_observations} observations, {sol.status})",
                     fontsize=FONT_SIZE_PT + 2)
        return _save(fig, path)


def write_figures(result: CalibrationResult, out_dir: Path | str) -> dict[str, Path]:
    """Write intensity.png, alignment.png and residuals.png into out_dir; returns {name: path}."""
    out = Path(out_dir)
    return {
        "intensity": intensity_figure(result, out / "intensity.png"),
        "alignment": alignment_figure(result, out / "alignment.png"),
        "residuals": residual_figure(result, out / "residuals.png"),
    }


__all__ = ["DPI", "HEIGHT_PX", "WIDTH_PX", "alignment_figure", "intensity_figure", "residual_figure",
           "write_figures"]

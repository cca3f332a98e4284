"""The intensity figure of a calibration (intensity.png, the seed paper's Figs. 8/9): the (scan, beam) intensity
image and the marker returns detected in it. It needs only the detection and the association, so the calibration
draws it while its solve goes on (lrfcal.commands.calibration_run)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
from numpy.typing import NDArray

from lrfcal.report.figlayout import FONT_SIZE_PT, new_figure, place_labels, rc, save
from lrfcal.types import Association, Detections, Scans

FloatArray = NDArray[np.float64]

#: Rows and columns of the intensity image drawn at most (scans, beams are max-pooled above this): about the
#: panel's size in pixels, so that matplotlib does not resample a larger image down (a third of the figure's time).
MAX_FIGURE_ROWS = 700
MAX_FIGURE_COLS = 700

#: the colour of the marker candidates (alignment.png draws its markers in the same colour)
C_MARKER = "#b0209a"

#: a pixel of an image max-pooled for drawing (intensity counts, or a candidate mask's bool)
Pixel = TypeVar("Pixel", bound=np.generic)


def _candidate_panel(ax: Any, shown: Any, cand: NDArray[np.bool_], kw: dict[str, Any], pool: int) -> None:
    """The intensity figure's right panel: every return (``shown``, a masked (rows, N) image drawn with ``kw``)
    faint grey for context, the marker candidates (``cand``) as dots: a blob is a few cells of a large image, so
    drawn as image cells it would be invisible at this size."""
    import matplotlib

    grey = matplotlib.colormaps["Greys"].with_extremes(bad="white")
    ax.imshow(shown[::2, ::2], **{**kw, "cmap": grey, "alpha": 0.35})  # context only: half resolution
    rows, cols = np.nonzero(cand & ~np.ma.getmaskarray(shown))
    if rows.size:
        x0, x1 = kw["extent"][:2]
        xs = x0 + (cols + 0.5) * (x1 - x0) / shown.shape[1]
        ys = rows * pool + 0.5 * (pool - 1)
        ax.scatter(xs, ys, color=C_MARKER, s=12, marker="s", linewidths=0, rasterized=True,
                   label="marker candidate return")
    ax.set_facecolor("white")


def _max_pool(img: NDArray[Pixel], rows: int, cols: int) -> NDArray[Pixel]:
    """The maximum of each ``rows`` x ``cols`` block of a 2-D image (the image padded with zeros, False)."""
    if rows == cols == 1:
        return img
    S, N = img.shape
    img = np.pad(img, ((0, (-S) % rows), (0, (-N) % cols)))
    return img.reshape(img.shape[0] // rows, rows, img.shape[1] // cols, cols).max(axis=(1, 3))


def _zoom(ax: Any, xs: FloatArray, ys: FloatArray, bounds: tuple[float, float, float, float],
          margins: tuple[float, float]) -> None:
    """Limits of ``ax`` around the points (xs, ys), 1.2 x their spread plus ``margins`` and at least a quarter of
    ``bounds`` (x0, x1, y0, y1) each way, within ``bounds``."""
    x0, x1, y0, y1 = bounds
    cx, cy = 0.5 * (xs.min() + xs.max()), 0.5 * (ys.min() + ys.max())
    hx = max(0.6 * (xs.max() - xs.min()) + margins[0], 0.125 * (x1 - x0))
    hy = max(0.6 * (ys.max() - ys.min()) + margins[1], 0.125 * (y1 - y0))
    ax.set_xlim(max(x0, cx - hx), min(x1, cx + hx))
    ax.set_ylim(max(y0, cy - hy), min(y1, cy + hy))


def intensity_figure(scans: Scans, detections: Detections, association: Association, marker_ids: Sequence[str],
                     path: Path | str) -> Path:
    """The (S, N) intensity image (paper Figs. 8/9) of ``scans`` in log scale, and the marker returns
    ``detections`` found in it; ``association`` gives blobs the markers named ``marker_ids``.

    Left: all intensities, x = beam angle mu [deg], y = scan index, log colour scale with colorbar
    "intensity [counts]", detected blobs outlined. Right: only the marker candidates (returns whose intensity is
    above the range-dependent background by the detection's contrast threshold, see lrfcal.stages.detection), blob
    peaks marked and labelled with their marker id, or "unmatched" (in red) for a blob the association did not
    give a marker; labels that would overprint are skipped. Returns the written path.
    """
    from matplotlib.colors import LogNorm
    from matplotlib.patches import Rectangle

    sc = scans
    inten = np.asarray(sc.intensities, dtype=float)
    S, N = inten.shape
    mu_deg = np.rad2deg(np.asarray(sc.mu_rad, dtype=float)[int(np.argmax(sc.beam_counts))])  # widest scan
    step = float(np.median(np.abs(np.diff(mu_deg)))) if N > 1 else 1.0
    x0, x1 = float(mu_deg.min()) - step / 2, float(mu_deg.max()) + step / 2
    flip = N > 1 and mu_deg[-1] < mu_deg[0]  # negative angle increment: show increasing angle left to right
    det = detections
    cand = det.labels >= 0
    img = inten[:, ::-1] if flip else inten
    cand = cand[:, ::-1] if flip else cand
    pool = max(1, int(np.ceil(S / MAX_FIGURE_ROWS)))  # max-pooled so that thin blobs stay visible
    pool_beams = max(1, int(np.ceil(N / MAX_FIGURE_COLS)))
    img, cand = _max_pool(img, pool, pool_beams), _max_pool(cand, pool, pool_beams)
    positive = img[np.isfinite(img) & (img > 0)]
    vmin = max(float(np.percentile(positive, 1.0)) if positive.size else 1.0, 1.0)
    vmax = max(float(positive.max()) if positive.size else 10.0, vmin * 10)
    ids = list(marker_ids)
    b2m = association.blob_to_marker

    def beam_x(b: int) -> float:
        return float(mu_deg[b])

    with rc():
        import matplotlib

        cmap = matplotlib.colormaps["inferno"].with_extremes(bad="black")
        # a fixed layout (no constrained layout): the labels are placed without a first full draw of the figure
        fig = new_figure(constrained=False)
        fig.subplots_adjust(left=0.065, right=0.875, bottom=0.115, top=0.885, wspace=0.2)
        axes = fig.subplots(1, 2)
        shown = np.ma.masked_invalid(np.where(img > 0, img, np.nan))
        x_end = x0 + (x1 - x0) * img.shape[1] * pool_beams / N  # past x1 by the beams padded to a whole block
        kw = {"origin": "lower", "aspect": "auto", "extent": (x0, x_end, -0.5, img.shape[0] * pool - 0.5),
              "cmap": cmap,
              "norm": LogNorm(vmin=vmin, vmax=vmax), "interpolation": "nearest"}
        im = axes[0].imshow(shown, **kw)
        _candidate_panel(axes[1], shown, cand, kw, pool)
        labels: list[tuple[float, float, str, str]] = []
        n_unmatched = 0
        for j, b in enumerate(det.blobs):
            xs = [beam_x(int(b.beam_idx.min())), beam_x(int(b.beam_idx.max()))]
            lo, hi = min(xs) - step / 2, max(xs) + step / 2
            s0, s1 = float(b.scan_idx.min()) - 0.5, float(b.scan_idx.max()) + 0.5
            # outline with a margin, at least ~1 % of the axes in each direction so that it stays visible
            mx = max(step, 0.005 * (x1 - x0), 0.5 * (0.01 * (x1 - x0) - (hi - lo)))
            my = max(1.0, 0.005 * S, 0.5 * (0.015 * S - (s1 - s0)))
            m = int(b2m[j]) if j < b2m.size else -1
            edge = "#00d8ff" if m >= 0 else "#ff4040"
            axes[0].add_patch(Rectangle((lo - mx, s0 - my), hi - lo + 2 * mx, s1 - s0 + 2 * my, fill=False,
                                        edgecolor=edge, linewidth=1.0))
            labels.append((beam_x(b.peak_beam), float(b.peak_scan), ids[m] if m >= 0 else "unmatched",
                           "black" if m >= 0 else "#d01010"))
            n_unmatched += m < 0
        if det.blobs:
            px = [beam_x(b.peak_beam) for b in det.blobs]
            py = [b.peak_scan for b in det.blobs]
            axes[1].plot(px, py, "+", color="#0a8a30", markersize=9, markeredgewidth=1.5)
        axes[0].set_xlim(x0, x1)
        axes[0].set_ylim(-0.5, S - 0.5)
        axes[1].set_xlim(x0, x1)
        axes[1].set_ylim(-0.5, S - 0.5)
        if det.blobs:  # the right panel zooms onto the blobs (at least a quarter of the image each way)
            bx = np.array([beam_x(int(b.beam_idx.min())) for b in det.blobs]
                          + [beam_x(int(b.beam_idx.max())) for b in det.blobs])
            by = np.array([float(b.scan_idx.min()) for b in det.blobs] + [float(b.scan_idx.max()) for b in det.blobs])
            _zoom(axes[1], bx, by, (x0, x1, -0.5, S - 0.5), (5 * step, 5.0))
        pooled = f" ({pool} x {pool_beams} max)" if pool * pool_beams > 1 else ""
        axes[0].set_title(f"all {S} x {N} returns{pooled}, blobs outlined")
        unmatched = f", {n_unmatched} unmatched" if n_unmatched else ""
        axes[1].set_title(f"zoom: marker candidates, {len(det.blobs)} blobs{unmatched}")
        for ax in axes:
            ax.set_xlabel("beam angle mu [deg]")
            ax.set_ylabel("scan index")
        fig.colorbar(im, cax=fig.add_axes((0.895, 0.115, 0.012, 0.77)), label="intensity [counts]")
        fig.suptitle("Marker detection in the (scan, beam) intensity image", fontsize=FONT_SIZE_PT + 2)
        fig.supxlabel("candidates: brighter than the range-dependent background by the contrast threshold (bright "
                      "walls seen head-on are not); + blob peak, label = its marker", fontsize=FONT_SIZE_PT - 2,
                      color="#444444")
        skipped = place_labels(axes[1], labels, FONT_SIZE_PT - 2)
        if skipped:
            axes[1].text(0.99, 0.01, f"{skipped} labels skipped (no room)", transform=axes[1].transAxes,
                         ha="right", va="bottom", color="#555555", fontsize=FONT_SIZE_PT - 2)
        return save(fig, path)


__all__ = ["C_MARKER", "MAX_FIGURE_COLS", "MAX_FIGURE_ROWS", "intensity_figure"]

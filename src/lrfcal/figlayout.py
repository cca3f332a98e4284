"""Layout helpers of the calibration figures (lrfcal.figures): labels placed without overprinting, the view frame
of a marker seen from the motor, round tick values. Pure functions of matplotlib axes and numpy arrays."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


def place_labels(ax: Any, items: list[tuple[float, float, str, str]], fontsize: float) -> int:
    """Write labels (x, y, text, colour) beside their points without overprinting: each label takes the first
    free spot among 8 offsets around its point (display coordinates); a label with no free spot is skipped.
    Returns the number of labels skipped."""
    fig = ax.figure
    if fig.get_layout_engine() is not None:
        fig.draw_without_rendering()  # display transforms are final only after the layout has run
        fig.set_layout_engine("none")  # and the layout stays as it is: saving does not lay the figure out again
    to_px = ax.transData.transform
    px_per_pt = fig.dpi / 72.0
    h = fontsize * px_per_pt * 1.2
    box = ax.get_window_extent()
    taken: list[tuple[float, float, float, float]] = []
    for x, y, _t, _c in items:  # the marks themselves are taken
        cx, cy = to_px((x, y))
        taken.append((cx - 6, cy - 6, cx + 6, cy + 6))
    skipped = 0
    offsets = [(1, 0), (-1, 0), (1, 1), (-1, 1), (1, -1), (-1, -1), (0, 1.6), (0, -1.6)]
    for x, y, text, colour in items:
        w = 0.62 * fontsize * px_per_pt * len(text)
        cx, cy = to_px((x, y))
        for dx, dy in offsets:
            x0 = cx + (8 if dx > 0 else -8 - w if dx < 0 else -w / 2)
            y0 = cy + dy * 0.8 * h - h / 2
            cand = (x0, y0, x0 + w, y0 + h)
            inside = box.x0 <= cand[0] and cand[2] <= box.x1 and box.y0 <= cand[1] and cand[3] <= box.y1
            if inside and all(cand[2] < t[0] or cand[0] > t[2] or cand[3] < t[1] or cand[1] > t[3] for t in taken):
                taken.append(cand)
                ax.annotate(text, (x, y), xytext=(x0 - cx, y0 - cy), textcoords="offset pixels", color=colour,
                            fontsize=fontsize, ha="left", va="bottom", annotation_clip=False)
                break
        else:
            skipped += 1
    return skipped


def view_frame(centre_W: FloatArray, eye_W: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Two unit vectors (u, v) spanning the plane perpendicular to the view ray eye -> centre; v as close to
    +z of W as possible ("up"), u = v x ray."""
    ray = centre_W - eye_W
    n = float(np.linalg.norm(ray))
    ray = ray / n if n > 0 else np.array([1.0, 0.0, 0.0])
    up = np.array([0.0, 0.0, 1.0])
    if abs(float(ray @ up)) > 0.95:
        up = np.array([0.0, 1.0, 0.0])
    v = up - (up @ ray) * ray
    v /= np.linalg.norm(v)
    u = np.cross(v, ray)
    return u, v


def three_ticks(extent: float) -> list[float]:
    """-t, 0, t with t a round number (1, 2 or 5 x 10^k) within ``extent``."""
    t = 10.0 ** math.floor(math.log10(max(extent, 1e-9)))
    for m in (5.0, 2.0, 1.0):
        if m * t <= extent * 0.95:
            return [-m * t, 0.0, m * t]
    return [-t, 0.0, t]


__all__ = ["place_labels", "three_ticks", "view_frame"]

"""Layout helpers of the calibration figures (lrfcal.report.figures, lrfcal.report.figintensity): the figure's size and
fonts, a
new figure and its atomic PNG file, labels placed without overprinting, the view frame of a marker seen from the
motor, round tick values. matplotlib is imported inside the functions."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from lrfcal.io.files import atomic_file

FloatArray = NDArray[np.float64]

WIDTH_PX = 1600
HEIGHT_PX = 900
DPI = 150
FONT_SIZE_PT = 11
#: a tick label's width per character and font point, as a fraction of the figure's width (DejaVu Sans' average
#: character is about 0.6 em)
LABEL_EM = 0.6 * DPI / 72 / WIDTH_PX


def new_figure(constrained: bool = True) -> Any:
    """A WIDTH_PX x HEIGHT_PX figure; ``constrained``: matplotlib's constrained layout (costly with many axes: a
    figure of many small panels places them itself)."""
    from matplotlib.figure import Figure

    return Figure(figsize=(WIDTH_PX / DPI, HEIGHT_PX / DPI), dpi=DPI, layout="constrained" if constrained else None)


def save(fig: Any, path: Path | str) -> Path:
    """Write ``fig`` as PNG at WIDTH_PX x HEIGHT_PX, atomically (temp file in the folder, then rename)."""
    path = Path(path)
    with atomic_file(path) as tmp:
        # zlib level 1: a third of the default level's encoding time for files about 10 % larger
        fig.savefig(tmp, format="png", dpi=DPI, pil_kwargs={"compress_level": 1})
    return path


def rc() -> Any:
    import matplotlib

    return matplotlib.rc_context({"font.size": FONT_SIZE_PT, "axes.titlesize": FONT_SIZE_PT + 1,
                                  "axes.labelsize": FONT_SIZE_PT, "legend.fontsize": FONT_SIZE_PT - 1,
                                  "xtick.labelsize": FONT_SIZE_PT - 1, "ytick.labelsize": FONT_SIZE_PT - 1})


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


__all__ = ["DPI", "FONT_SIZE_PT", "HEIGHT_PX", "LABEL_EM", "WIDTH_PX", "new_figure", "place_labels", "rc", "save",
           "three_ticks", "view_frame"]

"""The figures of a Monte-Carlo study (lrfsim.trials.study): error histograms with the predicted sigma, and with a
varied field the predicted and measured sigma against its value. matplotlib is imported only here, when they are drawn
(or ahead, by :func:`import_figures`, while the trials run: ``lrfsim study`` does)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

import numpy as np
from numpy.typing import NDArray

from lrfcal.model.kinematics import DH_NAMES

if TYPE_CHECKING:
    from lrfsim.plan.result import Plan


class PartLike(Protocol):
    """What the figures read of a lrfsim.trials.study_result.StudyPart."""

    @property
    def value(self) -> str: ...
    @property
    def plan(self) -> Plan | None: ...
    def errors(self) -> NDArray[np.float64]: ...
    def stats(self) -> dict[str, dict[str, float]]: ...


class StudyLike(Protocol):
    """What the figures read of a lrfsim.trials.study_result.Study."""

    @property
    def name(self) -> str: ...
    @property
    def key(self) -> str | None: ...
    @property
    def parts(self) -> Sequence[PartLike]: ...


def import_figures() -> None:
    """Import matplotlib (its Agg backend) and pyplot: the figures' 0.3-0.6 s of imports, done ahead (``lrfsim
    study`` does it while the workers run the trials, where it would otherwise run after them, one core idle)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot  # noqa: F401
    import matplotlib.ticker  # noqa: F401


def _scale(p: str) -> tuple[float, str]:
    return (1000.0, "mm") if p in ("a", "b") else (math.degrees(1.0), "deg")


def write_figures(s: StudyLike, folder: Path) -> list[Path]:
    """hist_<P>.png per DH parameter (errors of every part, the predicted sigma drawn) and, with a varied field,
    vary_sigma.png (predicted and measured sigma against the value)."""
    import_figures()
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator

    written = []
    for i, p in enumerate(DH_NAMES):
        k, unit = _scale(p)
        fig, ax = plt.subplots(figsize=(5, 3.5))
        for part in s.parts:
            e = part.errors()[:, i] * k
            label = f"{s.key}={part.value}" if s.key else "errors"
            if e.size:
                ax.hist(e, bins=max(5, min(30, e.size // 2)), alpha=0.6, label=f"{label} (n={e.size})")
            if part.plan is not None and math.isfinite(part.plan.sigma[p]):
                sig = part.plan.sigma[p] * k
                line = ax.axvline(sig, ls="--", color="k" if not s.key else None)
                ax.axvline(-sig, ls="--", color=line.get_color())
        ax.set_xlabel(f"{p} error [{unit}] (dashed: +-predicted 1-sigma)")
        ax.set_ylabel("trials")
        ax.yaxis.set_major_locator(MaxNLocator(integer=True))  # trials are counted, never fractions
        ax.set_title(f"{s.name}: {p}")
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7)
        fig.tight_layout()
        path = folder / f"hist_{p}.png"
        fig.savefig(path, dpi=90)
        plt.close(fig)
        written.append(path)
    if s.key:
        fig, axes = plt.subplots(2, 2, figsize=(8, 6))
        labels = [part.value for part in s.parts]
        x = np.arange(len(labels))
        for p, ax in zip(DH_NAMES, axes.ravel(), strict=True):
            k, unit = _scale(p)
            pred = [part.plan.sigma[p] * k if part.plan is not None else np.nan for part in s.parts]
            meas = [part.stats()[p]["std"] * k for part in s.parts]
            ax.plot(x, pred, "o-", label="predicted")
            ax.plot(x, meas, "s--", label="measured (std)")
            ax.set_xticks(x, labels)
            ax.set_xlabel(s.key)
            ax.set_ylabel(f"sigma {p} [{unit}]")
            ax.legend(fontsize=7)
        fig.tight_layout()
        path = folder / "vary_sigma.png"
        fig.savefig(path, dpi=90)
        plt.close(fig)
        written.append(path)
    return written


__all__ = ["PartLike", "StudyLike", "import_figures", "write_figures"]

"""What `lrfcal check` writes for a person: report.md (the verdict, the test, each parameter compared, what was not
tested and why) and check.png (each tested parameter's saved and new value with their 1-sigma bars and the band in
which no drift is called; with a history, each parameter over the history's rows)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from lrfcal.estimate.drift import Compared, DriftTest
from lrfcal.model.unknowns import BY_NAME
from lrfcal.report.figlayout import FONT_SIZE_PT, new_figure, rc, save


def unit_scale(name: str) -> tuple[float, str]:
    """(factor, unit) of a parameter's display unit: mm for metres, deg for radians, ms for seconds, mm/rad for the
    incidence bias, ppm for scales."""
    unit = BY_NAME[name].unit if name in BY_NAME else "1"
    return {"m": (1000.0, "mm"), "rad": (math.degrees(1.0), "deg"), "s": (1000.0, "ms"),
            "m/rad": (1000.0, "mm/rad")}.get(unit, (1e6, "ppm"))


def show(name: str, value: float, *, signed: bool = False) -> str:
    """A parameter's value (or, ``signed``, a change) in display units; a scale's value as a number, its change
    in ppm."""
    if not math.isfinite(value):
        return "-"
    k, unit = unit_scale(name)
    if unit == "ppm" and not signed:
        return f"{value:.6g}"
    return f"{value * k:{'+' if signed else ''}.3g} {unit}"


def _row(p: Compared) -> str:
    if not p.tested:
        return f"| {p.name} | {show(p.name, p.saved)} | {show(p.name, p.new)} | - | - | - | not tested: {p.why} |"
    verdict = "**drifted**" if p.drifted else "no change"
    return (f"| {p.name} | {show(p.name, p.saved)} | {show(p.name, p.new)} | {show(p.name, p.change, signed=True)} | "
            f"{show(p.name, p.sigma)} | {p.z:+.2f} | {verdict} |")


def check_markdown(test: DriftTest, line: str, calibration: str, recording: str, methods: tuple[str, str],
                   notes: Sequence[str], new_checks: Sequence[tuple[str, bool, str]], figure: str | None) -> str:
    """report.md of a check: the verdict ``line``, what was compared, the test, the table, the notes, the new
    calibration's own checks and the figure (``figure``: its file name; None: not drawn)."""
    z_band = _z_band(test.false_alarm)
    lines = [
        "# Check of a calibration against a new recording", "",
        f"**{line}**", "",
        f"- calibration: `{calibration}` ({methods[0]})",
        f"- new recording: `{recording}`, calibrated {methods[1]} on the calibration's own path, started from the "
        "saved values",
        f"- joint test of \"nothing changed\": chi2 = d^T (C_saved + C_new)^-1 d = {test.statistic:.3f} over "
        f"{test.dof} parameters; threshold {test.threshold:.3f} (chi-square quantile at 1 - {test.false_alarm:g}); "
        f"{'drifted' if test.drifted else 'still valid'}",
        f"- per parameter: change = new - saved, sigma = sqrt(sigma_saved^2 + sigma_new^2 - ...) from both "
        f"covariances, z = change / sigma; a drifted test names the parameters beyond |z| {z_band:.2f} and the "
        "one whose removal lowers the statistic most, first", "",
        "| parameter | saved | new | change | sigma of the change | z | |",
        "|---|---|---|---|---|---|---|",
        *(_row(p) for p in test.parameters), "",
    ]
    if test.drifted:
        lines += ["Named, the one that explains most of the test first (how much the statistic drops without it): "
                  + ", ".join(f"{p.name} ({p.explains:.1f})" for p in test.moved), ""]
    lines += ["Parameters not tested are not called valid: the new recording (or the saved calibration) does not "
              "determine them, or they are not the rig's own (the mount).", ""]
    if notes:
        lines += ["## Notes", "", *(f"- {n}" for n in notes), ""]
    lines += ["## The new calibration's checks", "",
              *(f"- {name}: {'passed' if ok else 'FAILED'}: {detail}" for name, ok, detail in new_checks), ""]
    lines += ["## Figure", "", f"![check]({figure})" if figure else "not drawn (--no-figures)", ""]
    return "\n".join(lines)


def _z_band(false_alarm: float) -> float:
    from scipy.stats import norm

    return float(norm.isf(false_alarm / 2))


def check_figure(test: DriftTest, path: Path | str, history: Sequence[dict[str, str]] = ()) -> Path:
    """check.png: one panel per tested parameter: the saved value and the new one with their own 1-sigma bars and
    the band of no drift (saved +- z sigma of the change, z the two-sided quantile at the false-alarm rate), as
    differences from the saved value; with ``history`` (the rows of --history, this check last) each panel shows
    every row of the history in order."""
    tested = test.tested
    z = _z_band(test.false_alarm)
    with rc():
        fig = new_figure()
        n = max(len(tested), 1)
        cols = min(n, 4)
        rows = math.ceil(n / cols)
        fig.set_size_inches(3.3 * cols, 2.7 * rows + 0.7)
        axes = np.atleast_1d(fig.subplots(rows, cols, squeeze=False)).ravel()
        for ax, p in zip(axes, tested, strict=False):
            k, unit = unit_scale(p.name)
            seq = (_history_of(p.name, history) if history else
                   [(p.saved, p.sigma_saved, p.new, p.sigma_new, p.sigma, p.drifted)])
            arr = np.array([r[:5] for r in seq], dtype=float) * np.array([k, k, k, k, k])
            base = arr[-1, 0]
            x = np.arange(len(seq), dtype=float)
            ax.bar(x, 2 * z * arr[:, 4], bottom=arr[:, 0] - base - z * arr[:, 4], width=0.8, color="0.88",
                   label="no drift")
            ax.errorbar(x - 0.15, arr[:, 0] - base, yerr=arr[:, 1], fmt="s", color="0.35", capsize=3,
                        markersize=5, label="saved")
            for xi, row, d in zip(x, arr, (r[5] for r in seq), strict=True):
                ax.errorbar(xi + 0.15, row[2] - base, yerr=row[3], fmt="o", color="#c0392b" if d else "#2471a3",
                            capsize=3, markersize=6)
            ax.set_title(f"{p.name} (saved {show(p.name, p.saved)})", fontsize=FONT_SIZE_PT - 1)
            ax.set_ylabel(f"minus saved [{unit}]")
            ax.set_xticks(x, [str(int(i) + 1) for i in x] if history else ["saved | new"])
            ax.set_xlim(-0.6, len(seq) - 0.4)
            if history:
                ax.set_xlabel("check (row of the history)")
            ax.grid(True, axis="y", alpha=0.3)
            ax.use_sticky_edges = False  # the band's bars whole, with a margin
            ax.margins(y=0.08)
        for ax in axes[len(tested):]:
            ax.set_visible(False)
        verdict = "drifted" if test.drifted else "still valid"
        fig.suptitle(f"{verdict}: chi2 {test.statistic:.2f} vs {test.threshold:.2f} ({test.dof} dof, false alarm "
                     f"{100 * test.false_alarm:g} %); grey band: no drift (|z| <= {z:.2f}); square: saved, dot: "
                     "new (red: named as drifted), 1-sigma bars", fontsize=FONT_SIZE_PT - 1)
        return save(fig, path)


def _history_of(name: str, history: Sequence[dict[str, str]]) -> list[tuple[float, float, float, float, float, bool]]:
    """(saved, its sigma, new, its sigma, sigma of the change, named as drifted) of ``name`` in every row of a
    history (NaN where not compared)."""

    def num(row: dict[str, str], key: str) -> float:
        try:
            return float(row.get(key) or "nan")
        except ValueError:
            return math.nan

    return [(num(r, f"{name}_saved"), num(r, f"{name}_saved_sigma"), num(r, f"{name}_new"), num(r, f"{name}_new_sigma"),
             num(r, f"{name}_change_sigma"), r.get(f"{name}_drifted") == "1") for r in history]


__all__ = ["check_figure", "check_markdown", "show", "unit_scale"]

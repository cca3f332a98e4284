"""What a Monte-Carlo study found (:mod:`lrfsim.trials.study` runs it) and how it is written: one row per trial
(:class:`TrialRow`), the trials of one scenario variant with their statistics against the plan (:class:`StudyPart`),
the study (:class:`Study`); trials.csv, summary.md and the figures, written atomically (:func:`write_study`).
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy import stats

from lrfcal.io.files import atomic_folder, check_replaceable
from lrfcal.model.kinematics import DH_NAMES
from lrfsim.plan.result import Plan, format_value
from lrfsim.scenario.file import Scenario

from .study_figures import write_figures
from .variants import PERTURB_HALF_WIDTH, TRUTH_HALF_WIDTH

FloatArray = NDArray[np.float64]

#: the columns of trials.csv, in order (P_error, P_sigma for each DH parameter P, SI units)
CSV_COLUMNS: tuple[str, ...] = (
    "value", "trial", "seed", "status", "reason", "exit_code",
    *(f"{p}_{k}" for p in DH_NAMES for k in ("error", "sigma")), "clock_offset_error",
)


def exact_interval(n: int, level: float = 0.95) -> tuple[float, float]:
    """Where an RMS of error / sigma over ``n`` trials falls with probability ``level`` when the sigma is exact and
    the errors normal: sqrt(chi2_n / n) at its two tails (24 trials: 0.72-1.28). An RMS outside says the sigma, one
    inside cannot tell it from exact."""
    tail = (1.0 - level) / 2.0
    lo, hi = stats.chi2.ppf([tail, 1.0 - tail], n)
    return float(np.sqrt(lo / n)), float(np.sqrt(hi / n))


def p_exact(rms: float, n: int) -> float:
    """How likely an RMS of error / sigma at least this far from 1 is over ``n`` trials whose sigma is exact (errors
    normal): two-sided, n rms^2 against chi-square with n degrees of freedom (NaN without trials)."""
    if not (n > 0 and math.isfinite(rms)):
        return math.nan
    lower = float(stats.chi2.cdf(n * rms * rms, n))
    return min(1.0, 2.0 * min(lower, 1.0 - lower))


@dataclass(frozen=True)
class TrialRow:
    """One trial of a study: value (the varied field's value as text, "" without --vary), trial index, seed,
    status ("calibrated" | "refused"), reason and exit code when refused, errors and sigma (4,) in DH_NAMES order
    (SI units, NaN when refused), the clock offset's error [s] and the calibration's seconds."""

    value: str
    trial: int
    seed: int
    status: str
    reason: str
    exit_code: int
    errors: tuple[float, ...]
    sigma: tuple[float, ...]
    clock_offset_error_s: float
    seconds: float

    def csv_row(self) -> list[str]:
        """The row as CSV cells (12 significant digits: the same seeds give the same text; no timings)."""
        cells = [self.value, str(self.trial), str(self.seed), self.status, self.reason, str(self.exit_code)]
        for e, s in zip(self.errors, self.sigma, strict=True):
            cells += [_num(e), _num(s)]
        return [*cells, _num(self.clock_offset_error_s)]


def _num(v: float) -> str:
    """12 significant digits: far beyond any meaningful precision, and deaf to the last-bit differences of
    multithreaded BLAS reductions between one process and another."""
    return "" if not math.isfinite(v) else f"{float(v):.12g}"


@dataclass(frozen=True)
class StudyPart:
    """The trials of one scenario variant (one value of the varied field, or the scenario itself) and its plan
    (None when the plan itself was refused: fewer than 3 markers seen)."""

    value: str
    scenario: Scenario
    plan: Plan | None
    rows: tuple[TrialRow, ...]

    def errors(self) -> FloatArray:
        """(n_calibrated, 4) errors of the calibrated trials."""
        ok = [r.errors for r in self.rows if r.status == "calibrated"]
        return np.array(ok, dtype=float).reshape(-1, 4)

    def sigmas(self) -> FloatArray:
        ok = [r.sigma for r in self.rows if r.status == "calibrated"]
        return np.array(ok, dtype=float).reshape(-1, 4)

    @property
    def refusal_rate(self) -> float:
        return sum(r.status != "calibrated" for r in self.rows) / max(len(self.rows), 1)

    def stats(self) -> dict[str, dict[str, float]]:
        """Per DH parameter: n, bias, bias_se, std, rmse, predicted, rmse_over_predicted, std_over_predicted,
        rms_z (RMS of error / reported sigma), mean_sigma (SI units; NaN where undefined), over the calibrated trials
        that estimated it (a targetless calibration holds, with sigma NaN, what the scene does not determine)."""
        E, S = self.errors(), self.sigmas()
        out: dict[str, dict[str, float]] = {}
        for i, p in enumerate(DH_NAMES):
            estimated = np.isfinite(S[:, i])
            e, sig = E[estimated, i], S[estimated, i]
            n = e.size
            pred = self.plan.sigma[p] if self.plan is not None else math.nan
            bias = float(e.mean()) if n else math.nan
            std = float(e.std(ddof=1)) if n > 1 else math.nan
            rmse = float(np.sqrt(np.mean(e**2))) if n else math.nan
            out[p] = {
                "n": float(n), "bias": bias, "bias_se": std / math.sqrt(n) if n > 1 else math.nan, "std": std,
                "rmse": rmse, "predicted": pred, "rmse_over_predicted": rmse / pred if pred > 0 else math.nan,
                "std_over_predicted": std / pred if pred > 0 else math.nan,
                "rms_z": float(np.sqrt(np.mean((e / sig) ** 2))) if n else math.nan,
                "mean_sigma": float(sig.mean()) if n else math.nan,
            }
        return out


@dataclass(frozen=True)
class Study:
    """A study: the scenario's name, the varied field (or None) and one part per value; seconds of wall time;
    perturb_start: the scale of the perturbed start (0: every trial starts from the scenario's nominal values);
    draws: what a trial draws from its seed besides the noise and the tape (:data:`DRAWS`)."""

    name: str
    key: str | None
    parts: tuple[StudyPart, ...]
    seconds: float
    workers: str = ""
    notes: tuple[str, ...] = field(default=())
    perturb_start: float = 0.0
    draws: str = "noise"
    truth_spread: float = 0.0
    forced: bool = False  #: every trial calibrated with --force (a failed check recorded, not refused)

    @property
    def rows(self) -> tuple[TrialRow, ...]:
        return tuple(r for p in self.parts for r in p.rows)


#: what summary.md says a trial draws from its seed: the noise alone on one cast (the default), a cast of its own
#: (``recast``), a marker layout and cast of its own (``new_layout``)
DRAWS = {
    "noise": "One cast for every trial (the laser phase of the scenario's seed), each trial drawing its noise and "
             "tape: the beams cut the same pattern on the markers in every trial, so the pattern's error is a bias "
             "here (bias / std), where across recordings it is a scatter; `--recast` draws the pattern anew for "
             "every trial (docs/study.md, \"The spinning rig\").",
    "cast": "Every trial cast anew (its laser phase, noise and tape from its seed).",
    "layout": "Every trial a marker layout and cast of its own (from its seed): the figures average over layouts.",
    "truth": "Every trial a true DH, scene and cast of its own (from its seed): the figures average over truths.",
}


# --- outputs --------------------------------------------------------------------------------------------------

def trials_csv(s: Study) -> str:
    """trials.csv as text (CSV_COLUMNS; rows sorted by value order, then trial)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(CSV_COLUMNS)
    for r in s.rows:
        w.writerow(r.csv_row())
    return buf.getvalue()


def _fmt(p: str, v: float) -> str:
    return "-" if not math.isfinite(v) else format_value(p, v)


def _ratio(v: float, spec: str = ".2f") -> str:
    """A ratio of the summary's table, "-" where there is none (no plan, no trial that estimated the parameter)."""
    return "-" if not math.isfinite(v) else format(v, spec)


#: what an RMS over the calibrated trials of a part that refused some can hide
SELECTED = ("The RMS is over the {n} calibrated trials alone: where the data decide a refusal (a sigma near its "
            "limit), the refused trials can be those with the larger errors, and the RMS then reads low (a points "
            "layout with b near its limit: 0.40 over the 9 of 24 trials it calibrated, 0.64 over all 24 with the "
            "checks recorded instead of refusing; docs/study.md). `lrfsim study --force` calibrates every trial so.")
#: what a forced study's summary says
FORCED = ("Forced (`--force`): every trial calibrated as `lrfcal calibrate --force` does, a failed check recorded "
          "instead of refusing, so the RMS of error / sigma is over the trials the checks would have refused too; "
          "the refusal rate counts the trials no estimate came out of.")


def summary_markdown(s: Study) -> str:
    """summary.md: per part, the efficiency table of the DH parameters and the refusals."""
    lines = [f"# Monte-Carlo study of {s.name}", "",
             f"{len(s.parts[0].rows)} trials per {'value' if s.key else 'study'} ({s.workers}, {s.seconds:.0f} s). "
             "Errors against the truth; predicted sigma from `lrfsim plan` (Fisher information of the noise-free "
             "geometry). Efficiency: RMSE / predicted sigma (1 = the method reaches the predicted accuracy); "
             "calibration: RMS of error / reported sigma (1 = the reported sigma is honest).", "",
             DRAWS[s.draws], ""]
    if s.truth_spread > 0:
        h = {k: s.truth_spread * v for k, v in TRUTH_HALF_WIDTH.items()}
        lines += [f"Drawn truth (scale {s.truth_spread:g}): each trial's true DH drawn around the nominal, uniform in "
                  f"+-{h['a'] * 1000:g} mm (a, b) and +-{math.degrees(h['alpha']):g} deg (alpha, beta), from the "
                  "trial's seed; its nominal.yaml declares that spread (dh_tolerance: the half width / sqrt 3).", ""]
    if s.forced:
        lines += [FORCED, ""]
    if s.perturb_start > 0:
        h = {k: s.perturb_start * v for k, v in PERTURB_HALF_WIDTH.items()}
        lines += [f"Perturbed start (scale {s.perturb_start:g}): each trial's nominal values moved by uniform draws "
                  f"in +-{h['a'] * 1000:g} mm (a, b), +-{math.degrees(h['alpha']):g} deg (alpha, beta), "
                  f"+-{h['x'] * 100:g} cm and +-{math.degrees(h['roll']):g} deg (mount), from the trial's seed.", ""]
    for part in s.parts:
        st = part.stats()
        title = f"## {s.key} = {part.value}" if s.key else "## Results"
        n = sum(r.status == "calibrated" for r in part.rows)
        no_plan = ("; no plan (a targetless calibration; a parameter a trial held counts in no column)"
                   if part.scenario.markers is None else "; plan refused (too few markers seen)")
        lines += [title, "", f"calibrated {n} of {len(part.rows)}, refusal rate {100 * part.refusal_rate:.0f} %"
                  + ("" if part.plan is not None else no_plan), "",
                  "| parameter | bias (+- its s.e.) | bias / std | std | RMSE | predicted sigma | RMSE / predicted | "
                  "std / predicted | RMS error / reported sigma | mean reported sigma |",
                  "|---|---|---|---|---|---|---|---|---|---|"]
        for p in DH_NAMES:
            d = st[p]
            bz = d["bias"] / d["std"] if d["std"] > 0 else math.nan
            lines.append(f"| {p} | {_fmt(p, d['bias'])} +- {_fmt(p, d['bias_se'])} | {_ratio(bz, '+.2f')} | "
                         f"{_fmt(p, d['std'])} | {_fmt(p, d['rmse'])} | "
                         f"{_fmt(p, d['predicted'])} | {_ratio(d['rmse_over_predicted'])} | "
                         f"{_ratio(d['std_over_predicted'])} | {_ratio(d['rms_z'])} | {_fmt(p, d['mean_sigma'])} |")
        if n > 1:  # what the trials can tell: an exact sigma's RMS spreads this much over n trials
            lo, hi = exact_interval(n)
            lines += ["", f"With an exact sigma, the RMS of error / sigma over {n} trials lies in {lo:.2f}-{hi:.2f} "
                          "(95 %: sqrt(chi2_n / n)): a value inside cannot tell the sigma from an exact one (nor "
                          "RMSE / predicted the plan's)."]
        if 0 < n < len(part.rows) and not s.forced:
            lines += ["", SELECTED.format(n=n)]
        reasons: dict[str, int] = {}
        for r in part.rows:
            if r.status != "calibrated":
                reasons[r.reason] = reasons.get(r.reason, 0) + 1
        if reasons:
            lines += ["", "Refusals:"] + [f"- {k} x {v}" for v, k in sorted(((v, k) for k, v in reasons.items()),
                                                                              reverse=True)]
        lines.append("")
    figs = [f"![{p}](hist_{p}.png)" for p in DH_NAMES]
    lines += ["## Figures", "", *figs]
    if s.key:
        lines += ["", "![predicted and measured sigma](vary_sigma.png)"]
    return "\n".join(lines) + "\n"


def write_study(s: Study, out_dir: str | Path, *, overwrite: bool = False) -> Path:
    """Write trials.csv, summary.md and the figures into ``out_dir`` atomically (a temporary folder beside it,
    renamed into place when complete; an existing folder is replaced only with ``overwrite`` and only if this
    project wrote it)."""
    out = check_replaceable(out_dir, overwrite)
    with atomic_folder(out, "lrfsim study") as tmp:
        (tmp / "trials.csv").write_text(trials_csv(s), encoding="utf-8")
        (tmp / "summary.md").write_text(summary_markdown(s), encoding="utf-8")
        write_figures(s, tmp)
    return out

__all__ = ["CSV_COLUMNS", "DRAWS", "FORCED", "SELECTED", "Study", "StudyPart", "TrialRow", "exact_interval", "p_exact",
           "summary_markdown", "trials_csv", "write_study"]

"""The drift's Monte Carlo (`lrfsim study SCENARIO --drift NAME=VALUE ...`): how often `lrfcal check` calls a rig
drifted, with no drift (its false-alarm rate) and with a drift of known size (its detection rate), and which parameter
it names first.

Pair k: a recording of the scenario (seed ``s0 + 2k``) is calibrated (lrfcal.calibrate, as `lrfcal calibrate` does,
written as calibration.yaml), and a second recording of the rig changed by each drift (the scenario's truth moved, its
nominal values not; seed ``s0 + 2k + 1``: other noise and, cast anew, another laser phase) is checked against it by
lrfcal's check (lrfcal.check_recording, the use case of `lrfcal check`, reading the calibration.yaml back). One
calibration of the first recording serves every drift of the pair; the second recording of each drift has the same
seed (the same noise on another truth). Every recording is simulated whole (cast anew): a cast shared between the
two would share its laser phase's pattern on the markers, which the check would then not see as noise.

A drift is ``NAME=VALUE[,NAME=VALUE...]``: a change of the truth of the DH (a, alpha, b, beta), the mount (x, y, z,
roll, pitch, yaw), the clock offset (clock_offset) or the scanner's range offset (range_offset), with a unit (mm, cm,
m; deg, rad; ms, s; bare numbers are SI); ``none`` is no drift (the false-alarm rate).
"""

from __future__ import annotations

import csv
import io
import math
import re
import shutil
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import yaml

from lrfcal import DEFAULT_FALSE_ALARM, CalibConfig, calibrate, check_recording
from lrfcal.errors import InputError, LrfError
from lrfcal.io.calibration_yaml import calibration_dict
from lrfcal.io.files import atomic_folder, check_replaceable
from lrfcal.io.recording import read_recording
from lrfsim.scenario.file import Scenario

from .pool import run_counted
from .variants import with_field

#: drift name -> the scenario field it moves (the truth), and its SI unit
DRIFT_FIELDS: dict[str, tuple[str, str]] = {
    **{n: (f"rig.dh.{n}", "m" if n in ("a", "b") else "rad") for n in ("a", "alpha", "b", "beta")},
    **{n: (f"rig.mount.{n}", "m" if n in ("x", "y", "z") else "rad") for n in ("x", "y", "z", "roll", "pitch", "yaw")},
    "clock_offset": ("servo.clock_offset_s", "s"),
    "range_offset": ("sensor.systematic.range_offset_m", "m"),
}
_UNITS = {"m": ("m", 1.0), "cm": ("m", 0.01), "mm": ("m", 0.001), "rad": ("rad", 1.0), "deg": ("rad", math.pi / 180),
          "s": ("s", 1.0), "ms": ("s", 0.001)}
#: the first recording's and the second's seeds of pair k: s0 + 2k and s0 + 2k + 1
SEED_STRIDE = 2


@dataclass(frozen=True)
class Drift:
    """A change of the rig: its label as given and (name, value in SI units) per parameter moved (none: ())."""

    label: str
    changes: tuple[tuple[str, float], ...]

    @property
    def single(self) -> str:
        """The one DH, clock or range-offset parameter moved ("" for none, several, or the mount: the check names
        no mount parameter unless --fixed-mount)."""
        names = [n for n, v in self.changes if v != 0.0]
        return names[0] if len(names) == 1 else ""


def parse_drift(text: str) -> Drift:
    """``none`` or ``NAME=VALUE[UNIT][,NAME=VALUE[UNIT]...]`` (module docstring) -> Drift.

    Raises:
        InputError: an unknown name or unit, a value that is not a number, a unit of the wrong kind.
    """
    text = text.strip()
    if text.lower() in ("none", "0", ""):
        return Drift("none", ())
    changes = []
    for part in text.split(","):
        name, sep, value = part.partition("=")
        name = name.strip()
        if not sep or name not in DRIFT_FIELDS:
            raise InputError(f"--drift: {part!r}: expected NAME=VALUE with NAME one of {', '.join(DRIFT_FIELDS)} "
                             "(e.g. a=2mm, alpha=0.05deg, clock_offset=2ms), or none")
        m = re.fullmatch(r"\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*([a-z]*)\s*", value)
        if m is None:
            raise InputError(f"--drift: {part!r}: {value!r} is not a number with an optional unit (mm, deg, ms, ...)")
        unit = DRIFT_FIELDS[name][1]
        kind, factor = _UNITS.get(m.group(2) or unit, ("?", 0.0))
        if kind != unit:
            raise InputError(f"--drift: {part!r}: unit {m.group(2)!r} is not one of {name}'s "
                             f"({', '.join(u for u, (k, _) in _UNITS.items() if k == unit)})")
        changes.append((name, float(m.group(1)) * factor))
    return Drift(text, tuple(changes))


def drifted(scenario: Scenario, drift: Drift) -> Scenario:
    """The scenario with its truth moved by ``drift`` (the nominal values, the scene and the markers unchanged)."""
    out = scenario
    for name, delta in drift.changes:
        key = DRIFT_FIELDS[name][0]
        node = out.model_dump(mode="python")
        for k in key.split("."):
            node = node[k]
        out = with_field(out, key, float(node) + delta)
    return out


@dataclass(frozen=True)
class PairRow:
    """One pair and one drift: status ("checked" | "saved refused" | "check refused"), the check's verdict and exit
    code, its statistic, degrees of freedom, threshold, the parameters named (first first), the tested DH z, the
    reason of a refusal, and the seconds of the first calibration and of the check."""

    drift: str
    pair: int
    seed_saved: int
    seed_new: int
    status: str
    verdict: str
    exit_code: int
    statistic: float
    dof: int
    threshold: float
    named: tuple[str, ...]
    reason: str
    seconds_calibrate: float
    seconds_check: float

    @property
    def named_first(self) -> str:
        return self.named[0] if self.named else ""


CSV_COLUMNS = ("drift", "pair", "seed_saved", "seed_new", "status", "verdict", "exit_code", "statistic", "dof",
               "threshold", "named", "reason")


def _config() -> CalibConfig:
    """The first recording's calibration: the estimate and its checks (no clouds, no tunnel, no paper's method)."""
    return CalibConfig(baseline=False, clouds=False, geometry=False)


def run_pairs(scenario: Scenario, drifts: Sequence[Drift], pairs: Sequence[tuple[int, int, int]], *,
              false_alarm: float = DEFAULT_FALSE_ALARM, fixed_mount: bool = False,
              progress: Callable[[int], None] | None = None) -> list[PairRow]:
    """Run the pairs ``[(k, seed of the first recording, seed of the second), ...]`` for every drift (module
    docstring); ``progress(j)`` after the j-th pair."""
    from lrfsim.simulation.recording import write_recording
    from lrfsim.simulation.simulate import simulate

    rows: list[PairRow] = []
    variants = [(d, drifted(scenario, d)) for d in drifts]
    with tempfile.TemporaryDirectory(prefix="lrfsim-drift-") as tmp:
        for j, (k, s_saved, s_new) in enumerate(pairs):
            first = Path(tmp) / f"saved_{k}"
            sc = scenario.model_copy(update={"seed": int(s_saved)})
            write_recording(simulate(sc), sc, first)
            t0 = time.perf_counter()
            try:
                rec = read_recording(first, require_distances=(first / "distances.csv").exists())
                result = calibrate(rec, _config())
            except LrfError as err:
                rows += [PairRow(d.label, k, s_saved, s_new, "saved refused", "", err.exit_code, math.nan, 0,
                                 math.nan, (), " ".join(str(err).split()), time.perf_counter() - t0, math.nan)
                         for d, _ in variants]
                shutil.rmtree(first, ignore_errors=True)
                if progress is not None:
                    progress(j + 1)
                continue
            t_cal = time.perf_counter() - t0
            cal = Path(tmp) / f"cal_{k}.yaml"
            cal.write_text(yaml.safe_dump(calibration_dict(result), sort_keys=False), encoding="utf-8")
            shutil.rmtree(first, ignore_errors=True)
            for d, sc_d in variants:
                second = Path(tmp) / f"new_{k}"
                sc2 = sc_d.model_copy(update={"seed": int(s_new)})
                write_recording(simulate(sc2), sc2, second)
                t1 = time.perf_counter()
                try:
                    out = check_recording(cal, second, false_alarm=false_alarm, fixed_mount=fixed_mount)
                    t = out.test
                    rows.append(PairRow(d.label, k, s_saved, s_new, "checked", "drifted" if t.drifted else
                                        "still valid", 4 if t.drifted else 0, t.statistic, t.dof, t.threshold,
                                        tuple(p.name for p in t.moved), "", t_cal, time.perf_counter() - t1))
                except LrfError as err:
                    rows.append(PairRow(d.label, k, s_saved, s_new, "check refused", "", err.exit_code, math.nan, 0,
                                        math.nan, (), " ".join(str(err).split()), t_cal, time.perf_counter() - t1))
                shutil.rmtree(second, ignore_errors=True)
            if progress is not None:
                progress(j + 1)
    return rows


def _pool_pairs(scenario: Scenario, drifts: Sequence[Drift], false_alarm: float, fixed_mount: bool,
                pairs: Sequence[tuple[int, int, int]], progress: Callable[[int], None] | None = None) -> list[PairRow]:
    return run_pairs(scenario, drifts, pairs, false_alarm=false_alarm, fixed_mount=fixed_mount, progress=progress)


def _worker_policy() -> None:
    from lrfcal import apply_memory_policy, apply_thread_policy, keep_freed_memory

    apply_memory_policy()
    keep_freed_memory()
    apply_thread_policy()


@dataclass(frozen=True)
class DriftStudy:
    """A drift study: the scenario's name, the drifts, the rows (pair-major), the false-alarm rate, wall seconds."""

    name: str
    drifts: tuple[Drift, ...]
    rows: tuple[PairRow, ...]
    false_alarm: float
    fixed_mount: bool
    seconds: float
    workers: int

    def of(self, drift: Drift) -> list[PairRow]:
        return [r for r in self.rows if r.drift == drift.label]


def drift_study(scenario: Scenario, drifts: Sequence[Drift], pairs: int, *, seed0: int | None = None,
                workers: int = 1, false_alarm: float = DEFAULT_FALSE_ALARM, fixed_mount: bool = False,
                progress: Callable[[int, int], None] | None = None) -> DriftStudy:
    """Run ``pairs`` pairs for every drift (module docstring), on ``workers`` processes (one pair a batch)."""
    if pairs < 1:
        raise InputError(f"study: --trials must be >= 1, got {pairs}")
    t0 = time.perf_counter()
    s0 = scenario.seed if seed0 is None else int(seed0)
    items = [(k, s0 + SEED_STRIDE * k, s0 + SEED_STRIDE * k + 1) for k in range(pairs)]
    for d in drifts:  # every drift makes a valid scenario before any pair runs
        drifted(scenario, d)
    rows: list[PairRow] = []
    if workers > 1:
        task = partial(_pool_pairs, scenario, tuple(drifts), false_alarm, fixed_mount)
        for part in run_counted(task, [[it] for it in items], workers, _worker_policy,
                                None if progress is None else (lambda j: progress(j, pairs))):
            rows.extend(part)
    else:
        rows = run_pairs(scenario, drifts, items, false_alarm=false_alarm, fixed_mount=fixed_mount,
                         progress=None if progress is None else (lambda j: progress(j, pairs)))
    rows.sort(key=lambda r: (r.pair, [d.label for d in drifts].index(r.drift)))
    return DriftStudy(scenario.name, tuple(drifts), tuple(rows), false_alarm, fixed_mount,
                      time.perf_counter() - t0, workers)


def interval(k: int, n: int, level: float = 0.95) -> tuple[float, float]:
    """The Clopper-Pearson interval of a binomial rate k / n at ``level`` (exact: it never undercovers)."""
    from scipy.stats import beta

    if n == 0:
        return math.nan, math.nan
    a = (1 - level) / 2
    lo = 0.0 if k == 0 else float(beta.ppf(a, k, n - k + 1))
    hi = 1.0 if k == n else float(beta.ppf(1 - a, k + 1, n - k))
    return lo, hi


def drift_summary(s: DriftStudy) -> list[dict[str, object]]:
    """Per drift: pairs checked, called drifted (rate and its 95 % interval), named first right (for a single
    parameter's drift), refusals by kind, and the median seconds of a calibration and of a check."""
    out = []
    for d in s.drifts:
        rows = s.of(d)
        checked = [r for r in rows if r.status == "checked"]
        hit = sum(r.verdict == "drifted" for r in checked)
        first = sum(r.verdict == "drifted" and r.named_first == d.single for r in checked) if d.single else None
        lo, hi = interval(hit, len(checked))
        secs = sorted(r.seconds_check for r in checked)
        cal = sorted(r.seconds_calibrate for r in rows if math.isfinite(r.seconds_calibrate))
        out.append({"drift": d.label, "pairs": len(rows), "checked": len(checked), "drifted": hit,
                    "rate": hit / len(checked) if checked else math.nan, "interval": (lo, hi),
                    "named_first": first, "single": d.single,
                    "saved_refused": sum(r.status == "saved refused" for r in rows),
                    "check_refused": sum(r.status == "check refused" for r in rows),
                    "median_check_s": secs[len(secs) // 2] if secs else math.nan,
                    "median_calibrate_s": cal[len(cal) // 2] if cal else math.nan})
    return out


def summary_markdown(s: DriftStudy) -> str:
    """summary.md of a drift study: one row per drift."""
    lines = [f"# Drift study of {s.name}", "",
             f"{len(s.rows) // max(len(s.drifts), 1)} pairs per drift ({s.workers} "
             f"worker{'s' if s.workers > 1 else ''}, {s.seconds:.0f} s); `lrfcal check` at a false-alarm rate of "
             f"{100 * s.false_alarm:g} %"
             + (" with --fixed-mount" if s.fixed_mount else "") + ". Pair k: a recording (seed s0 + 2k) calibrated, "
             "a second one (seed s0 + 2k + 1) of the rig changed by the drift checked against it. Rate: pairs "
             "called drifted of those checked, with its 95 % Clopper-Pearson interval (with no drift: the false-alarm "
             "rate).", "",
             "| drift | checked | called drifted | rate | 95 % interval | named first right "
             "| refused (first / check) |",
             "|---|---|---|---|---|---|---|"]
    for r in drift_summary(s):
        lo, hi = r["interval"]  # type: ignore[misc]
        nf = "-" if r["named_first"] is None else f"{r['named_first']} of {r['drifted']} ({r['single']})"
        lines.append(f"| {r['drift']} | {r['checked']} | {r['drifted']} | {100 * float(r['rate']):.1f} % | "  # type: ignore[arg-type]
                     f"{100 * lo:.1f}-{100 * hi:.1f} % | {nf} | {r['saved_refused']} / {r['check_refused']} |")
    reasons: dict[str, int] = {}
    for row in s.rows:
        if row.reason:
            reasons[row.reason[:300]] = reasons.get(row.reason[:300], 0) + 1
    if reasons:
        lines += ["", "Refusals:", *(f"- {k} x {v}" for k, v in sorted(reasons.items(), key=lambda kv: -kv[1]))]
    return "\n".join(lines) + "\n"


def pairs_csv(s: DriftStudy) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(CSV_COLUMNS)
    for r in s.rows:
        w.writerow([r.drift, r.pair, r.seed_saved, r.seed_new, r.status, r.verdict, r.exit_code,
                    "" if not math.isfinite(r.statistic) else f"{r.statistic:.6g}", r.dof,
                    "" if not math.isfinite(r.threshold) else f"{r.threshold:.6g}", " ".join(r.named), r.reason])
    return buf.getvalue()


def write_drift_study(s: DriftStudy, out_dir: str | Path, *, overwrite: bool = False) -> Path:
    """Write pairs.csv and summary.md into ``out_dir`` atomically."""
    out = check_replaceable(out_dir, overwrite)
    with atomic_folder(out, "lrfsim study") as tmp:
        (tmp / "pairs.csv").write_text(pairs_csv(s), encoding="utf-8")
        (tmp / "summary.md").write_text(summary_markdown(s), encoding="utf-8")
    return out


__all__ = ["DRIFT_FIELDS", "Drift", "DriftStudy", "PairRow", "drift_study", "drift_summary", "drifted", "interval",
           "pairs_csv", "parse_drift", "run_pairs", "summary_markdown", "write_drift_study"]

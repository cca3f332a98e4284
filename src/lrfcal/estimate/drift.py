"""Has the rig changed? Two calibrations of one rig compared: per parameter the change, its sigma and z, and one joint
test of "nothing changed" at a stated false-alarm rate (`lrfcal check`, lrfcal.commands.check).

The two calibrations come from independent recordings, so the covariance of their difference d = new - saved is the
sum of theirs, C = C_saved + C_new, and without a change d ~ N(0, C). The joint test's statistic over the k tested
parameters is chi2 = d^T C^-1 d, chi-square with k degrees of freedom without a change; the rig is called drifted when
it exceeds that distribution's quantile at 1 - false_alarm (Mahalanobis' distance; e.g. Bar-Shalom, Li and
Kirubarajan, *Estimation with Applications to Tracking and Navigation*, 2001, Sec. 1.4.17 and 5.4 for the
normalised error and its chi-square test). Its false-alarm rate is the stated one only as far as both covariances are
honest: a covariance too small raises it (docs/check.md measures it).

Which parameter explains the test: the one whose removal lowers the statistic most (d_-i^T C_-i^-1 d_-i over the
others), the others ranked alike; a drifted test names every parameter whose own z is beyond the two-sided quantile
at the same rate, and always the first one.

The smallest drift detected: a drift delta of parameter i alone gives the statistic a non-central chi-square with k
degrees of freedom and non-centrality delta^2 (C^-1)_ii; the drift detected with probability p is the delta whose
non-central distribution exceeds the threshold with probability p (:func:`detectable_drift`; `lrfsim plan`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from lrfcal.errors import InputError

FloatArray = NDArray[np.float64]

#: the false-alarm rate of `lrfcal check` unless --false-alarm says otherwise
DEFAULT_FALSE_ALARM = 0.05


@dataclass(frozen=True)
class Compared:
    """One parameter of the rig in both calibrations: its values (SI units), the change new - saved (angles
    wrapped), the sigma of the change (both covariances), z = change / sigma; ``tested`` whether it entered the joint
    test (``why`` not, when it did not), ``drifted`` whether the check names it; ``explains``: how much the statistic
    drops without it (0 when not tested); each calibration's own 1-sigma of it (NaN when not tested)."""

    name: str
    saved: float
    new: float
    change: float
    sigma: float
    z: float
    tested: bool
    why: str = ""
    drifted: bool = False
    explains: float = 0.0
    sigma_saved: float = math.nan
    sigma_new: float = math.nan


@dataclass(frozen=True)
class DriftTest:
    """The joint test of "nothing changed" over the tested parameters: the statistic d^T C^-1 d, its degrees of
    freedom, the threshold (chi-square quantile at 1 - false_alarm), the rate; every parameter compared (tested or
    not, in the order given), and whether the rig drifted."""

    parameters: tuple[Compared, ...]
    statistic: float
    dof: int
    threshold: float
    false_alarm: float

    @property
    def drifted(self) -> bool:
        return self.dof > 0 and self.statistic > self.threshold

    @property
    def tested(self) -> tuple[Compared, ...]:
        return tuple(p for p in self.parameters if p.tested)

    @property
    def not_tested(self) -> tuple[Compared, ...]:
        return tuple(p for p in self.parameters if not p.tested)

    @property
    def moved(self) -> tuple[Compared, ...]:
        """The parameters the check names as moved, the one that explains most of the statistic first."""
        return tuple(sorted((p for p in self.parameters if p.drifted), key=lambda p: -p.explains))

    @property
    def named_first(self) -> str:
        """The parameter named first ("" when the rig did not drift)."""
        return self.moved[0].name if self.moved else ""

    def to_dict(self) -> dict[str, object]:
        """check.yaml's test and parameters (plain values; NaN as None)."""

        def f(v: float) -> float | None:
            return float(v) if math.isfinite(v) else None

        return {
            "test": {"statistic": f(self.statistic), "dof": self.dof, "threshold": f(self.threshold),
                     "false_alarm": self.false_alarm, "drifted": self.drifted,
                     "named": [p.name for p in self.moved]},
            "parameters": {p.name: {"saved": f(p.saved), "new": f(p.new), "change": f(p.change), "sigma": f(p.sigma),
                                    "z": f(p.z), "tested": p.tested, "drifted": p.drifted,
                                    "sigma_saved": f(p.sigma_saved), "sigma_new": f(p.sigma_new),
                                    **({"explains": f(p.explains)} if p.tested else {"why": p.why})}
                           for p in self.parameters},
        }


def check_rate(false_alarm: float) -> float:
    """``false_alarm`` when it is a probability strictly between 0 and 0.5.

    Raises:
        InputError: naming the value and the range.
    """
    if not (isinstance(false_alarm, float | int) and math.isfinite(false_alarm) and 0.0 < false_alarm < 0.5):
        raise InputError(f"--false-alarm: expected a rate between 0 and 0.5 (e.g. 0.05 for 5 %), got {false_alarm!r}")
    return float(false_alarm)


def chi2_threshold(dof: int, false_alarm: float) -> float:
    """The chi-square quantile at 1 - false_alarm with ``dof`` degrees of freedom (inf for none)."""
    from scipy.stats import chi2

    return float(chi2.isf(false_alarm, dof)) if dof > 0 else math.inf


def _statistic(d: FloatArray, C: FloatArray) -> float:
    """d^T C^-1 d, computed column-scaled (the parameters mix metres, radians and seconds)."""
    if d.size == 0:
        return 0.0
    s = np.sqrt(np.diag(C))
    return float(np.linalg.solve(C / np.outer(s, s), d / s) @ (d / s))


def drift_test(names: Sequence[str], saved: Mapping[str, float], new: Mapping[str, float],
               change: Mapping[str, float], cov_saved: FloatArray, cov_new: FloatArray, false_alarm: float,
               not_tested: Mapping[str, str] | None = None) -> DriftTest:
    """The joint test over the parameters ``names`` (the order of ``cov_saved`` and ``cov_new``, each (k, k), the two
    calibrations' covariances of them), their values in each (``saved``, ``new``) and their ``change`` (new - saved,
    angles wrapped: the caller's, so that a rotation's change can be a rotation vector); ``not_tested``: the other
    parameters compared, each with why it is not tested (listed, never called valid)."""
    false_alarm = check_rate(false_alarm)
    names = list(names)
    k = len(names)
    d = np.array([change[n] for n in names], dtype=float)
    Cs, Cn = np.asarray(cov_saved, dtype=float), np.asarray(cov_new, dtype=float)
    C = Cs + Cn
    C = 0.5 * (C + C.T)
    stat = _statistic(d, C)
    threshold = chi2_threshold(k, false_alarm)
    sig = np.sqrt(np.diag(C)) if k else np.zeros(0)
    explains = [stat - _statistic(np.delete(d, i), np.delete(np.delete(C, i, 0), i, 1)) for i in range(k)]
    from scipy.stats import norm

    z_each = float(norm.isf(false_alarm / 2))
    drifted = stat > threshold
    first = int(np.argmax(explains)) if drifted and k else -1
    rows = [Compared(n, float(saved[n]), float(new[n]), float(d[i]), float(sig[i]), float(d[i] / sig[i]), True,
                     drifted=bool(drifted and (i == first or abs(d[i] / sig[i]) > z_each)),
                     explains=float(explains[i]), sigma_saved=float(math.sqrt(Cs[i, i])),
                     sigma_new=float(math.sqrt(Cn[i, i])))
            for i, n in enumerate(names)]
    for n, why in (not_tested or {}).items():
        s, nw = float(saved.get(n, math.nan)), float(new.get(n, math.nan))
        ch = float(change.get(n, nw - s))
        rows.append(Compared(n, s, nw, ch, math.nan, math.nan, False, why=why))
    return DriftTest(tuple(rows), stat, k, threshold, false_alarm)


def detectable_drift(cov: FloatArray, false_alarm: float = DEFAULT_FALSE_ALARM, power: float = 0.95
                     ) -> FloatArray:
    """(k,) the smallest drift of each parameter alone that the joint test over all k detects with probability
    ``power`` at ``false_alarm``, for ``cov`` (k, k) the covariance of the difference (C_saved + C_new): the
    non-centrality lam with P(chi2'_k(lam) > threshold) = power, over (C^-1)_ii (module docstring). inf where a
    parameter is not determined."""
    from scipy.optimize import brentq
    from scipy.stats import ncx2

    C = np.asarray(cov, dtype=float)
    k = C.shape[0]
    if k == 0:
        return np.zeros(0)
    threshold = chi2_threshold(k, check_rate(false_alarm))
    lam = brentq(lambda x: float(ncx2.sf(threshold, k, x)) - power, 1e-9, 1e4)
    s = np.sqrt(np.diag(C))
    try:
        inv = np.linalg.inv(C / np.outer(s, s)) / np.outer(s, s)
    except np.linalg.LinAlgError:
        return np.full(k, math.inf)
    diag = np.diag(inv)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(diag > 0, np.sqrt(lam / diag), math.inf)


__all__ = ["DEFAULT_FALSE_ALARM", "Compared", "DriftTest", "check_rate", "chi2_threshold", "detectable_drift",
           "drift_test"]

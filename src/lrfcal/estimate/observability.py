"""What the data determine, decided from the information matrix itself (never from a solver that ran away).

Given the information I (k, k) of the estimated core unknowns (lrfcal.model.unknowns.CORE_NAMES: the mount, the DH
parameters, the clock offset), the DH block is marginalised over the others (Schur complement) and normalised by
:data:`LIMITS`, the 1-sigma beyond which a parameter counts as not calibrated: N = D I_dh D, D = diag(limits).
An eigenvalue e of N belongs to a combination of DH parameters whose 1-sigma is 1 / sqrt(e) limits: e < 1 means
that combination is undetermined even when each parameter's own sigma looks acceptable. The eigenvector names the
combination in words ("b against alpha"), with what would determine it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

#: 1-sigma above which a parameter (or a normalised combination) is not calibrated by the recording: a calibration
#: that cannot do better than a design drawing and a ruler (a few mm, about a degree) has calibrated nothing.
LIMITS: dict[str, float] = {
    "x": 0.02, "y": 0.02, "z": 0.02,
    "rx": math.radians(1.0), "ry": math.radians(1.0), "rz": math.radians(1.0),
    "a": 0.005, "alpha": math.radians(1.0), "b": 0.005, "beta": math.radians(1.0),
    "clock_offset": 0.005,
}
DH = ("a", "alpha", "b", "beta")
#: a scan plane within this angle of perpendicular to the motor axis (DH alpha near 0 or 180 deg): b and the
#: mount's offset along the motor axis are nearly one quantity (Tz(b) commutes with Rz(lambda) at alpha = 0)
NEAR_PERPENDICULAR_RAD = math.radians(20.0)
#: a range offset or marker range bias this uncertain is held at 0 rather than estimated [m]
RANGE_BIAS_LIMIT_M = 0.005

_HINTS = {
    frozenset({"alpha", "b"}): "the markers are all at about one distance along the motor axis: place markers at "
                               "several depths along the axis (a board extending along it, or a second board)",
    frozenset({"a"}): "a needs markers at several ranges, seen over a wide sweep of the motor angle",
    # b moves a marker across the scan plane as the mount's turn about the motor axis does, by its distance from the
    # axis: markers all at one distance from it (a board beside the rig facing the axis) cannot tell them apart
    frozenset({"b"}): "b needs markers spread along the motor axis and at several distances from it (a board "
                      "turned obliquely to the axis, or markers near and far from it)",
    frozenset({"alpha"}): "alpha needs markers spread along the motor axis and seen over a wide sweep",
    frozenset({"beta"}): "beta needs markers spread across the scan's field of view",
}


@dataclass(frozen=True)
class Observability:
    """The DH block's marginal 1-sigma (4,) (inf where undetermined), the spectrum (4,) of its normalised
    information (ascending) and the weakest combination (4,) (unit vector over DH, in limit units)."""

    sigma: FloatArray
    spectrum: FloatArray
    weakest: FloatArray
    #: the scan plane's angle from perpendicular to the motor axis [rad] (NaN: not given)
    tilt_rad: float = math.nan

    @property
    def limits(self) -> FloatArray:
        return np.array([LIMITS[n] for n in DH])

    @property
    def weakest_sigma_in_limits(self) -> float:
        """1-sigma of the weakest combination, in units of the limits (> 1: undetermined)."""
        e = float(self.spectrum[0])
        return math.inf if e <= 0 else 1.0 / math.sqrt(e)

    @property
    def determined(self) -> bool:
        return self.weakest_sigma_in_limits <= 1.0 and bool(np.all(self.sigma <= self.limits))

    @property
    def undetermined(self) -> tuple[str, ...]:
        """DH parameters with a large share in the weakest combination when that combination is undetermined."""
        if self.determined:
            return ()
        return tuple(n for n, v in zip(DH, self.weakest, strict=True) if abs(v) >= 0.3)

    def describe(self) -> str:
        """The weakest combination in words, e.g. 'b against alpha'."""
        order = np.argsort(-np.abs(self.weakest))
        names = [DH[i] for i in order if abs(self.weakest[i]) >= 0.3] or [DH[int(order[0])]]
        if len(names) == 1:
            return f"{names[0]} alone"
        return " against ".join(names)

    def hint(self) -> str:
        names = frozenset(n for n, v in zip(DH, self.weakest, strict=True) if abs(v) >= 0.3)
        if "b" in names and self.tilt_rad < NEAR_PERPENDICULAR_RAD:
            return (f"the scan plane is {math.degrees(self.tilt_rad):.1f} deg from perpendicular to the motor axis: "
                    "there b (the scanner's offset along its own axis) and the mount's offset along the motor axis "
                    "are nearly one quantity (exactly so at 0 deg) and only their sum is determined; tilt the scan "
                    "plane further from perpendicular, or spread markers far along the motor axis")
        for key, text in _HINTS.items():
            if key <= names and len(key) > 1:
                return text
        for key, text in _HINTS.items():
            if key == names:
                return text
        return "add markers at other ranges and motor angles, or sweep more passes"

    def summary(self) -> str:
        """One line: the weakest combination, its sigma in limits, and each DH sigma."""
        return (f"weakest direction {self.describe()} at {self.weakest_sigma_in_limits:.2g} of the limit; 1-sigma: "
                + sigma_words(self.sigma))


def _fmt(name: str, v: float) -> str:
    """A DH parameter's 1-sigma in mm or deg; "unbounded" where it is not finite or beyond a kilometre or half a
    turn (a null direction's numerical remainder)."""
    angle = name in ("alpha", "beta")
    if not (math.isfinite(v) and v < (math.pi if angle else 1e3)):
        return "unbounded"
    return f"{math.degrees(v):.3g} deg" if angle else f"{v * 1000:.3g} mm"


def sigma_words(dh_sigma: FloatArray) -> str:
    """The 1-sigma of a, alpha, b, beta ((4,), m and rad) in words."""
    return ", ".join(f"{n} {_fmt(n, float(s))}" for n, s in zip(DH, dh_sigma, strict=True))


def analyse(information: FloatArray, names: tuple[str, ...], alpha: float | None = None) -> Observability:
    """Observability of the DH parameters from the information (k, k) over ``names`` (must contain a, alpha, b,
    beta; the others are marginalised); ``alpha`` [rad], the DH twist, lets the hint name a scan plane nearly
    perpendicular to the motor axis."""
    N = _normalised(np.asarray(information, dtype=float), names, DH)
    D = np.array([LIMITS[n] for n in DH])
    vals, vecs = np.linalg.eigh(N)
    scale = max(float(np.abs(vals).max()), 1e-300)
    vals = np.where(vals > 1e-12 * scale, vals, 0.0)
    # marginal sigma of each DH parameter: sqrt(diag(N^+)) * limit, infinite along null directions
    sigma = np.empty(4)
    for i in range(4):
        null_share = sum(vecs[i, j] ** 2 for j in range(4) if vals[j] == 0.0)
        if null_share > 1e-6:
            sigma[i] = math.inf
        else:
            sigma[i] = math.sqrt(sum(vecs[i, j] ** 2 / vals[j] for j in range(4) if vals[j] > 0)) * D[i]
    weakest = vecs[:, 0] * (1.0 if vecs[np.argmax(np.abs(vecs[:, 0])), 0] >= 0 else -1.0)
    tilt = math.nan if alpha is None else math.asin(min(1.0, abs(math.sin(alpha))))
    return Observability(sigma=sigma, spectrum=vals, weakest=weakest, tilt_rad=tilt)


def marginal_information(A: FloatArray, keep: Sequence[int]) -> FloatArray:
    """The information of the ``keep`` block of A (k, k) with the others marginalised: A_kk - A_ko A_oo^+ A_ok."""
    keep = list(keep)
    other = [i for i in range(A.shape[0]) if i not in keep]
    if not other:
        return A[np.ix_(keep, keep)]
    Akk, Ako, Aoo = A[np.ix_(keep, keep)], A[np.ix_(keep, other)], A[np.ix_(other, other)]
    return Akk - Ako @ np.linalg.pinv(Aoo, rcond=1e-12) @ Ako.T


def marginal(info: FloatArray, names: Sequence[str], keep: Sequence[str]) -> FloatArray:
    """:func:`marginal_information` of the unknowns ``keep`` of ``info`` (k, k) over ``names``, symmetrised."""
    A = marginal_information(info, [names.index(n) for n in keep])
    return 0.5 * (A + A.T)


def _normalised(info: FloatArray, names: Sequence[str], keep: Sequence[str]) -> FloatArray:
    """N = D I D (module docstring) of the unknowns ``keep`` (D their LIMITS), the others marginalised."""
    D = np.array([LIMITS[n] for n in keep])
    return D[:, None] * marginal(info, names, keep) * D[None, :]


@dataclass(frozen=True)
class Information:
    """An information (k, k) over ``names``, without any prior: holding an unknown deletes its row and column (the
    nuisances' elimination does not involve it), and a prior on the DH parameters adds to their diagonal, so every
    judgement below takes its part of this one matrix instead of assembling the data's Jacobian again."""

    info: FloatArray
    names: tuple[str, ...]

    def part(self, held: Sequence[str] = (), dh_prior_sigma: FloatArray | None = None
             ) -> tuple[FloatArray, tuple[str, ...]]:
        """The information without the unknowns ``held``, with the DH prior of 1-sigma ``dh_prior_sigma`` (4,)."""
        keep = [i for i, n in enumerate(self.names) if n not in held]
        names = tuple(self.names[i] for i in keep)
        info = self.info[np.ix_(keep, keep)].copy()
        if dh_prior_sigma is not None:
            for i, n in enumerate(names):
                if n in DH:
                    info[i, i] += 1.0 / float(dh_prior_sigma[DH.index(n)]) ** 2
        return info, names

    def sigma(self, name: str) -> float:
        """The marginal 1-sigma of one unknown (from the pseudo-inverse: large, not inf, when undetermined)."""
        k = self.names.index(name)
        return float(np.sqrt(np.linalg.pinv(self.info)[k, k]))

    def undetermined_dh(self, held: Sequence[str] = (), dh_prior_sigma: FloatArray | None = None
                        ) -> tuple[str, ...]:
        """The DH parameters to hold, one at a time, until every one left and every combination of them is
        determined within LIMITS: each time the one with the largest share in the weakest combination (``held``:
        other unknowns held; with the DH prior)."""
        hold: list[str] = []
        while len(hold) < len(DH):
            info, names = self.part([*held, *hold], dh_prior_sigma)
            free = [n for n in DH if n not in hold]
            N = _normalised(info, names, free)
            w = np.linalg.eigvalsh(N)
            if w[0] > 1e-12 * max(float(w[-1]), 1e-300) and 1.0 / math.sqrt(float(w[0])) <= 1.0 \
                    and np.all(np.sqrt(np.diag(np.linalg.inv(N))) <= 1.0):
                break
            hold.append(free[int(np.argmax(np.abs(np.linalg.eigh(N)[1][:, 0])))])  # its weakest combination's
        return tuple(hold)


def of_solution(information: FloatArray | None, names: Sequence[str], dh_sigma: FloatArray, alpha: float
                ) -> Observability:
    """The observability of a solution's DH parameters: its ``information`` over ``names``, ``dh_sigma`` (4,) its
    reported 1-sigma, ``alpha`` its DH twist [rad]. Not determined (``.determined`` False) where the information's
    weakest combination or some parameter is beyond :data:`LIMITS`, where a reported sigma is (a widened covariance:
    those parameters are then named), or without an information (rank loss)."""
    sigma = np.asarray(dh_sigma, dtype=float)
    tilt = math.asin(min(1.0, abs(math.sin(alpha))))
    if information is None:
        return Observability(sigma=np.full(4, math.inf), spectrum=np.zeros(4), weakest=np.full(4, 0.5),
                             tilt_rad=tilt)
    obs = analyse(information, tuple(names), alpha)
    if not obs.determined or within_limits(sigma):
        return obs
    beyond = beyond_limits(dict(zip(DH, sigma.tolist(), strict=True)))
    over = np.array([1.0 if n in beyond else 0.0 for n in DH])
    return Observability(sigma=np.maximum(obs.sigma, np.where(np.isfinite(sigma), sigma, math.inf)),
                         spectrum=obs.spectrum, weakest=over / float(np.linalg.norm(over)),
                         tilt_rad=tilt)


def of_covariance(cov: FloatArray, names: Sequence[str], alpha: float | None = None) -> Observability:
    """:func:`analyse` of the information a covariance (k, k) over ``names`` holds (its inverse; the pseudo-inverse
    where it is singular): the judgement of a final, widened covariance, as calibrate's observability check makes it
    of a solution (its information is the inverse of its covariance) and plan of the covariance it predicts."""
    C = np.asarray(cov, dtype=float)
    finite = np.isfinite(np.diag(C))
    keep = [i for i, n in enumerate(names) if finite[i]]
    kept = tuple(names[i] for i in keep)
    if any(n not in kept for n in DH):
        tilt = math.nan if alpha is None else math.asin(min(1.0, abs(math.sin(alpha))))
        return Observability(sigma=np.array([math.inf if n not in kept else math.sqrt(C[names.index(n),
                             names.index(n)]) for n in DH]), spectrum=np.zeros(4), weakest=np.full(4, 0.5),
                             tilt_rad=tilt)
    sub = C[np.ix_(keep, keep)]
    return analyse(np.linalg.pinv(0.5 * (sub + sub.T), rcond=1e-12), kept, alpha)


@dataclass(frozen=True)
class Verdict:
    """Whether the DH parameters are determined, by the one rule ``lrfcal calibrate`` refuses on (exit 3) and
    ``lrfsim plan`` predicts: the marker returns alone at the start (``start``: calibrate refuses before it solves
    where they do not determine the DH) and the final covariance (``final``: calibrate's observability check after it
    solves, with every widening; :func:`of_covariance`) must determine the DH, and the nominal must tell the rig from
    its mirror image (``mirror``)."""

    start: Observability
    final: Observability
    #: whether the nominal tells the rig from its mirror image, and the words (lrfcal.estimate.checks.mirror_check:
    #: calibrate refuses where it cannot; None: not judged)
    mirror: tuple[bool, str] | None = None

    @property
    def determined(self) -> bool:
        return self.start.determined and self.final.determined and (self.mirror is None or self.mirror[0])

    def reason(self) -> str:
        """Why not (empty when determined): the judgement that fails, its weakest combination and every sigma."""
        if self.determined:
            return ""
        # in the order calibrate names them: before it solves, then its checks (mirror image before observability)
        if self.start.determined and self.mirror is not None and not self.mirror[0]:
            return f"the rig cannot be told from its mirror image: {self.mirror[1]}"
        obs, when = ((self.start, "the marker returns alone, judged before solving") if not self.start.determined
                     else (self.final, "the final covariance, judged after solving"))
        names = obs.undetermined or tuple(n for n, v, lim in zip(DH, obs.sigma, obs.limits, strict=True)
                                          if not v <= lim)
        return (f"{', '.join(names) or 'the DH parameters'} not determined by {when} ({obs.describe()} at "
                f"{obs.weakest_sigma_in_limits:.2g} of the limit; 1-sigma {sigma_words(obs.sigma)}): {obs.hint()}")


def unjudged_refusal(obs: Observability, what: str, and_: str, disagreement: str) -> str:
    """The refusal where blobs disagree with the marker map (``disagreement``, lrfcal.stages.association's words) at a
    solution of ``what`` (e.g. "the markers alone") whose observability is ``obs``; ``and_``: what else is missing.

    The causes are ranked: where the DH parameters are not determined, good markers look moved (the fit puts them
    where its loose DH can) and a wrong match cannot be told from a moved marker, so the refusal leads with that
    cause and its remedy (the hint), and names the disagreement after it as a symptom, without the "moved after
    taping?" that would blame the wrong thing. Only where ``what`` determine them is the disagreement the finding."""
    if obs.determined:
        return (f"{disagreement}: check the tape distances and the markers' positions, and sweep slower or more "
                "passes, so that several scan lines cross every marker")
    limits = np.array([LIMITS[n] for n in DH])
    names = obs.undetermined or tuple(n for n, s, lim in zip(DH, obs.sigma, limits, strict=True) if not s <= lim)
    return (f"{what} do not determine {', '.join(names) or 'the DH parameters'} here ({obs.describe()}; 1-sigma "
            f"{sigma_words(obs.sigma)}; limits {LIMITS['b'] * 1000:g} mm, {math.degrees(LIMITS['beta']):g} deg)"
            f"{' ' + and_ if and_ else ''}: {obs.hint()}; at such a solution good markers look moved and a wrong "
            f"match cannot be told from a moved marker ({disagreement.replace(' (moved after taping?)', '')})")


def beyond_limits(sigma: Mapping[str, float]) -> tuple[str, ...]:
    """The DH parameters among ``sigma`` (name -> 1-sigma, m or rad) whose 1-sigma is not finite or beyond
    :data:`LIMITS`, the farthest beyond first (empty: every one is determined)."""
    over = {n: (v / LIMITS[n] if math.isfinite(v) else math.inf) for n, v in sigma.items()}
    return tuple(sorted((n for n, r in over.items() if r > 1.0), key=lambda n: -over[n]))


def within_limits(dh_sigma: NDArray[np.float64]) -> bool:
    """Whether every DH parameter's 1-sigma (a, alpha, b, beta: (4,) in m and rad) is within :data:`LIMITS`
    (:func:`beyond_limits` names none)."""
    return not beyond_limits(dict(zip(DH, np.asarray(dh_sigma, dtype=float).tolist(), strict=True)))


__all__ = ["DH", "LIMITS", "NEAR_PERPENDICULAR_RAD", "RANGE_BIAS_LIMIT_M", "Information", "Observability",
           "Verdict", "analyse", "beyond_limits", "marginal", "marginal_information", "of_covariance", "of_solution",
           "sigma_words", "unjudged_refusal", "within_limits"]

"""The checks a result must pass before it is written, for both ways of calibrating (lrfcal.stages.markers,
lrfcal.stages.targetless):
convergence, observability, the reduced chi-square, a second opinion from two independent parts of the recording, and
the servo's direction; and the refusal when one fails.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import replace
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from lrfcal.errors import CalibrationError
from lrfcal.estimate import observability
from lrfcal.estimate.covariance import widen
from lrfcal.estimate.engine import solved
from lrfcal.estimate.request import MarkerRequest, PlaneOptions, PlaneRequest
from lrfcal.model.chart import gauge_distance
from lrfcal.model.kinematics import DH, PARAM_NAMES, dh_twins
from lrfcal.model.motor import CLOCK_OFFSET_PASS_SHARE, MAX_CLOCK_OFFSET_S, Clock
from lrfcal.model.unknowns import CORE_NAMES, dh_difference, wrap_pi
from lrfcal.types import Check, MarkerMap, Solution, SurfaceReturns

FloatArray = NDArray[np.float64]
DH_NAMES = observability.DH


class CheckConfig(Protocol):
    """The configuration the checks read: their slice of lrfcal.config.CalibConfig (which satisfies it; validated
    and written whole into calibration.yaml there)."""

    @property
    def force(self) -> bool: ...
    @property
    def max_reduced_chi2(self) -> float: ...
    @property
    def nominal_tolerance(self) -> tuple[float, float, float, float]: ...
    @property
    def range_sigma_m(self) -> float | None: ...
    @property
    def second_opinion_p(self) -> float: ...
    @property
    def range_pattern(self) -> bool: ...


#: failed checks that follow from another failed check, by the check they follow from: where the data do not
#: determine the DH parameters, the solver may stop anywhere along the loose direction (convergence) and the
#: recording's parts disagree along it (second opinion), so those failures and their remedies come after the cause
#: (lrfcal.estimate.observability.unjudged_refusal ranks a disagreement with the marker map the same way)
FOLLOWS_FROM = {"convergence": "observability", "second opinion": "observability"}


def refuse_failed(checks: list[Check], config: CheckConfig) -> None:
    """Raise CalibrationError naming the failed check the data support as the cause: the first (in the checks'
    order) that does not follow from another failed one (:data:`FOLLOWS_FROM`), and how many more failed; unless
    ``config.force``.

    Raises:
        CalibrationError: a check failed and the result may not be written.
    """
    failed = [c for c in checks if not c.passed]
    names = {c.name for c in failed}
    failed.sort(key=lambda c: FOLLOWS_FROM.get(c.name) in names)  # stable: a consequence after its cause
    if failed and not config.force:
        c = failed[0]
        raise CalibrationError(f"{c.name}: {c.detail}"
                               + ("" if len(failed) == 1 else f" (and {len(failed) - 1} more failed checks)")
                               + "; --force writes the result anyway with the failed checks recorded")


def clock_offset_check(sol: Solution, bound_s: float, shortest_pass_s: float) -> Check:
    """The clock offset reported (estimated or held) lies within ``bound_s`` (lrfcal.model.motor.clock_offset_bound_s:
    the smaller of MAX_CLOCK_OFFSET_S and a share of the sweep's ``shortest_pass_s``)."""
    tau = sol.clock_offset_s
    ok = bool(abs(tau) <= bound_s)
    detail = (f"{tau * 1000:+.1f} ms, within +-{bound_s * 1000:.0f} ms (the smaller of {MAX_CLOCK_OFFSET_S:g} s and "
              f"1/{1 / CLOCK_OFFSET_PASS_SHARE:.0f} of the sweep's shortest pass, {shortest_pass_s:.3g} s)")
    if not ok:
        detail = (f"the estimate {tau * 1000:+.1f} ms is beyond " + detail.split(", within ", 1)[1]
                  + ": a larger offset is not a latency between the laser's and the servo's stamps, and one near a "
                  "pass makes the sweep alias (the fit settles on a wrong offset that explains the data as well); "
                  "calibrate from --clock-offset 0, or with the offset the drivers' stamps are known to differ by")
    return Check("clock offset", ok, detail)


def split_in_two(scan: np.ndarray, passes: np.ndarray) -> tuple[list[np.ndarray], str]:
    """Two independent parts of a recording's returns (their scan indices (K,); passes (S,) of the sweep): the
    even and odd passes when the sweep goes both ways, else the two halves in time; and their name."""
    if passes.max() >= 1:
        scan_pass = passes[scan]
        return [scan_pass % 2 == 0, scan_pass % 2 == 1], "even and odd passes"
    mid = np.median(scan)
    return [scan <= mid, scan > mid], "the two halves of the sweep"


def chi2_check(chi2: float, config: CheckConfig, what: str, otherwise: str) -> Check:
    """The reduced chi-square check: ``what`` (the residuals' name) at most sqrt(config.max_reduced_chi2) times the
    stated range noise; the failure says what else (``otherwise``) could be wrong."""
    ok = bool(chi2 <= config.max_reduced_chi2)
    assert config.range_sigma_m is not None  # resolved by lrfcal.pipeline.calibrate
    return Check("reduced chi-square", ok,
                 f"{chi2:.3g} (limit {config.max_reduced_chi2:g}): {what} {math.sqrt(max(chi2, 0.0)):.2g} times the "
                 f"stated range noise {config.range_sigma_m * 1000:g} mm"
                 + ("" if ok else f"; if the scanner is this noisy, pass --range-sigma; otherwise {otherwise}"))


def servo_direction(by_sign: Mapping[int, Solution], nominal_dh: DH, config: CheckConfig) -> int:
    """The servo's direction (``by_sign``: the marker-only solution with each direction tried): the declared one
    (+1) unless the nominal DH contradicts it and fits the other.

    A negated motor angle together with a mirrored marker map and (alpha, b) -> (pi - alpha, -b) predicts exactly
    the same ranges (distances fix the marker map only up to a reflection), so only the nominal values can tell
    the two apart. When they contradict the declared direction, the calibration is refused with the rig-file
    setting that resolves it.
    """
    declared = by_sign.get(1)
    other = by_sign.get(-1)
    if declared is None:
        assert other is not None
        raise CalibrationError(
            "the markers match only with the servo angle negated: the servo turns the other way than declared; set "
            "servo.sign: -1 in the rig file (or --servo-sign -1) if it is mounted the other way round"
        )
    if other is None:
        return 1
    dh1, dh2 = declared.params.dh, other.params.dh
    if far_from_nominal(dh1, nominal_dh, config) and not far_from_nominal(dh2, nominal_dh, config):
        _, far_decl = nominal_distance(dh1, nominal_dh, config)
        raise CalibrationError(
            f"servo direction: with the declared sign (+1) the fit gives {dh_text(dh1)}, far from the nominal "
            f"{dh_text(nominal_dh)} ({far_decl}); with the servo angle negated it gives {dh_text(dh2)}, which "
            "explains the data equally well. If the servo turns the other way, set servo.sign: -1 in the rig file "
            "(or --servo-sign -1)"
        )
    return 1


#: chi-square quantile with 1 degree of freedom at p = 1e-3: a difference of cost below it does not tell two
#: minima apart
LR_LIMIT = 10.83


def judge_minima(lr: float) -> tuple[bool, str]:
    """The one rule for two distinct minima of a calibration's cost: ``lr`` (the other minimum's cost above the
    estimate's, in the estimate's whitened units, i.e. twice the log-likelihood ratio) must reach :data:`LR_LIMIT`
    for the estimate to stand (the other a local minimum); below it the two explain the data equally well, and below
    -LR_LIMIT the other explains them better. Whether it stands, and the verdict in words."""
    if lr >= LR_LIMIT:
        return True, f"by a likelihood ratio of {lr:.1f}, limit {LR_LIMIT}"
    what = ("they explain the data equally well" if lr > -LR_LIMIT
            else "the other explains the data better: the solve landed in a local minimum")
    return False, f"{what} (likelihood ratio {lr:+.1f}, limit {LR_LIMIT})"


#: a mirror image within this many of the estimate's 1-sigma of it, on every DH parameter, is the same rig to within
#: the estimate's uncertainty (a scan plane a hundredth of a degree from perpendicular to the motor axis and its mirror
#: image): either is right within a few of its sigma, never confidently wrong (4 sigma)
MIRROR_SAME_SIGMA = 2.0


def _nearest_mirror(dh: DH, nominal: DH, config: CheckConfig) -> tuple[str, DH, FloatArray, float, float]:
    """The mirror twin of ``dh`` (lrfcal.model.kinematics.dh_twins, improper Q) nearest the nominal DH: (name, twin
    DH, its isometry Q (3, 3) in M, the estimate's and the twin's distance from the nominal in nominal tolerances)."""
    d_est, _ = nominal_distance(dh, nominal, config)
    twins = [(name, twin, Q, nominal_distance(twin, nominal, config)[0]) for name, twin, Q in dh_twins(dh)
             if np.linalg.det(Q) < 0]
    name, twin, Q, d_twin = min(twins, key=lambda t: t[3])
    return name, twin, Q, d_est, d_twin


def nearer_mirror(dh: DH, nominal: DH, config: CheckConfig, dh_sigma: FloatArray
                  ) -> tuple[str, DH, FloatArray, float, float] | None:
    """The nearest mirror twin of ``dh`` (as :func:`_nearest_mirror`) when the nominal DH prefer it by the rule that
    decides between minima (lrfcal.estimate.minima.judge_minima: the nominal's prior, each distance d in nominal
    tolerances counting d^2, must favour the twin by LR_LIMIT) and the twin is not the same rig within ``dh_sigma``
    (4,), the estimate's 1-sigma; else None."""
    found = _nearest_mirror(dh, nominal, config)
    twin, d_est, d_twin = found[1], found[3], found[4]
    if _same_rig(twin, dh, dh_sigma) or not judge_minima(d_est**2 - d_twin**2)[0]:
        return None
    return found


def _same_rig(twin: DH, dh: DH, dh_sigma: FloatArray) -> bool:
    """Whether a twin, in either of its DH representatives (itself and its "turned" twin: one rig), lies within
    MIRROR_SAME_SIGMA of ``dh``'s 1-sigma ``dh_sigma`` (4,) on every DH parameter."""
    s = np.asarray(dh_sigma, dtype=float)
    scale = np.where(np.isfinite(s) & (s > 0), s, np.inf)
    return any(bool(np.all(np.abs(dh_difference(t.vector(), dh.vector())) / scale <= MIRROR_SAME_SIGMA))
               for t in (twin, dh_twins(twin)[0][1]))


#: nominal tolerances beyond which a nominal DH far from both the estimate and its mirror image (50 deg at the 5 deg
#: default) is named as the likely culprit of a mirror-image refusal (rather than the signs of alpha and b)
FAR_FROM_BOTH = 10.0


def mirror_check(dh: DH, nominal: DH, config: CheckConfig, dh_sigma: FloatArray) -> Check:
    """The rig or its mirror image: each mirror twin of the estimate (lrfcal.model.kinematics.dh_twins) explains the
    data exactly as well (with the marker map mirrored; flatness alike): tape distances fix the map only up to a
    reflection, and the servo's declared direction and the beams' order are the same in both. So only the nominal DH
    (a prior of the nominal tolerance, config.nominal_tolerance) can tell them apart, by the rule every choice between
    two minima is made by (lrfcal.estimate.minima.judge_minima: a distance d in nominal tolerances counts d^2). Passed
    when the nearest mirror twin is the same rig within the estimate's 1-sigma ``dh_sigma`` (4,), or the nominal
    favours the estimate by that rule; else refused naming both and what would tell them apart."""
    name, twin, _, d_est, d_twin = _nearest_mirror(dh, nominal, config)
    head = (f"the estimate is {d_est:.1f} nominal tolerances from the nominal DH, its nearest mirror image "
            f"({name}: {dh_text(twin)}) {d_twin:.1f}")
    if _same_rig(twin, dh, dh_sigma):
        return Check("mirror image", True, f"{head}; the two are one rig within the estimate's {MIRROR_SAME_SIGMA:g} "
                                           "sigma")
    ok, words = judge_minima(d_twin**2 - d_est**2)
    if ok:
        return Check("mirror image", True, f"{head}: the nominal favours the estimate ({words})")
    why = (": the data fit the rig and its mirror image exactly as well (tape distances fix the marker map only up "
           f"to a reflection; flatness likewise) and the nominal DH do not tell which ({words})")
    if min(d_est, d_twin) > FAR_FROM_BOTH:  # e.g. a nominal beta 90 deg off: the nominal can't judge
        why += (f"; the nominal DH are far from both: the rig file's dh is likely wrong (the estimate: {dh_text(dh)}): "
                "set it to whichever of the two the drawings confirm and calibrate again")
    elif abs(d_est - d_twin) < 1.0:
        why += ("; the nominal lies between the two (a scan plane near perpendicular to the motor axis, alpha near 0): "
                "give the nominal alpha and b with the signs the drawings show (a nominal alpha away from 0 tells the "
                "two apart), or tilt the scan plane further from perpendicular")
    else:
        why += "; check the signs of alpha and b in the rig file's dh against the drawings"
    return Check("mirror image", False, head + why)


def far_from_nominal(dh: DH, nominal: DH, config: CheckConfig) -> bool:
    """Whether a DH estimate is beyond the nominal tolerance (config.nominal_tolerance, :func:`nominal_distance`): a
    declared servo direction whose estimate is not far is kept whatever the other direction gives
    (:func:`servo_direction`)."""
    return nominal_distance(dh, nominal, config)[0] > 1.0


def nominal_distance(dh: DH, nominal: DH, config: CheckConfig) -> tuple[float, str]:
    """How far a DH estimate is from the nominal DH in nominal tolerances, and that in words. Compared as the
    scanner's poses in M' modulo the gauge (lrfcal.model.chart.gauge_distance): the larger of the origins' offset
    over the length tolerance (a's and b's, the larger) and the attitudes' angle over the angle tolerance (alpha's
    and beta's). DH differences themselves are singular near a scan plane perpendicular to the motor axis: a
    scanner tilted 0.04 deg towards the motor axis is b of 3.3 m in DH, and 2.6 mm from an untilted one here."""
    tol = config.nominal_tolerance
    dist, offset_m, angle_rad = gauge_distance(dh.vector(), nominal.vector(), max(tol[0], tol[2]),
                                               max(tol[1], tol[3]))
    return dist, f"the scanner {offset_m * 1000:.1f} mm and {math.degrees(angle_rad):.1f} deg from the nominal's pose"


def dh_text(dh: DH) -> str:
    return (f"a {dh.a * 1000:.1f} mm, alpha {math.degrees(dh.alpha):.2f} deg, b {dh.b * 1000:.1f} mm, "
            f"beta {math.degrees(dh.beta):.2f} deg")


def marker_checks(sol: Solution, marker_only: Solution, request: MarkerRequest, passes: np.ndarray,
                  config: CheckConfig, nominal: DH) -> list[Check]:
    """The consistency checks a result must pass before it is written (docs/method.md, stage 6c). The second opinion
    compares parts of the marker returns with the marker-only solution of them all (``request``: the marker-only
    problem it solved, its returns and marker map; the same model and data type, so that it tests the recording's
    parts, not the markers against the surfaces)."""
    checks = [Check("convergence", sol.converged, sol.status.split(";")[0]),
              mirror_check(sol.params.dh, nominal, config, sol.dh_sigma)]
    finite = bool(np.all(np.isfinite(sol.sigma)))
    if sol.information is not None and finite:
        obs = observability.analyse(sol.information, sol.information_names, sol.params.dh.alpha)
        checks.append(Check("observability", obs.determined,
                            f"{obs.summary()}" + ("" if obs.determined else f": {obs.hint()}")))
    else:  # a singular information (the solver's rank test): no covariance exists, so nothing is determined
        checks.append(Check("observability", False, f"the final solve is {sol.status.split(', ')[-1]}: the data do "
                            "not determine the parameters jointly (no finite covariance)"))
    checks.append(chi2_check(sol.reduced_chi2, config, "residuals", "the model does not explain the data (an "
                             "unmodelled clock offset or motion, a wrong marker radius)"))
    checks.append(_marker_second_opinion(marker_only, request, passes, config))
    return checks


def difference_covariance(part: Solution, joint: Solution, idx: list[int], map_cov: FloatArray | None
                          ) -> FloatArray:
    """The covariance (k, k) of part - joint over the unknowns ``idx`` (core order) of two solutions whose data
    overlap (the part's a subset of the joint's). Each parameter's sigma is the larger of:
    - the nested estimators' C_part - C_joint from their statistical covariances (before any widening: widened for
      errors the two share, the difference of the covariances would shrink, not grow);
    - the cluster-robust sum over clusters (a marker's crossing, a scan) of (i_part - i_joint)(...)^T, i each
      cluster's influence on each solution (lrfcal.estimate.covariance.Spread): errors shared within a crossing (where
      its
      lines fall on the marker) that the two solutions do not share.
    The marker map's error is shared: it moves the part and the joint solution by G dc each, the difference by
    (G_part - G_joint) dc, added. Without the spreads (rank loss): the reported covariances' difference."""
    Gp = Gj = np.zeros((len(idx), 0))  # without the map's sensitivities its terms are empty
    Cm = np.zeros((0, 0))
    if map_cov is not None and part.map_sensitivity is not None and joint.map_sensitivity is not None:
        Gp, Gj, Cm = part.map_sensitivity[idx], joint.map_sensitivity[idx], map_cov
    shared = (Gp - Gj) @ Cm @ (Gp - Gj).T
    sp, sj = part.spread, joint.spread
    if sp is None or sj is None or not (sp.ids.size and sj.ids.size):
        C = part.covariance[np.ix_(idx, idx)] - joint.covariance[np.ix_(idx, idx)]
        return C + Gj @ Cm @ Gj.T - Gp @ Cm @ Gp.T + shared
    ids = np.union1d(sp.ids, sj.ids)
    D = np.zeros((ids.size, len(idx)))
    D[np.searchsorted(ids, sp.ids)] += sp.influence[:, idx]
    D[np.searchsorted(ids, sj.ids)] -= sj.influence[:, idx]
    nested = sp.statistical[np.ix_(idx, idx)] - sj.statistical[np.ix_(idx, idx)]
    return widen(nested, D.T @ D) + shared


def _marker_second_opinion(sol: Solution, request: MarkerRequest, passes: np.ndarray, config: CheckConfig) -> Check:
    """Calibrate two independent parts of the data (odd and even passes of the sweep, or its two halves in time)
    and test that each agrees with the joint solution: chi2 = d^T (C_part - C_joint)^-1 d over the DH parameters
    (the part's data are a subset of the joint's; the marker map's shared error enters as (G_part - G_joint) C_map
    (G_part - G_joint)^T), against the chi-square quantile with 4 degrees of freedom. ``request``: the marker-only
    problem ``sol`` solved; each part is solved from ``sol``, its clock offset held."""
    from scipy.special import chdtri  # chi-square quantile: chdtri(k, 1 - q) = ppf(q) (scipy.stats is slow to import)

    matched = request.obs
    map_cov = request.markers.covariance if isinstance(request.markers, MarkerMap) else None
    groups, how = split_in_two(matched.scan, passes)
    dh = [PARAM_NAMES.index(n) for n in ("a", "alpha", "b", "beta")]
    limit = float(chdtri(4, 1.0 - (1.0 - config.second_opinion_p / 2.0)))
    results = []
    for g in groups:
        part = matched.subset(g)
        try:
            ps = solved(replace(request, obs=part, start=sol.params, clock=Clock(None, sol.clock_offset_s)))
        except CalibrationError:
            return Check("second opinion", True, f"not available: {how} alone have too few returns")
        if ps.information is None or not observability.analyse(ps.information, ps.information_names).determined:
            return Check("second opinion", True, f"not available: {how} alone do not determine the DH parameters")
        d = dh_difference(ps.params.vector()[dh], sol.params.vector()[dh])
        C = difference_covariance(ps, sol, dh, map_cov)
        if not (np.all(np.isfinite(C)) and np.all(np.isfinite(d))):
            return Check("second opinion", True, f"not available: {how} alone do not determine the DH parameters")
        w, V = np.linalg.eigh(0.5 * (C + C.T))
        floor = 0.05 * np.diag(ps.covariance[np.ix_(dh, dh)]).min()
        w = np.maximum(w, floor)  # the difference must not look more certain than 5 % of the part's own variance
        stat = float(d @ V @ np.diag(1.0 / w) @ V.T @ d)
        results.append((stat, d))
    worst = max(results, key=lambda r: r[0])
    ok = worst[0] <= limit
    d = worst[1]
    return Check(
        "second opinion", ok,
        f"{how} calibrated separately differ from the marker-only joint solution by chi2 {worst[0]:.3g} "
        f"(limit {limit:.3g}, 4 dof;"
        f" a {d[0] * 1000:+.2f} mm, alpha {math.degrees(d[1]):+.3f} deg, b {d[2] * 1000:+.2f} mm, "
        f"beta {math.degrees(d[3]):+.3f} deg)"
        + ("" if ok else ": the parts of the recording disagree (servo backlash or slip, an unmodelled clock "
                         "offset, markers that moved)"),
    )


def plane_checks(sol: Solution, returns: SurfaceReturns, passes: NDArray[np.int64], held: tuple[str, ...],
            config: CheckConfig, prior: tuple[FloatArray, FloatArray], nominal: DH) -> list[Check]:
    """Convergence, mirror image, the planes' agreement, observability of the estimated parameters, reduced
    chi-square and a second opinion."""
    checks = [Check("convergence", sol.converged, sol.status.split(";")[0]),
              mirror_check(sol.params.dh, nominal, config, sol.dh_sigma)]
    checks.append(planes_agree(sol, held, returns))
    est = [n for n in DH_NAMES if n not in held]
    s = {n: sol.sigma[6 + DH_NAMES.index(n)] for n in est}
    ok = not observability.beyond_limits(s)
    checks.append(Check("observability", ok, "1-sigma " + ", ".join(
        f"{n} {math.degrees(v):.3g} deg" if n in ("alpha", "beta") else f"{n} {v * 1000:.3g} mm"
        for n, v in s.items()) + (f"; held at nominal: {', '.join(held)}" if held else "")))
    checks.append(chi2_check(sol.reduced_chi2, config, "plane residuals", "the scene's surfaces are not flat "
                             "enough or the model does not explain the data (servo backlash, an unmodelled clock "
                             "offset)"))
    checks.append(_plane_second_opinion(sol, returns, passes, held, config, prior))
    return checks


#: "planes agree": a plane's pull on the estimate fails where its chi-square (over the estimated DH parameters,
#: against the difference's covariance by the noise, lrfcal.estimate.influence) has a tail probability below
#: PULL_P and it moves some estimated DH parameter by more than PULL_SIGMA of its stated sigma (a plane whose
#: pull is beyond the noise but within the sigma biases the estimate by less than its sigma)
PULL_P, PULL_SIGMA = 1e-6, 3.0
#: the least variance [stated sigma^2] a pull's chi-square divides by: where a plane adds nothing to a combination of
#: the DH parameters the pull along it is 0 but for the one Gauss-Newton step's own error, not noise to judge
PULL_FLOOR = 0.01


def planes_agree(sol: Solution, held: tuple[str, ...], returns: SurfaceReturns) -> Check:
    """The check "planes agree": no plane pulls the estimate beyond the noise and the stated sigma (:data:`PULL_P`,
    :data:`PULL_SIGMA`), judged for each plane without which the other planes alone (the design drawing's prior left
    out) determine the estimated DH parameters within lrfcal.estimate.observability's limits (without the others,
    the estimate without the plane is the prior's). The difference's covariance is the statistical one's
    (Solution.spread), scaled as the stated sigma is (the scans' correlated noise, the held parameters' tolerance)
    on each parameter; a range pattern in the cost is held at its estimate from every plane in each pull
    (lrfcal.estimate.influence). ``returns``: the plane returns solved (the failure names the plane by its normal and
    offset)."""
    from scipy.special import chdtri  # chi-square quantile (scipy.stats is slow to import)

    spread = sol.spread
    pulls = spread.planes if spread is not None else None
    est = [n for n in DH_NAMES if n not in held and pulls is not None and n in pulls.names]
    if spread is None or pulls is None or not est:
        return Check("planes agree", True, "not available: no plane returns, or no DH parameter estimated")
    at = [pulls.names.index(n) for n in est]
    stated = sol.dh_sigma[[DH_NAMES.index(n) for n in est]]
    scale = stated / np.sqrt(np.diag(spread.statistical)[[CORE_NAMES.index(n) for n in est]])
    limit = float(chdtri(len(est), PULL_P))
    judged = []  # (largest |shift| / sigma, chi-square, plane)
    for j in map(int, np.flatnonzero(pulls.returns)):
        if observability.beyond_limits(dict(zip(est, (pulls.others[j, at] * scale).tolist(), strict=True))):
            continue  # the others alone do not determine the DH: the estimate without the plane is the prior's
        pull = _pull(pulls.shift[j, at] / stated,
                     pulls.difference[j][np.ix_(at, at)] * np.outer(scale / stated, scale / stated))
        if pull is not None:
            judged.append((*pull, j))
    if not judged:
        return Check("planes agree", True, "not available: no plane without which the other planes determine the DH")
    bad = [x for x in judged if x[1] > limit and x[0] > PULL_SIGMA]
    if not bad:
        most, chi2, j = max(judged)
        return Check("planes agree", True, f"without any one of the {len(judged)} planes the estimate moves by at "
                                           f"most {most:.2g} sigma (plane {j}, chi-square {chi2:.3g} on {len(est)})")
    _, chi2, j = max(bad)
    moved = ", ".join(f"{n} {v:+.1f}" for n, v in zip(est, pulls.shift[j, at] / stated, strict=True)
                      if abs(v) > PULL_SIGMA)
    return Check("planes agree", False, (
        f"{len(bad)} of {len(judged)} planes judged pull{'s' if len(bad) == 1 else ''} the estimate beyond the noise; "
        f"without plane {j} ({_plane_words(returns, j)}{pulls.returns[j]} of the {int(pulls.returns.sum())} returns) "
        f"it moves by {moved} sigma (chi-square {chi2:.3g} on {len(est)}, limit {limit:.3g}): the scene's planes do "
        "not agree on the DH parameters; that plane is not one flat surface the rig model explains (two surfaces "
        "taken as one, a curved or moving one, the stand itself, a range error along the scan); calibrate in a "
        "scene of plain walls, or with markers"))


def _pull(z: FloatArray, C: FloatArray) -> tuple[float, float] | None:
    """A plane's pull ``z`` (k,) and its covariance by the noise ``C`` (k, k), both in units of the stated sigma:
    (its largest |z|, its chi-square with the variances floored at :data:`PULL_FLOOR`), None where not finite."""
    if not (np.all(np.isfinite(z)) and np.all(np.isfinite(C))):
        return None
    w, U = np.linalg.eigh(0.5 * (C + C.T))
    return float(np.max(np.abs(z))), float(np.sum((U.T @ z) ** 2 / np.maximum(w, PULL_FLOOR)))


def _plane_words(returns: SurfaceReturns, j: int) -> str:
    """Plane ``j`` of ``returns`` by its normal and offset, as the start of a parenthesis ("" without returns)."""
    rows = np.flatnonzero(returns.surface == j)
    if not rows.size:
        return ""
    n = returns.normals[rows[0]]
    return (f"normal ({n[0]:+.2f}, {n[1]:+.2f}, {n[2]:+.2f}), {returns.offsets_m[rows[0]]:.2f} m from the frame's "
            "origin, ")


def _plane_second_opinion(sol: Solution, returns: SurfaceReturns, passes: NDArray[np.int64], held: tuple[str, ...],
                    config: CheckConfig, prior: tuple[FloatArray, FloatArray]) -> Check:
    """Even and odd passes (or the sweep's two halves) calibrated separately and compared with each other:
    chi2 = d^T (C_1 + C_2)^-1 d over the estimated DH parameters (independent data), clock offset held at the
    joint estimate."""
    from scipy.special import chdtri  # chi-square quantile: chdtri(k, 1 - q) = ppf(q) (scipy.stats is slow to import)

    groups, how = split_in_two(returns.scan, passes)
    est = [6 + DH_NAMES.index(n) for n in DH_NAMES if n not in held]
    limit = float(chdtri(len(est), 1.0 - (1.0 - config.second_opinion_p)))
    parts = []
    sigma_r = config.range_sigma_m
    assert sigma_r is not None  # resolved by lrfcal.pipeline.calibrate
    for g in groups:
        try:
            kept = g if sol.inlier is None else g & sol.inlier  # the joint solve's outliers stay out
            parts.append(solved(PlaneRequest(returns.subset(kept), sol.params, range_sigma_m=sigma_r,
                                             clock_offset_s=sol.clock_offset_s, hold=held, dh_prior=prior,
                                             options=PlaneOptions(robust=False,
                                                                  range_pattern=config.range_pattern))))
        except CalibrationError:
            return Check("second opinion", True, f"not available: {how} alone have too few plane returns")
    d = parts[0].params.vector()[est] - parts[1].params.vector()[est]
    d = np.where(np.isin(est, (7, 9)), wrap_pi(d), d)
    C = parts[0].covariance[np.ix_(est, est)] + parts[1].covariance[np.ix_(est, est)]
    if not (np.all(np.isfinite(C)) and np.all(np.isfinite(d))):
        return Check("second opinion", True, f"not available: {how} alone do not determine the DH parameters")
    stat = float(d @ np.linalg.solve(C, d))
    ok = stat <= limit
    names = [CORE_NAMES[i] for i in est]
    diffs = ", ".join(f"{n} {math.degrees(v):+.3f} deg" if n in ("alpha", "beta") else f"{n} {v * 1000:+.2f} mm"
                      for n, v in zip(names, d, strict=True))
    return Check("second opinion", ok,
                 f"{how} calibrated separately differ by chi2 {stat:.3g} (limit {limit:.3g}, {len(est)} dof; {diffs})"
                 + ("" if ok else ": the parts of the recording disagree (servo backlash or slip, an unmodelled "
                                  "clock offset, a scene that moved)"))


__all__ = ["LR_LIMIT", "Check", "CheckConfig", "chi2_check", "clock_offset_check", "dh_text", "judge_minima",
           "marker_checks", "mirror_check", "nearer_mirror", "nominal_distance", "plane_checks", "refuse_failed",
           "servo_direction", "split_in_two"]

"""Stage 6: the one least-squares engine: Levenberg-Marquardt over the rig model's unknowns, used by the marker
calibration (:func:`solve`), the targetless one (:func:`solve_planes`), ``plan`` and ``study``.

The unknowns (lrfcal.model.unknowns, never Euler angles): the mount translation t, the mount rotation on SO(3) as a
reference R_ref and a small rotation vector w applied in frame M (R = R_ref Exp(w); after every solver pass w is
folded into R_ref and restarts at 0, so the parameterisation has no singularity at any attitude), the DH parameters,
the clock offset and the intrinsics; the observation models are lrfcal.model's (marker: ray-sphere with the beam's
footprint, or the seed paper's eq. (10); plane: ray-plane), assembled by lrfcal.estimate.problem.

Solver: a robust pass (Huber weights at 2 sigma) from the start, then plain least squares with observations whose
whitened residual exceeds 4 sigma dropped (repeated until the inlier set is stable), whose Jacobian gives the
covariance s^2 (J^T J)^-1, s^2 the reduced chi-square of the whitened residuals, widened where errors shared within
a scan or by the returns of one marker make it optimistic (cluster-robust sandwiches), plus the marker map's own
uncertainty carried through the solution (lrfcal.estimate.covariance). The markers the scan plane crosses on one side
only keep their range residuals (lrfcal.model.marker.two_sided, :func:`with_sides`). The plain passes, the
targetless solve and the information run on the normal equations with the planes' nuisances eliminated by the Schur
complement (lrfcal.estimate.normal_equations).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from functools import partial

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lrfcal.errors import CalibrationError
from lrfcal.estimate.covariance import held_score, uncertainty
from lrfcal.estimate.normal_equations import levenberg_marquardt
from lrfcal.estimate.problem import Problem, marker_problem, plane_problem, plane_set
from lrfcal.model.chart import regular_chart_at, regular_step
from lrfcal.model.kinematics import Params, exp_so3
from lrfcal.model.marker import crossing_ids, crossings, residuals_3d
from lrfcal.model.motor import MotorClock, motor_angles
from lrfcal.model.plane import plane_rows
from lrfcal.model.scanner import true_bearing, true_range
from lrfcal.model.unknowns import CORE_NAMES, INTRINSICS, MBIAS, N_CORE, ROFF, TAU, free_by_default, pack, unpack
from lrfcal.stages.surfaces import Surface, SurfaceReturns
from lrfcal.types import MarkerMap, Observations, Solution

FloatArray = NDArray[np.float64]


def _fit(th0: FloatArray, R_ref: FloatArray, pb: Problem, free: NDArray[np.bool_], robust: bool
         ) -> tuple[FloatArray, FloatArray, int, str]:
    """One solver pass over the free unknowns; returns (th with w folded into R_ref, R_ref, nfev, message).

    With the mount and every DH parameter free and no prior on them, the scan plane moves in the regular chart
    (lrfcal.model.chart), the gauge into the mount after every step: regular at every geometry, the scan plane
    perpendicular to the motor axis included. Otherwise in the DH parameters themselves."""
    # robust: Huber weights (threshold 2 sigma) against stray returns; plain: least squares, stopped at steps below
    # 1e-2 sigma (the clock offset's Jacobian, a smoothed joint velocity, makes the last iterations converge only
    # linearly, by factors of ~2 per evaluation of every marker and surface return)
    regular = pb.mount_jac and pb.dh_prior is None and bool(free[:10].all())
    th, nfev, ok = levenberg_marquardt(
        th0, lambda x, j: pb.blocks(x, R_ref, j, chart=regular_chart_at(x) if regular else None),
        np.flatnonzero(free[:N_CORE]), N_CORE, huber=2.0 if robust else None, max_iter=100, step_tol=1e-2,
        retract=regular_step(R_ref) if regular else None)
    msg = "converged" if ok else "maximum number of function evaluations exceeded"
    R_new = R_ref @ exp_so3(th[3:6])
    th[3:6] = 0.0
    return th, R_new, nfev, msg


def _per_return_chi(th: FloatArray, pb: Problem, R_ref: FloatArray) -> FloatArray:
    """Whitened residual norm per marker return over the square root of its independent components (MarkerSet.dof)."""
    res, _ = pb.marker_rows(th, R_ref, jac=False)
    return np.sqrt((res**2).sum(1) / pb.markers.dof())


def solve(
    obs: Observations,
    markers_W: ArrayLike | MarkerMap,
    start: Params,
    *,
    model: str,
    marker_radius_m: float,
    range_sigma_m: float = 0.010,
    robust: bool = True,
    surfaces: SurfaceReturns | None = None,
    planes: Sequence[Surface] | None = None,
    clock: MotorClock | None = None,
    clock_offset_s: float = 0.0,
    hold: Sequence[str] = (),
    estimate_range_bias: bool = False,
    beam_divergence_rad: float = 0.0,
    estimate: Sequence[str] = (),
    in_plane_at_turns: bool = False,
    held_scores: Sequence[str] = (),
) -> Solution:
    """Estimate the 10 parameters (and the clock offset, the intrinsics) from marker returns.

    Args:
        obs: K returns; rows with marker < 0 or non-finite values are ignored. obs.lambda_rad must be the motor
            angles at ``clock_offset_s``; obs.times_s the beam times (laser clock).
        markers_W: the marker map (lrfcal.stages.mds; its covariance, the tape's noise, joins the estimate's), or the
            marker centres (n, 3) in W taken as exact (the MDS frame, un-mirrored).
        start: initial parameters (mount pose from the association, DH from the nominal values).
        model: "paper" (eq. (10), return point vs marker centre) or "sphere" (ray vs sphere, sub-beam).
        marker_radius_m: marker sphere radius R_m.
        beam_divergence_rad: the scanner's full beam divergence: the sphere model averages over the footprint
            (lrfcal.model.sphere.footprint_depth); 0: the beam's axis alone.
        range_sigma_m: range noise sigma_r (UTM-30LX-EW repeatability, Hokuyo's specification).
        robust: Huber first pass and 4-sigma rejection before the final plain least-squares pass.
        surfaces: optional non-marker returns on the marker-carrying planes (lrfcal.stages.surfaces), solved jointly
            as ray-plane range residuals (whitened by range_sigma_m), rejected at 4 sigma like the markers.
        planes: the lrfcal.stages.surfaces.Surface of each surface index: each plane's normal and offset are nuisance
            parameters with the markers' prior (Surface.prior_sigma); without them the planes are free
            (only flatness counts), started from the returns' normals and offsets.
        clock: the joint states as a MotorClock: the clock offset is then estimated, started at
            ``clock_offset_s``; None holds it at ``clock_offset_s``.
        hold: names from CORE_NAMES held at their start value (not estimated; their sigma is NaN).
        estimate_range_bias: also estimate a constant range offset (every return) and a marker-return range bias
            (the returns of retroreflective markers only; "range walk" of strong returns), started at 0; only
            separable with surface returns (see lrfcal.stages.markers).
        estimate: names of unknowns the model holds by default (lrfcal.model.unknowns.UNKNOWNS) to estimate here.
        in_plane_at_turns: the model variant (lrfcal.model.marker.MarkerSet.in_plane_at_turns).
        held_scores: names of unknowns held by default whose score test to run where held (Solution.held_score).
    Returns:
        Solution: estimate, covariance (10, 10) in ESTIMATE_NAMES order (the rotation as a rotation vector in
        frame M; the marginal over plane nuisances and the clock offset; NaN rows for held parameters), the clock
        offset and its sigma, the marginal information over the estimated core unknowns, residuals_m (K, 3) for
        all K rows (NaN for unused rows), chi (K,) whitened residual per return, residual_rms_m over the returns
        kept, per_marker_rms_m (n,) (NaN for markers without returns).
    Raises:
        CalibrationError: fewer than 4 usable returns or fewer than 3 distinct markers.
    """
    if isinstance(markers_W, MarkerMap):
        X, map_cov = markers_W.positions_W, markers_W.covariance
    else:
        X, map_cov = np.asarray(markers_W, dtype=float), None
    pb_all, use = marker_problem(obs, X, model, marker_radius_m, range_sigma_m, beam_divergence_rad)
    K = pb_all.markers.r.size
    n_markers = len(np.unique(np.asarray(obs.marker)[use]))
    if K < 4 or n_markers < 3:
        raise CalibrationError(f"solve ({model}): need >= 4 returns on >= 3 markers, got {K} on {n_markers}")
    free_core = free_by_default(hold, estimate)
    free_core[TAU] &= clock is not None
    free_core[[ROFF, MBIAS]] &= estimate_range_bias
    th, R_ref = pack(start, clock_offset_s)
    pb_all = replace(pb_all, clock=clock, markers=replace(pb_all.markers, in_plane_at_turns=in_plane_at_turns))
    if surfaces is not None and len(surfaces):
        surf, nu0 = plane_set(surfaces, planes)
        pb_all = replace(pb_all, surf=surf)
        th = np.concatenate([th, nu0])
    free = np.concatenate([free_core, np.ones(th.size - N_CORE, dtype=bool)])
    th, R_ref, keep, keep_s, nfev, msg, pb_all = _marker_passes(th, R_ref, pb_all, free, robust)
    return _marker_solution(obs, use, len(X), pb_all, th, R_ref, free, keep, keep_s, nfev, msg, surfaces, map_cov,
                            held_scores)


def _marker_passes(th: FloatArray, R_ref: FloatArray, pb_all: Problem, free: NDArray[np.bool_], robust: bool
                   ) -> tuple[FloatArray, FloatArray, NDArray[np.bool_], NDArray[np.bool_], int, str, Problem]:
    """The solver passes of :func:`solve`: Huber-weighted (markers alone), then plain least squares with the returns
    beyond 4 robust sigma dropped until the kept set is stable, each on the lateral residuals of the markers crossed
    on both sides (:func:`with_sides`). Returns (th, R_ref, kept marker returns (K,), kept surface returns (K2,),
    evaluations, the last pass's message, the problem as last solved)."""
    K = pb_all.markers.r.size
    K2 = 0 if pb_all.surf is None else pb_all.surf.r.size
    nfev = 0
    keep = np.ones(K, dtype=bool)
    keep_s = np.ones(K2, dtype=bool)
    changed, msg = True, ""
    if robust:
        if pb_all.surf is None:  # the joint solve starts from the converged marker-only estimate: no robust pass
            th, R_ref, nf, _ = _fit(th, R_ref, pb_all, free, robust=True)
            nfev += nf
        for _ in range(5):
            pb_all = with_sides(pb_all, th, R_ref)
            chi = _per_return_chi(th, pb_all, R_ref)
            # robust scale of the whitened residuals (median of chi2_3 / 3 is 0.789), never below the model's
            scale = max(1.0, float(np.sqrt(np.median(chi[keep] ** 2) / 0.789)))
            new = chi <= 4.0 * scale
            new_s = keep_s
            if pb_all.surf is not None:
                rs = np.abs(plane_rows(th, pb_all.surf, pb_all.sigma_r, R_ref, jac=False, clock=pb_all.clock).res)
                new_s = rs <= 4.0 * max(1.0, float(np.median(rs[keep_s]) / 0.674))
            if new.sum() < 4:
                break
            changed = not (np.array_equal(new, keep) and np.array_equal(new_s, keep_s))
            keep, keep_s = new, new_s
            th, R_ref, nf, msg = _fit(th, R_ref, pb_all.subset(keep, keep_s), free, robust=False)
            nfev += nf
            if not changed:  # the last pass was on this very set: it is the solution
                break
    if not robust or changed:
        pb_all = with_sides(pb_all, th, R_ref)
        th, R_ref, nf, msg = _fit(th, R_ref, pb_all.subset(keep, keep_s), free, robust=False)
        nfev += nf
    return th, R_ref, keep, keep_s, nfev, msg, pb_all


def marker_clusters(scan: NDArray[np.int64], marker: NDArray[np.int64], times: FloatArray | None,
                    scan_s: NDArray[np.int64]) -> NDArray[np.int64]:
    """(K,) the cluster of each marker return (its ``scan``, ``marker`` and laser-clock ``times``, (K,) each) for the
    covariance's sandwich: its crossing (the marker's successive scan lines, lrfcal.model.marker.crossing_ids),
    numbered after the scans' ids (``scan`` and the surface returns' ``scan_s``: each scan's surface returns one
    cluster). A crossing's lines share where they fall on the marker, so they count as one sample, not one each;
    without the returns' times, each scan's returns are one cluster."""
    if times is None:
        return scan
    first = int(max(scan.max(initial=0), scan_s.max(initial=0))) + 1
    return first + crossing_ids(marker, times)


def with_sides(pb: Problem, th: FloatArray, R_ref: FloatArray) -> Problem:
    """``pb`` with the lateral residuals of the markers the scan plane crosses on one side only left out, and in
    the model variant ``in_plane_at_turns`` only their in-plane part in crossings that turn on their marker
    (lrfcal.model.marker.crossings, at th)."""
    turns = pb.markers.in_plane_at_turns
    lateral, across = crossings(th, pb.markers, R_ref, pb.clock, turns=turns)
    return replace(pb, markers=replace(pb.markers, lateral=lateral, across=across if turns else None))


def _marker_solution(obs: Observations, use: NDArray[np.bool_], n_markers: int, pb_all: Problem, th: FloatArray,
                     R_ref: FloatArray, free: NDArray[np.bool_], keep: NDArray[np.bool_], keep_s: NDArray[np.bool_],
                     nfev: int, msg: str, surfaces: SurfaceReturns | None, map_cov: FloatArray | None,
                     held_scores: Sequence[str]) -> Solution:
    """The Solution of :func:`solve` at the solution th: covariance, residuals per return and per marker, status."""
    ms = pb_all.markers
    K, K2 = ms.r.size, 0 if pb_all.surf is None else pb_all.surf.r.size
    pb = pb_all.subset(keep, keep_s)
    k_in, k_s = int(keep.sum()), int(keep_s.sum())
    n_prior = 0 if pb.surf is None or pb.surf.prior_sigma is None else pb.surf.prior_sigma.size
    scan_s = np.zeros(0, dtype=np.int64) if surfaces is None or pb.surf is None else np.asarray(surfaces.scan)[keep_s]
    # per marker return its independent residuals (MarkerSet.n_independent), 1 per surface return and prior row
    assert pb.markers.marker is not None  # marker_problem numbers every return's marker
    clusters = marker_clusters(np.asarray(obs.scan)[use][keep], pb.markers.marker, pb.markers.times, scan_s)
    unc = partial(uncertainty, pb, R_ref=R_ref, n_rows=pb.markers.n_independent + k_s + n_prior,
                  cluster_dense=np.repeat(clusters, ms.n_res), cluster_plane=scan_s, map_cov=map_cov,
                  marker_dense=np.repeat(pb.markers.marker, ms.n_res))
    cov_core, info, core_names, s2, rank_txt, G, spread = unc(th=th, free=free)
    params = unpack(th[:N_CORE], R_ref)
    score = held_score(pb, th, R_ref, free, s2, unc, held_scores)
    lam_all = motor_angles(th, np.asarray(obs.lambda_rad, dtype=float), np.asarray(obs.times_s, dtype=float),
                           pb_all.clock).lam
    res3 = np.full((len(obs), 3), np.nan)
    res3[use] = residuals_3d(params, true_range(th, ms.r, on_marker=True).r, lam_all[use], true_bearing(th, ms.mu).mu,
                             ms.c, model=ms.model, marker_radius_m=ms.radius)
    idx_used = np.nonzero(use)[0]
    inl = np.zeros(len(obs), dtype=bool)
    inl[idx_used[keep]] = True
    chi_all = np.full(len(obs), np.nan)
    chi_all[idx_used] = _per_return_chi(th, pb_all, R_ref)
    sq = (res3[inl] ** 2).sum(1)
    mk = np.asarray(obs.marker)[inl]
    per = np.full(n_markers, np.nan)
    for i in np.unique(mk):
        per[i] = float(np.sqrt(sq[mk == i].mean()))
    surf_txt = f", {k_s}/{K2} surface returns ({K2 - k_s} dropped)" if K2 else ""
    status = (f"{ms.model}: {msg.rstrip('.')}; {k_in}/{K} returns used ({K - k_in} dropped > 4 sigma){surf_txt}, "
              f"reduced chi2 {s2:.2f}, {rank_txt}")
    return _solution(th, R_ref, cov_core, free, params=params, residual_rms_m=float(np.sqrt(sq.mean())),
                     residuals_m=res3, per_marker_rms_m=per, n_observations=k_in, n_iterations=nfev, status=status,
                     information=info, information_names=core_names, reduced_chi2=s2,
                     converged="maximum number of function evaluations" not in msg, chi=chi_all, inlier=inl,
                     lambda_rad=lam_all, n_surface_returns=k_s, held_score=score,
                     map_sensitivity=None if G is None else G[:10], spread=spread)


def _solution(th: FloatArray, R_ref: FloatArray, cov_core: FloatArray, free: NDArray[np.bool_], **fields: object
              ) -> Solution:
    """A Solution from the unknowns th, their covariance (N_CORE, N_CORE) and which were free, with ``fields``."""
    cov10 = cov_core[:10, :10]

    def sig(i: int) -> float:
        return float(np.sqrt(cov_core[i, i])) if free[i] else float("nan")

    intrinsics = {n: (float(th[CORE_NAMES.index(n)]), sig(CORE_NAMES.index(n))) for n in INTRINSICS}
    fields.setdefault("params", unpack(th[:N_CORE], R_ref))
    return Solution(covariance=cov10, sigma=np.sqrt(np.clip(np.diag(cov10), 0.0, None)),
                    clock_offset_s=float(th[TAU]), clock_offset_sigma_s=sig(TAU),
                    intrinsics=intrinsics, **fields)  # type: ignore[arg-type]


#: the unknowns a targetless calibration never estimates: the world frame is the motor frame M (the planes are
#: free, so the mount is a gauge freedom), and there are no marker returns to carry a marker range bias
_TARGETLESS_HELD = ("x", "y", "z", "rx", "ry", "rz", "marker_range_bias")


def plane_free(n_par: int, hold: Sequence[str], clock: MotorClock | None, estimate_range_offset: bool
                ) -> NDArray[np.bool_]:
    """(n_par,) the unknowns :func:`solve_planes` estimates: the model's defaults without the targetless-held ones
    and ``hold``, the clock offset with a clock, the range offset when asked; every plane nuisance."""
    free = np.ones(n_par, dtype=bool)
    free[:N_CORE] = free_by_default((*_TARGETLESS_HELD, *hold))
    free[TAU] &= clock is not None
    free[ROFF] &= estimate_range_offset
    return free


def solve_planes(
    surfaces: SurfaceReturns,
    start: Params,
    *,
    range_sigma_m: float = 0.010,
    clock: MotorClock | None = None,
    clock_offset_s: float = 0.0,
    hold: Sequence[str] = (),
    estimate_range_offset: bool = False,
    robust: bool = True,
    dh_prior: tuple[FloatArray, FloatArray] | None = None,
    huber_first: bool = True,
) -> Solution:
    """Targetless: the DH parameters (and the clock offset, the range offset) from the flatness of planes alone.

    Every return is a ray-plane range residual (as the surface returns of :func:`solve`) on a plane whose normal and
    offset are free nuisance parameters. The mount is held at ``start.mount`` (without markers the world frame is
    arbitrary: the returns and planes are expressed in the frame of the start's mount, normally M itself).

    Args:
        surfaces: K returns with their plane index (``surface``), the planes' start normals and offsets in the
            start's frame, and beam times (``times_s``, needed with ``clock``).
        start: the start (the mount is held; the DH parameters start from it).
        range_sigma_m: range noise sigma_r.
        clock: the joint states as a MotorClock to estimate the clock offset (started at ``clock_offset_s``); None
            holds it.
        hold: names from CORE_NAMES held at their start value (in addition to the mount).
        estimate_range_offset: also estimate a constant range offset.
        robust: a Huber pass, then plain least squares with returns beyond 4 robust sigma dropped.
        huber_first: with ``robust``, the Huber pass (False: a start that a robust solve of nearly the same returns
            gave, which the 4-sigma rejection alone keeps from stray returns; the same solution to 1e-4 sigma on
            room_box, 15 % of its targetless time saved).
        dh_prior: (mean (4,), sigma (4,)) of a, alpha, b, beta: the design drawing's values and tolerance, as
            prior residuals (None: none).
    Returns:
        Solution as :func:`solve` (NaN sigma for held parameters; residuals_m, per_marker_rms_m and chi are empty;
        n_surface_returns the returns kept; inlier (K,) which of the K returns were kept; residual_rms_m the RMS of
        their range residuals).
    Raises:
        CalibrationError: fewer returns than 10 per unknown.
    """
    pb_all, nu0 = plane_problem(surfaces, range_sigma_m, clock, dh_prior)
    surf = pb_all.surf
    assert surf is not None
    th, R_ref = pack(start, clock_offset_s)
    th = np.concatenate([th, nu0])
    free = plane_free(th.size, hold, clock, estimate_range_offset)
    K = surf.r.size
    if 10 * int(free.sum()) > K:
        raise CalibrationError(f"targetless solve: {K} plane returns for {int(free.sum())} unknowns (need 10 each)")
    nfev = 0
    keep = np.ones(K, dtype=bool)
    none = np.zeros(0, dtype=bool)
    msg = "converged"
    if robust and huber_first:  # Huber first (a plane's stray returns: edges, clutter), then 4-sigma rejection
        th, nfev, msg = _gauss_newton(th, R_ref, pb_all, free, huber=2.0)
    plain = False
    for _ in range(6 if robust else 1):
        if robust:
            rs = np.abs(plane_rows(th, surf, pb_all.sigma_r, R_ref, jac=False, clock=clock).res)
            new = rs <= 4.0 * max(1.0, float(np.median(rs[keep]) / 0.674))
            if plain and np.array_equal(new, keep):
                break
            keep = new
        th, nf, msg = _gauss_newton(th, R_ref, pb_all.subset(none, keep), free)
        nfev += nf
        plain = True
    pb = pb_all.subset(none, keep)
    assert pb.surf is not None
    n_prior = 0 if dh_prior is None else 4
    cov_core, info, core_names, s2, rank_txt, *_ = uncertainty(
        pb, th, R_ref, free, int(keep.sum()) + n_prior,
        -1 - np.arange(n_prior), np.asarray(surfaces.scan)[keep])
    rs = plane_rows(th, pb.surf, 1.0, R_ref, jac=False, clock=clock).res
    status = (f"planes: {msg.rstrip('.')}; {int(keep.sum())}/{K} plane returns on {surf.n_planes} planes used "
              f"({int(K - keep.sum())} dropped > 4 sigma), reduced chi2 {s2:.2f}, {rank_txt}")
    return _solution(th, R_ref, cov_core, free, residual_rms_m=float(np.sqrt(np.mean(rs**2))),
                     residuals_m=np.zeros((0, 3)), per_marker_rms_m=np.zeros(0), n_observations=0,
                     n_iterations=nfev, status=status, information=info, information_names=core_names,
                     reduced_chi2=s2, converged=msg == "converged", chi=np.zeros(0), inlier=keep, lambda_rad=None,
                     n_surface_returns=int(keep.sum()))


def _gauss_newton(th0: FloatArray, R_ref: FloatArray, pb: Problem, free: NDArray[np.bool_],
                  huber: float | None = None, max_iter: int = 60) -> tuple[FloatArray, int, str]:
    """Levenberg-Marquardt on the normal equations (lrfcal.estimate.normal_equations: the planes eliminated by the Schur
    complement) over the free unknowns, with Huber weights of threshold ``huber`` (None: plain least squares). The
    mount must be held (R_ref is not updated). Stops when every step is below 1e-3 of its parameter's sigma.
    Returns (th, evaluations, "converged" or why not)."""
    th, n_eval, ok = levenberg_marquardt(th0, lambda x, j: pb.blocks(x, R_ref, j), np.flatnonzero(free[:N_CORE]),
                                         N_CORE, huber=huber, max_iter=max_iter)
    return th, n_eval, "converged" if ok else f"not converged in {max_iter} iterations"


__all__ = ["CORE_NAMES", "MotorClock", "solve", "solve_planes"]

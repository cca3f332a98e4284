"""What to estimate, as data: a request the engine solves (lrfcal.estimate.engine.solved), built by the stages and
solved by the orchestrator (lrfcal.pipeline) or, for the checks that solve again, by lrfcal.estimate itself.

:class:`MarkerRequest` is the marker calibration's (marker returns, optionally with surface returns on their planes),
:class:`PlaneRequest` the targetless one's (plane returns alone). Each says how it is posed to the engine (its
observation sets, start and unknowns, which are held and why, its passes: lrfcal.estimate.engine.MARKER_PASSES,
PLANE_PASSES) and how the engine's estimate is reported as a Solution; neither runs the engine.

The unknowns (lrfcal.model.unknowns, never Euler angles): the mount translation t, the mount rotation on SO(3) as a
reference R_ref and a small rotation vector w applied in frame M (R = R_ref Exp(w); after every solver pass w is
folded into R_ref and restarts at 0, so the parameterisation has no singularity at any attitude), the DH parameters,
the clock offset and the intrinsics; the observation sets are lrfcal.model's (marker: ray-sphere with the beam's
footprint, or the seed paper's eq. (10), lrfcal.model.marker.MarkerSet; plane: ray-plane, lrfcal.model.plane.
PlaneSet), assembled by lrfcal.estimate.problem.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from lrfcal.errors import CalibrationError, RunOffError
from lrfcal.estimate.engine import MARKER_PASSES, PLANE_PASSES, Estimate, Passes, State, Status, Unknowns
from lrfcal.estimate.problem import OnPlanes, Problem, marker_set, plane_problem, plane_set
from lrfcal.model.kinematics import Params
from lrfcal.model.marker import MarkerModel, MarkerSensor, residuals_3d
from lrfcal.model.motor import NO_CLOCK, Clock, MotorClock, motor_angles
from lrfcal.model.plane import Footing, plane_rows
from lrfcal.model.scanner import true_bearing, true_range
from lrfcal.model.unknowns import CORE_NAMES, INTRINSICS, MBIAS, N_CORE, ROFF, TAU, free_by_default, pack, unpack
from lrfcal.types import MarkerMap, Observations, Solution, SurfaceReturns

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

#: why the unknowns a solve holds are held, beyond the model's defaults (lrfcal.model.unknowns.UNKNOWNS)
_WHY = {"clock_offset": "no joint states to judge it by (no clock)",
        "range_offset": "not asked for (only separable with surface returns)",
        "marker_range_bias": "not asked for (only separable with surface returns)"}


@dataclass(frozen=True)
class SolveOptions:
    """What a marker solve holds and estimates beyond the model's defaults (lrfcal.model.unknowns.UNKNOWNS), and
    how it solves.

    hold: names from CORE_NAMES held at their start value (not estimated; their sigma is NaN).
    estimate: names of unknowns the model holds by default to estimate here.
    estimate_range_bias: also estimate a constant range offset (every return) and a marker-return range bias (the
        returns of retroreflective markers only; "range walk" of strong returns), started at 0; only separable with
        surface returns (see lrfcal.stages.markers).
    held_scores: names of unknowns held by default whose score test to run where held (Solution.held_score).
    robust: Huber first pass and 4-sigma rejection before the final plain least-squares pass.
    in_plane_at_turns: the marker model's variant (lrfcal.model.marker.MarkerSet.in_plane_at_turns).
    """

    hold: Sequence[str] = ()
    estimate: Sequence[str] = ()
    estimate_range_bias: bool = False
    held_scores: Sequence[str] = ()
    robust: bool = True
    in_plane_at_turns: bool = False


#: the model's defaults, robust passes
DEFAULT_OPTIONS = SolveOptions()


@dataclass(frozen=True)
class MarkerRequest:
    """Estimate the 10 parameters (and the clock offset, the intrinsics) from marker returns.

    obs: K returns; rows with marker < 0 or non-finite values are ignored. obs.lambda_rad must be the motor angles
        at ``clock.offset_s``; obs.times_s the beam times (laser clock).
    markers: the marker map (lrfcal.stages.mds; its covariance, the tape's noise, joins the estimate's), or the
        marker centres (n, 3) in W taken as exact (the MDS frame, un-mirrored).
    start: initial parameters (mount pose from the association, DH from the nominal values).
    sensor: the marker observation model's constants (its variant: "paper", eq. (10), return point vs marker centre,
        or "sphere", ray vs sphere, sub-beam, averaged over the beam's footprint: lrfcal.model.sphere.footprint_depth;
        the marker radius; the range noise sigma_r, which whitens the surface returns too).
    surfaces: optional non-marker returns on the marker-carrying planes (lrfcal.stages.surfaces), solved jointly as
        ray-plane range residuals, rejected at 4 sigma like the markers; with their planes, each plane's normal and
        offset are nuisance parameters with the markers' prior (Surface.prior_sigma); without them the planes are
        free (only flatness counts), started from the returns' normals and offsets.
    clock: the clock offset's start (or held value) and the joint states as a MotorClock (``clock.motor``): the clock
        offset is then estimated; None holds it.
    options: what is held and estimated, the robust passes, the model variant (:class:`SolveOptions`).

    Its Solution: estimate, covariance (10, 10) in ESTIMATE_NAMES order (the rotation as a rotation vector in frame
    M; the marginal over plane nuisances and the clock offset; NaN rows for held parameters), the clock offset and
    its sigma, the marginal information over the estimated core unknowns, residuals_m (K, 3) for all K rows (NaN for
    unused rows), chi (K,) whitened residual per return, residual_rms_m over the returns kept, per_marker_rms_m (n,)
    (NaN for markers without returns). Posing it raises CalibrationError: fewer than 4 usable returns or fewer than
    3 distinct markers.
    """

    obs: Observations
    markers: MarkerMap | FloatArray
    start: Params
    sensor: MarkerSensor
    surfaces: OnPlanes | None = None
    clock: Clock = NO_CLOCK
    options: SolveOptions = DEFAULT_OPTIONS

    def paper(self) -> MarkerRequest:
        """The same request with the seed paper's marker model (eq. (10)): a return's point, which knows no surface
        and so no incidence (the incidence bias held, lrfcal.model.scanner)."""
        options = replace(self.options, estimate=tuple(n for n in self.options.estimate if n != "incidence_bias"))
        return replace(self, sensor=replace(self.sensor, model=MarkerModel.PAPER), options=options)

    def posed(self) -> _MarkerPosed:
        """The request as the engine takes it (lrfcal.estimate.engine.Posed)."""
        obs, sensor, opt, clock, surfaces = self.obs, self.sensor, self.options, self.clock, self.surfaces
        if isinstance(self.markers, MarkerMap):
            X, map_cov = self.markers.positions_W, self.markers.covariance
        else:
            X, map_cov = np.asarray(self.markers, dtype=float), None
        ms, use = marker_set(obs, X, sensor)
        n_markers = len(np.unique(np.asarray(obs.marker)[use]))
        if ms.size < 4 or n_markers < 3:
            raise CalibrationError(f"solve ({sensor.model.value}): need >= 4 returns on >= 3 markers, got {ms.size} "
                                   f"on {n_markers}")
        free_core = free_by_default(opt.hold, opt.estimate)
        free_core[TAU] &= clock.motor is not None
        free_core[[ROFF, MBIAS]] &= opt.estimate_range_bias
        th, R_ref = pack(self.start, clock.offset_s)
        pb = Problem((replace(ms, in_plane_at_turns=opt.in_plane_at_turns),), sensor.range_sigma_m, clock=clock.motor)
        with_surfaces = surfaces is not None and len(surfaces) > 0
        if surfaces is not None and with_surfaces:
            surf, nu0 = plane_set(surfaces.returns, surfaces.planes)
            pb = pb.with_sets([*pb.sets, surf])
            th = np.concatenate([th, nu0])
        unknowns = Unknowns.of(free_core, th.size - N_CORE, {**_WHY, **{n: "held by the call" for n in opt.hold}})
        # the joint solve (with surface returns) starts from the converged marker-only estimate: no Huber pass
        passes = replace(MARKER_PASSES, robust=opt.robust, huber_first=not with_surfaces)
        return _MarkerPosed(pb, State(th, R_ref), unknowns, passes, map_cov, tuple(opt.held_scores), obs, use, len(X))


@dataclass(frozen=True)
class _Posed:
    """A request as the engine takes it (lrfcal.estimate.engine.Posed, but for the report of its estimate)."""

    problem: Problem
    start: State
    unknowns: Unknowns
    passes: Passes
    map_cov: FloatArray | None
    held_scores: tuple[str, ...]


@dataclass(frozen=True)
class _MarkerPosed(_Posed):
    """A :class:`MarkerRequest` as the engine takes it, with what its Solution reports from: the returns, which of
    them the marker set uses, the number of markers."""

    obs: Observations
    use: BoolArray
    n_markers: int

    def solution(self, est: Estimate) -> Solution:
        """The Solution of the estimate: covariance, residuals per return and per marker, status."""
        obs, use, free = self.obs, self.use, self.unknowns.free
        th, R_ref = est.state.th, est.state.R_ref
        ms = est.problem.markers
        assert ms is not None
        keep = est.keep[0]
        K, k_in = ms.size, int(keep.sum())
        K2 = est.keep[1].size if len(est.keep) > 1 else 0
        k_s = int(est.keep[1].sum()) if K2 else 0
        unc = est.uncertainty
        params = unpack(th[:N_CORE], R_ref)
        lam_all = motor_angles(th, np.asarray(obs.lambda_rad, dtype=float), np.asarray(obs.times_s, dtype=float),
                               est.problem.clock).lam
        res3 = np.full((len(obs), 3), np.nan)
        res3[use] = residuals_3d(params, true_range(th, ms.r, on_marker=True).r, lam_all[use],
                                 true_bearing(th, ms.mu).mu, ms.c, model=ms.model, marker_radius_m=ms.radius)
        idx_used = np.nonzero(use)[0]
        inl = np.zeros(len(obs), dtype=bool)
        inl[idx_used[keep]] = True
        chi_all = np.full(len(obs), np.nan)
        chi_all[idx_used] = ms.chi(th, R_ref, est.problem.context())
        sq = (res3[inl] ** 2).sum(1)
        mk = np.asarray(obs.marker)[inl]
        per = np.full(self.n_markers, np.nan)
        for i in np.unique(mk):
            per[i] = float(np.sqrt(sq[mk == i].mean()))
        surf_txt = f", {k_s}/{K2} surface returns ({K2 - k_s} dropped)" if K2 else ""
        msg = "converged" if est.status is Status.CONVERGED else "maximum number of function evaluations exceeded"
        status = (f"{ms.model.value}: {msg}; {k_in}/{K} returns used ({K - k_in} dropped > 4 sigma){surf_txt}, "
                  f"reduced chi2 {unc.reduced_chi2:.2f}, {unc.rank}")
        G = unc.map_sensitivity
        return _solution(th, R_ref, unc.covariance, free, params=params, residual_rms_m=float(np.sqrt(sq.mean())),
                         residuals_m=res3, per_marker_rms_m=per, n_observations=k_in, n_iterations=est.n_evaluations,
                         status=status, information=unc.information, information_names=unc.names,
                         reduced_chi2=unc.reduced_chi2, converged=est.status is Status.CONVERGED, chi=chi_all,
                         inlier=inl, lambda_rad=lam_all, n_surface_returns=k_s, held_score=dict(unc.held_score),
                         map_sensitivity=None if G is None else G[:10], spread=unc.spread, iterations=est.log,
                         range_correlation=unc.range_correlation)


def _solution(th: FloatArray, R_ref: FloatArray, cov_core: FloatArray, free: BoolArray, **fields: object
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
_TARGETLESS_WHY = "targetless: the world frame is the motor frame M (the mount a gauge freedom), no marker returns"


def plane_free(n_par: int, hold: Sequence[str], clock: MotorClock | None, estimate_range_offset: bool
               ) -> BoolArray:
    """(n_par,) the unknowns a :class:`PlaneRequest` estimates: the model's defaults without the targetless-held
    ones and ``hold``, the clock offset with a clock, the range offset when asked; every plane nuisance."""
    free = np.ones(n_par, dtype=bool)
    free[:N_CORE] = free_by_default((*_TARGETLESS_HELD, *hold))
    free[TAU] &= clock is not None
    free[ROFF] &= estimate_range_offset
    return free


@dataclass(frozen=True)
class PlaneOptions:
    """What a targetless solve estimates beyond its defaults, and how it solves.

    estimate_range_offset: also estimate a constant range offset.
    robust: a Huber pass, then plain least squares with returns beyond 4 robust sigma dropped.
    huber_first: with ``robust``, the Huber pass (False: a start that a robust solve of nearly the same returns gave,
        which the 4-sigma rejection alone keeps from stray returns; the same solution to 1e-4 sigma on room_box,
        15 % of its targetless time saved).
    footing: where a return counts, judged with the 4-sigma rejection at every estimate (lrfcal.model.plane.Footing:
        the targetless cost's incidence and edge rule; None: every return may).
    range_pattern: the scanner's range error along the scan a nuisance of the cost (lrfcal.model.range_pattern).
    """

    estimate_range_offset: bool = False
    robust: bool = True
    huber_first: bool = True
    footing: Footing | None = None
    range_pattern: bool = False


#: the targetless defaults: robust, a Huber pass first
DEFAULT_PLANE_OPTIONS = PlaneOptions()


@dataclass(frozen=True)
class PlaneRequest:
    """Targetless: the DH parameters (and the clock offset, the range offset) from the flatness of planes alone.

    Every return is a ray-plane range residual (as the surface returns of a :class:`MarkerRequest`) on a plane whose
    normal and offset are free nuisance parameters. The mount is held at ``start.mount`` (without markers the world
    frame is arbitrary: the returns and planes are expressed in the frame of the start's mount, normally M itself).

    surfaces: K returns with their plane index (``surface``), the planes' start normals and offsets in the start's
        frame, and beam times (``times_s``, needed with ``clock``).
    start: the start (the mount is held; the DH parameters start from it).
    range_sigma_m: range noise sigma_r.
    clock: the joint states as a MotorClock to estimate the clock offset (started at ``clock_offset_s``); None holds
        it.
    hold: names from CORE_NAMES held at their start value (in addition to the mount).
    dh_prior: (mean (4,), sigma (4,)) of a, alpha, b, beta: the design drawing's values and tolerance, as prior
        residuals (None: none).
    options: the range offset estimated or not, the robust passes (:class:`PlaneOptions`).

    Its Solution as a MarkerRequest's (NaN sigma for held parameters; residuals_m, per_marker_rms_m and chi are
    empty; n_surface_returns the returns kept; inlier (K,) which of the K returns were kept; residual_rms_m the RMS of
    their range residuals). Posing it raises CalibrationError: fewer returns than 10 per unknown.
    """

    surfaces: SurfaceReturns
    start: Params
    range_sigma_m: float = 0.010
    clock: MotorClock | None = None
    clock_offset_s: float = 0.0
    hold: tuple[str, ...] = ()
    dh_prior: tuple[FloatArray, FloatArray] | None = None
    options: PlaneOptions = DEFAULT_PLANE_OPTIONS

    def posed(self) -> _PlanePosed:
        """The request as the engine takes it (lrfcal.estimate.engine.Posed)."""
        surfaces, clock, hold, options = self.surfaces, self.clock, self.hold, self.options
        pb, nu0 = plane_problem(surfaces, self.range_sigma_m, clock, self.dh_prior, options.footing,
                                options.range_pattern)
        th, R_ref = pack(self.start, self.clock_offset_s)
        th = np.concatenate([th, nu0])
        free = plane_free(th.size, hold, clock, options.estimate_range_offset)
        K = surfaces.ranges_m.size
        if 10 * int(free.sum()) > K:
            raise CalibrationError(f"targetless solve: {K} plane returns for {int(free.sum())} unknowns (need 10 each)")
        why = {**_WHY, **{n: _TARGETLESS_WHY for n in _TARGETLESS_HELD}, **{n: "held by the call" for n in hold}}
        unknowns = Unknowns.of(free[:N_CORE], th.size - N_CORE, why)
        passes = replace(PLANE_PASSES, robust=options.robust, huber_first=options.huber_first)
        return _PlanePosed(pb, State(th, R_ref), unknowns, passes, None, (), K, clock)


@dataclass(frozen=True)
class _PlanePosed(_Posed):
    """A :class:`PlaneRequest` as the engine takes it, with what its Solution reports from: the number of returns
    and the clock."""

    n_returns: int
    clock: MotorClock | None

    def solution(self, est: Estimate) -> Solution:
        """The Solution of the estimate: covariance, the kept returns and their residuals' RMS, status."""
        K, free = self.n_returns, self.unknowns.free
        keep = est.keep[-1]
        if 10 * int(free.sum()) > int(keep.sum()):  # the returns that count at the estimate: too few to judge by
            raise RunOffError(f"targetless solve: {int(keep.sum())} of {K} plane returns count at the estimate "
                              f"(their plane's 4 sigma, incidence and edges) for {int(free.sum())} unknowns (need "
                              "10 each)", int(keep.sum()), K)
        surf = est.kept.surf
        assert surf is not None
        th, unc = est.state.th, est.uncertainty
        rs = plane_rows(th, surf, 1.0, est.state.R_ref, jac=False, clock=self.clock).res
        msg = "converged" if est.status is Status.CONVERGED else f"not converged in {PLANE_PASSES.max_iter} iterations"
        status = (f"planes: {msg}; {int(keep.sum())}/{K} plane returns on {surf.n_planes} planes used "
                  f"({int(K - keep.sum())} dropped > 4 sigma), reduced chi2 {unc.reduced_chi2:.2f}, {unc.rank}")
        return _solution(th, est.state.R_ref, unc.covariance, free, residual_rms_m=float(np.sqrt(np.mean(rs**2))),
                         residuals_m=np.zeros((0, 3)), per_marker_rms_m=np.zeros(0), n_observations=0,
                         n_iterations=est.n_evaluations, status=status, information=unc.information,
                         information_names=unc.names, reduced_chi2=unc.reduced_chi2,
                         converged=est.status is Status.CONVERGED, chi=np.zeros(0), inlier=keep, lambda_rad=None,
                         n_surface_returns=int(keep.sum()), spread=unc.spread, iterations=est.log)


#: what the engine solves: a marker calibration's request or a targetless one's
Request = MarkerRequest | PlaneRequest

__all__ = ["DEFAULT_OPTIONS", "DEFAULT_PLANE_OPTIONS", "MarkerRequest", "OnPlanes", "PlaneOptions", "PlaneRequest",
           "Request", "SolveOptions", "plane_free"]

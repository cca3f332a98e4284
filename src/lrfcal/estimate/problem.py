"""The data of one least-squares problem and its whitened residuals: a tuple of observation sets
(lrfcal.model.observations.ObservationSet: marker returns, lrfcal.model.marker.MarkerSet; surface returns on planes
whose normals and offsets are nuisances, lrfcal.model.plane.PlaneSet, with the planes' priors; the design drawing's
prior on the DH parameters, lrfcal.model.observations.DHPrior), with the range noise and the motor clock, as the
blocks the solver's normal equations take (lrfcal.estimate.normal_equations). Markers, surfaces, targetless, plan
and study build one of these; one estimate (lrfcal.estimate.engine) solves it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lrfcal.errors import InputError
from lrfcal.model.marker import MarkerSensor, MarkerSet, centre_jacobian, marker_rows
from lrfcal.model.motor import MotorClock
from lrfcal.model.observations import Blocks, DHPrior, ObservationSet, RowContext, stack_blocks
from lrfcal.model.plane import Footing, PlaneSet
from lrfcal.model.range_pattern import beam_bins
from lrfcal.model.unknowns import N_CORE, plane_nuisance_start
from lrfcal.types import Observations, Surface, SurfaceReturns

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
IntArray = NDArray[np.int64]


@dataclass(frozen=True)
class Problem:
    """Observation sets (their nuisances follow the core unknowns in the sets' order), the range noise, optional
    clock (the clock offset estimated), and whether the mount's Jacobian is needed."""

    sets: tuple[ObservationSet, ...]
    sigma_r: float
    clock: MotorClock | None = None  # set when the clock offset is estimated
    mount_jac: bool = True  # False: the mount is held, its Jacobian columns are not computed (left 0)
    #: False: the incidence bias is held and never score-tested (the targetless problem), its column left 0: the
    #: incidence of every plane return (an arccos per row) is not computed for it
    incidence_jac: bool = True

    def _first(self, kind: type) -> ObservationSet | None:
        return next((s for s in self.sets if isinstance(s, kind)), None)

    @property
    def markers(self) -> MarkerSet | None:
        """The marker returns (the first MarkerSet), if any."""
        m = self._first(MarkerSet)
        return m if isinstance(m, MarkerSet) else None

    @property
    def surf(self) -> PlaneSet | None:
        """The plane returns (the first PlaneSet), if any."""
        s = self._first(PlaneSet)
        return s if isinstance(s, PlaneSet) else None

    @property
    def dh_prior(self) -> DHPrior | None:
        """The design drawing's prior on the DH parameters, if any."""
        d = self._first(DHPrior)
        return d if isinstance(d, DHPrior) else None

    def context(self, chart: FloatArray | None = None) -> RowContext:
        """How the sets' rows are evaluated (``chart``: lrfcal.model.chart, None for the DH parameters)."""
        return RowContext(self.sigma_r, self.clock, self.mount_jac, chart, self.incidence_jac)

    def with_sets(self, sets: Sequence[ObservationSet]) -> Problem:
        """The same problem of other sets (as many, with as many nuisances each)."""
        return replace(self, sets=tuple(sets))

    @property
    def has_pattern(self) -> bool:
        """Whether a plane set has the range pattern along the scan as a nuisance (lrfcal.model.range_pattern)."""
        return any(isinstance(s, PlaneSet) and s.pattern_bins is not None for s in self.sets)

    def without_pattern(self) -> Problem:
        """The same problem with the plane sets' range pattern along the scan held at 0 (lrfcal.model.range_pattern)."""
        if not self.has_pattern:
            return self
        return self.with_sets([replace(s, pattern_bins=None) if isinstance(s, PlaneSet) else s for s in self.sets])

    def subset(self, keeps: Sequence[BoolArray]) -> Problem:
        """Each set's returns ``keeps[i]``."""
        return self.with_sets([s.subset(k) for s, k in zip(self.sets, keeps, strict=True)])

    def chosen_at(self, th: FloatArray, R_ref: FloatArray) -> Problem:
        """Every set chosen again at th (ObservationSet.chosen_at: the markers crossed on both sides)."""
        ctx = self.context()
        return self.with_sets([s.chosen_at(self.own(th, i), R_ref, ctx) for i, s in enumerate(self.sets)])

    def kept(self, th: FloatArray, R_ref: FloatArray, keeps: Sequence[BoolArray]) -> tuple[BoolArray, ...]:
        """Each set's returns its robust rule keeps at th (ObservationSet.kept), the scale from ``keeps``."""
        ctx = self.context()
        return tuple(s.kept(self.own(th, i), R_ref, ctx, k) for i, (s, k) in enumerate(zip(self.sets, keeps,
                                                                                             strict=True)))

    def clusters(self) -> tuple[IntArray, IntArray, IntArray | None]:
        """The cluster of each dense row and of each plane row (each set's, ObservationSet.clusters; the ids a set
        makes up start above every set's scans), and each dense row's group (ObservationSet.groups; rows of a set
        without groups one group each; None when no set has groups): the covariance's sandwiches."""
        scans = [s.scan for s in self.sets if s.scan is not None]
        first = max((int(sc.max(initial=0)) for sc in scans), default=0) + 1
        dense, plane, groups = [], [], []
        for s in self.sets:
            d, p = s.clusters(first)
            dense.append(d)
            plane.append(p)
            groups.append(s.groups())
        marker_dense = None
        if any(g is not None for g in groups):
            marker_dense = np.concatenate([g if g is not None else -1 - np.arange(d.size)
                                           for g, d in zip(groups, dense, strict=True)]).astype(np.int64)
        return (np.concatenate(dense).astype(np.int64), np.concatenate(plane).astype(np.int64), marker_dense)

    def own(self, th: FloatArray, i: int) -> FloatArray:
        """The core unknowns and set i's own nuisances of th (N_CORE + its n_nuisance,)."""
        start = N_CORE + sum(s.n_nuisance for s in self.sets[:i])
        n = self.sets[i].n_nuisance
        if start == N_CORE and start + n == th.size:
            return th
        return np.concatenate([th[:N_CORE], th[start:start + n]])

    def marker_rows(self, th: FloatArray, R_ref: FloatArray, jac: bool = True, chart: FloatArray | None = None
                    ) -> tuple[FloatArray, FloatArray | None]:
        """Whitened marker residuals (K, n_res) and Jacobian (K, n_res, N_CORE) (lrfcal.model.marker; ``chart``:
        lrfcal.model.chart, None for the DH parameters)."""
        assert self.markers is not None, "a problem without marker returns"
        return marker_rows(th, self.markers, self.sigma_r, R_ref, jac=jac, clock=self.clock, mount_jac=self.mount_jac,
                           chart=chart)

    def markers_in(self, dense: FloatArray) -> FloatArray:
        """The marker returns' part of :meth:`blocks`' dense rows ``dense`` (m,) or (m, p): (K, n_res) or (K, n_res, p)
        (the marker set is the first set: its rows come first)."""
        ms = self.markers
        assert ms is not None and self.sets[0] is ms, "the marker returns must be the first set"
        n = ms.r.size * ms.n_res
        return dense[:n].reshape(ms.r.size, ms.n_res, *dense.shape[1:])

    def centre_cross(self, th: FloatArray, R_ref: FloatArray, core: NDArray[np.intp], n_markers: int,
                     J_dense: FloatArray | None = None) -> FloatArray:
        """J_m^T J_c (len(core), 3 n_markers): the marker rows' core columns against their derivatives with respect
        to the marker centres (lrfcal.model.marker.centre_jacobian), summed per marker (each marker's x, y, z).
        Only marker rows depend on the centres among the residuals, and none of them on a plane's nuisances (the
        planes' priors do: :meth:`prior_cross`). ``J_dense``: :meth:`blocks`' dense Jacobian at th, when already
        computed (its first rows are the marker rows)."""
        ms = self.markers
        assert ms is not None, "the marker map's uncertainty needs marker returns"
        J = self.marker_rows(th, R_ref)[1] if J_dense is None else self.markers_in(J_dense)
        assert J is not None and ms.marker is not None
        Jc = centre_jacobian(th, ms, self.sigma_r, R_ref, self.clock)
        per_return = np.einsum("kri,krj->kij", J[:, :, core], Jc)  # (K, len(core), 3)
        B = np.zeros((n_markers, core.size, 3))
        np.add.at(B, ms.marker, per_return)
        return B.transpose(1, 0, 2).reshape(core.size, 3 * n_markers)

    def prior_cross(self, n_markers: int) -> FloatArray | None:
        """J_q^T J_qc (3P, 3 n_markers) of the planes' prior rows (th_nu - mean(c)) / sigma against the marker
        coordinates: -diag(1 / sigma^2) d mean / dc (lrfcal.stages.surfaces.plane_prior_jacobian); None without it."""
        s = self.surf
        if s is None or s.prior_sigma is None or s.prior_mean is None or s.prior_jacobian is None:
            return None
        assert s.prior_jacobian.shape[1] == 3 * n_markers
        return -s.prior_jacobian / s.prior_sigma[:, None] ** 2

    def blocks(self, th: FloatArray, R_ref: FloatArray, jac: bool = True, chart: FloatArray | None = None
               ) -> Blocks:
        """All whitened residuals as lrfcal.estimate.normal_equations.Blocks, each set's in the sets' order (dense
        rows: the marker returns, the design drawing's prior on the DH parameters; plane rows: the surface returns,
        with the planes' priors). ``chart`` (6, 4): what the scan-plane columns are derivatives by
        (lrfcal.model.chart; None: the DH parameters, as the prior's rows are)."""
        ctx = self.context(chart)
        return stack_blocks([s.blocks(self.own(th, i), R_ref, ctx, jac) for i, s in enumerate(self.sets)])

    def stacked(self, th: FloatArray, R_ref: FloatArray, jac: bool = True) -> tuple[FloatArray, FloatArray | None]:
        """All whitened residuals as one vector (dense rows, plane rows, plane priors) and the dense Jacobian
        (rows, N_CORE + 3P) (to check the blocks against finite differences; the solver uses :meth:`blocks`)."""
        b = self.blocks(th, R_ref, jac)
        res = b.residuals()
        if b.J_dense is None or b.Jc_plane is None or b.Jn_plane is None:
            return res, None
        m, K = b.r_dense.size, b.r_plane.size
        J = np.zeros((res.size, th.size))
        J[:m, :N_CORE] = b.J_dense
        J[m:m + K, :N_CORE] = b.Jc_plane
        J[m + np.arange(K)[:, None], N_CORE + 3 * b.plane[:, None] + np.arange(3)] = b.Jn_plane
        if b.w_prior is not None:
            J[m + K + np.arange(b.w_prior.size), N_CORE + np.arange(b.w_prior.size)] = b.w_prior
        return res, J


def marker_set(obs: Observations, markers_W: ArrayLike, sensor: MarkerSensor) -> tuple[MarkerSet, BoolArray]:
    """The returns of ``obs`` with a marker (and finite values) as a MarkerSet, and which rows those are (K,).

    Raises:
        InputError: a marker array out of its domain."""
    X = np.asarray(markers_W, dtype=float)
    if X.ndim != 2 or X.shape[1] != 3:
        raise InputError(f"solve: markers_W must be (n, 3), got {X.shape}")
    marker = np.asarray(obs.marker)
    if np.any(marker >= len(X)):
        raise InputError(f"solve: observation marker index {int(marker.max())} >= number of markers {len(X)}")
    use = (marker >= 0) & np.isfinite(obs.ranges_m) & np.isfinite(obs.lambda_rad) & np.isfinite(obs.mu_rad)
    ms = MarkerSet(np.asarray(obs.lambda_rad, dtype=float)[use], np.asarray(obs.mu_rad, dtype=float)[use],
                   np.asarray(obs.ranges_m, dtype=float)[use], X[marker[use]], sensor,
                   np.asarray(obs.times_s, dtype=float)[use], marker[use].astype(np.int64),
                   scan=np.asarray(obs.scan)[use].astype(np.int64), beam=np.asarray(obs.beam)[use].astype(np.int64))
    return ms, use


def marker_problem(obs: Observations, markers_W: ArrayLike, sensor: MarkerSensor) -> tuple[Problem, BoolArray]:
    """The problem of the returns of ``obs`` with a marker (and finite values), and which rows those are (K,).

    Raises:
        InputError: a marker array out of its domain.
    """
    ms, use = marker_set(obs, markers_W, sensor)
    return Problem((ms,), sensor.range_sigma_m), use


@dataclass(frozen=True)
class OnPlanes:
    """Surface returns with the planes they lie on, as an estimate takes them: ``returns`` (K returns with their
    plane index) and ``planes`` (the lrfcal.types.Surface of each plane index, whose normal and offset
    carry the markers' prior; None: free planes, started from the returns' normals and offsets)."""

    returns: SurfaceReturns
    planes: Sequence[Surface] | None = None

    def __len__(self) -> int:
        return len(self.returns)


def plane_set(surfaces: SurfaceReturns, planes: Sequence[Surface] | None) -> tuple[PlaneSet, FloatArray]:
    """The surface returns as a PlaneSet with the planes' nuisance start (3P,): started from the returns' normals
    and offsets; with ``planes`` (each surface index's lrfcal.types.Surface), their tangent axes and the
    markers' prior on them."""
    ids, plane_idx = np.unique(surfaces.surface, return_inverse=True)
    first = np.array([np.nonzero(surfaces.surface == p)[0][0] for p in ids])
    n0, t1, t2, nu0 = plane_nuisance_start(surfaces.normals[first], surfaces.offsets_m[first])
    prior_sigma = prior_jacobian = None
    if planes is not None:
        t1 = np.array([planes[i].axes[0] for i in ids])
        t2 = np.array([planes[i].axes[1] for i in ids])
        prior_sigma = np.concatenate([planes[i].prior_sigma for i in ids])
        jacobians = [planes[i].prior_jacobian for i in ids]
        if all(j is not None for j in jacobians):
            prior_jacobian = np.vstack(jacobians)
    surf = PlaneSet(surfaces.lambda_rad, surfaces.mu_rad, surfaces.ranges_m, plane_idx.astype(np.int64), n0, t1, t2,
                    nu0.copy(), prior_sigma, times=surfaces.times_s, prior_jacobian=prior_jacobian,
                    scan=np.asarray(surfaces.scan).astype(np.int64), beam=np.asarray(surfaces.beam).astype(np.int64))
    return surf, nu0


def plane_problem(surfaces: SurfaceReturns, range_sigma_m: float, clock: MotorClock | None,
                  dh_prior: tuple[FloatArray, FloatArray] | None = None, footing: Footing | None = None,
                  range_pattern: bool = False) -> tuple[Problem, FloatArray]:
    """A problem of surface returns only (no marker returns) on free planes (with the design drawing's prior on
    the DH parameters when given: its mean (4,) and sigma (4,); where a return counts judged at every estimate by
    ``footing``, lrfcal.model.plane.Footing; with ``range_pattern``, the scanner's range error along the scan a
    nuisance beside the planes, lrfcal.model.range_pattern), and the planes' nuisance start.

    Raises:
        InputError: a range noise not above 0, or a clock without the returns' beam times.
    """
    if not range_sigma_m > 0:
        raise InputError(f"solve: range_sigma_m must be > 0, got {range_sigma_m}")
    if clock is not None and surfaces.times_s is None:
        raise InputError("solve: the clock offset needs the surface returns' beam times (times_s)")
    surf, nu0 = plane_set(surfaces, None)
    surf = replace(surf, footing=footing, pattern_bins=beam_bins(surfaces.beam) if range_pattern else None)
    sets: tuple[ObservationSet, ...] = (surf,) if dh_prior is None else (DHPrior(*dh_prior), surf)
    return Problem(sets, float(range_sigma_m), clock=clock, mount_jac=False, incidence_jac=False), nu0


__all__ = ["OnPlanes", "Problem", "marker_problem", "marker_set", "plane_problem", "plane_set"]

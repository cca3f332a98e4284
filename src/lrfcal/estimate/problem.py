"""The data of one least-squares problem and its whitened residuals: marker returns (lrfcal.model.marker), surface
returns on planes whose normals and offsets are nuisances (lrfcal.model.plane), the planes' priors and the design
drawing's prior on the DH parameters, all as the blocks the solver's normal equations take
(lrfcal.estimate.normal_equations). Markers, surfaces, targetless, plan and study build one of these; one engine
(lrfcal.estimate.solve) solves it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lrfcal.errors import InputError
from lrfcal.estimate.normal_equations import Blocks
from lrfcal.model.marker import MODELS, MarkerSet, centre_jacobian, marker_rows
from lrfcal.model.motor import MotorClock
from lrfcal.model.plane import plane_rows
from lrfcal.model.unknowns import DH_SLICE, N_CORE, PlaneSet, dh_difference, plane_nuisance_start
from lrfcal.stages.surfaces import Surface, SurfaceReturns
from lrfcal.types import Observations

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Problem:
    """Marker returns, optional surface returns, the range noise, optional clock (the clock offset estimated), an
    optional prior on the DH parameters, and whether the mount's Jacobian is needed."""

    markers: MarkerSet
    sigma_r: float
    surf: PlaneSet | None = None
    clock: MotorClock | None = None  # set when the clock offset is estimated
    dh_prior: tuple[FloatArray, FloatArray] | None = None  # (mean (4,), sigma (4,)) of a, alpha, b, beta
    mount_jac: bool = True  # False: the mount is held, its Jacobian columns are not computed (left 0)

    def subset(self, m: NDArray[np.bool_], ms: NDArray[np.bool_] | None = None) -> Problem:
        """The marker returns ``m`` and the surface returns ``ms`` (all when None)."""
        surf = self.surf if self.surf is None or ms is None else self.surf.subset(ms)
        return replace(self, markers=self.markers.subset(m), surf=surf)

    def marker_rows(self, th: FloatArray, R_ref: FloatArray, jac: bool = True, chart: FloatArray | None = None
                    ) -> tuple[FloatArray, FloatArray | None]:
        """Whitened marker residuals (K, n_res) and Jacobian (K, n_res, N_CORE) (lrfcal.model.marker; ``chart``:
        lrfcal.model.chart, None for the DH parameters)."""
        return marker_rows(th, self.markers, self.sigma_r, R_ref, jac=jac, clock=self.clock, mount_jac=self.mount_jac,
                           chart=chart)

    def centre_cross(self, th: FloatArray, R_ref: FloatArray, core: NDArray[np.intp], n_markers: int,
                     J_dense: FloatArray | None = None) -> FloatArray:
        """J_m^T J_c (len(core), 3 n_markers): the marker rows' core columns against their derivatives with respect
        to the marker centres (lrfcal.model.marker.centre_jacobian), summed per marker (each marker's x, y, z).
        Only marker rows depend on the centres among the residuals, and none of them on a plane's nuisances (the
        planes' priors do: :meth:`prior_cross`). ``J_dense``: :meth:`blocks`' dense Jacobian at th, when already
        computed (its first rows are the marker rows)."""
        ms = self.markers
        if J_dense is None:
            _, J = self.marker_rows(th, R_ref)
        else:
            J = J_dense[:ms.r.size * ms.n_res].reshape(ms.r.size, ms.n_res, N_CORE)
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
        """All whitened residuals as lrfcal.estimate.normal_equations.Blocks: the marker returns and the design
        drawing's
        prior on the DH parameters (dense rows), the surface returns (plane rows) and the planes' priors. ``chart``
        (6, 4): what the scan-plane columns are derivatives by (lrfcal.model.chart; None: the DH parameters, as
        the prior's rows are)."""
        assert chart is None or self.dh_prior is None, "a prior on the DH parameters needs the DH chart"
        z = np.zeros(0)
        r_d = z
        J_d: FloatArray | None = np.zeros((0, N_CORE))
        if self.markers.r.size:
            res, J = self.marker_rows(th, R_ref, jac=jac, chart=chart)
            r_d, J_d = res.ravel(), (None if J is None else J.reshape(-1, N_CORE))
        if self.dh_prior is not None:  # the design drawing's word on the DH parameters
            mean, sig = self.dh_prior
            d = dh_difference(th[DH_SLICE], mean)
            r_d = np.concatenate([r_d, d / sig])
            if J_d is not None:
                Jp = np.zeros((4, N_CORE))
                Jp[:, DH_SLICE] = np.diag(1.0 / sig)
                J_d = np.vstack([J_d, Jp])
        s = self.surf
        if s is None:
            return Blocks(r_d, J_d, z, np.zeros((0, N_CORE)), np.zeros((0, 3)), np.zeros(0, dtype=np.int64), 0)
        rows = plane_rows(th, s, self.sigma_r, R_ref, jac=jac, clock=self.clock, mount_jac=self.mount_jac,
                          chart=chart)
        r_q = w_q = None
        if s.prior_sigma is not None and s.prior_mean is not None:  # the markers' word on the planes
            r_q, w_q = (th[N_CORE:] - s.prior_mean) / s.prior_sigma, 1.0 / s.prior_sigma
        return Blocks(r_d, J_d, rows.res, rows.Jc, rows.Jn, s.plane, s.n_planes, r_q, w_q, s.segments)

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


def marker_problem(
    obs: Observations, markers_W: ArrayLike, model: str, radius: float, sigma_r: float, divergence: float = 0.0
) -> tuple[Problem, NDArray[np.bool_]]:
    """The problem of the returns of ``obs`` with a marker (and finite values), and which rows those are (K,).

    Raises:
        InputError: a model, marker array, radius, noise or divergence out of its domain.
    """
    if model not in MODELS:
        raise InputError(f"solve: model must be one of {', '.join(MODELS)}, got {model!r}")
    X = np.asarray(markers_W, dtype=float)
    if X.ndim != 2 or X.shape[1] != 3:
        raise InputError(f"solve: markers_W must be (n, 3), got {X.shape}")
    if not radius > 0 or not sigma_r > 0:
        raise InputError(f"solve: marker_radius_m and range_sigma_m must be > 0, got {radius}, {sigma_r}")
    if not 0.0 <= divergence < 0.1:
        raise InputError(f"solve: beam_divergence_rad must be in [0, 0.1) rad, got {divergence}")
    marker = np.asarray(obs.marker)
    if np.any(marker >= len(X)):
        raise InputError(f"solve: observation marker index {int(marker.max())} >= number of markers {len(X)}")
    use = (marker >= 0) & np.isfinite(obs.ranges_m) & np.isfinite(obs.lambda_rad) & np.isfinite(obs.mu_rad)
    ms = MarkerSet(np.asarray(obs.lambda_rad, dtype=float)[use], np.asarray(obs.mu_rad, dtype=float)[use],
                   np.asarray(obs.ranges_m, dtype=float)[use], X[marker[use]], model, float(radius),
                   float(divergence), np.asarray(obs.times_s, dtype=float)[use], marker[use].astype(np.int64))
    return Problem(ms, float(sigma_r)), use


def no_markers() -> MarkerSet:
    """An empty marker set (a problem of surface returns only)."""
    z = np.zeros(0)
    return MarkerSet(z, z, z, np.zeros((0, 3)), "sphere", 1.0, 0.0, z)


def plane_set(surfaces: SurfaceReturns, planes: Sequence[Surface] | None) -> tuple[PlaneSet, FloatArray]:
    """The surface returns as a PlaneSet with the planes' nuisance start (3P,): started from the returns' normals
    and offsets; with ``planes`` (each surface index's lrfcal.stages.surfaces.Surface), their tangent axes and the
    markers'
    prior on them."""
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
                    nu0.copy(), prior_sigma, times=surfaces.times_s, prior_jacobian=prior_jacobian)
    return surf, nu0


def plane_problem(surfaces: SurfaceReturns, range_sigma_m: float, clock: MotorClock | None,
                  dh_prior: tuple[FloatArray, FloatArray] | None = None) -> tuple[Problem, FloatArray]:
    """A problem of surface returns only (no marker returns) on free planes, and the planes' nuisance start.

    Raises:
        InputError: a range noise not above 0, or a clock without the returns' beam times.
    """
    if not range_sigma_m > 0:
        raise InputError(f"solve: range_sigma_m must be > 0, got {range_sigma_m}")
    if clock is not None and surfaces.times_s is None:
        raise InputError("solve: the clock offset needs the surface returns' beam times (times_s)")
    surf, nu0 = plane_set(surfaces, None)
    return Problem(no_markers(), float(range_sigma_m), surf=surf, clock=clock, dh_prior=dh_prior,
                   mount_jac=False), nu0


__all__ = ["Problem", "marker_problem", "no_markers", "plane_problem", "plane_set"]

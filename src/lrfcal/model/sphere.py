"""The marker model's depth: how far below a sphere's centre plane a beam meets its surface (lrfcal.estimate.solve's
sphere
model), for a beam's axis (:func:`sphere_depth`) and for a beam with a finite footprint (:func:`footprint_depth`).

Split out of lrfcal.estimate.solve (which re-exports both names); the formulas are documented in that module's
docstring.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import expit

FloatArray = NDArray[np.float64]

_ETA = 0.05  # softness of the sphere's rim in s(u)


def sphere_depth(u: ArrayLike, eta: float = _ETA) -> tuple[FloatArray, FloatArray]:
    """Smoothed depth of a unit sphere's surface below its centre plane at lateral offset u, and ds/du.

    s(u) = sqrt(eta log(1 + exp((1 - u^2) / eta))) ~ sqrt(1 - u^2) inside, -> 0 beyond the rim;
    ds/du = -u expit((1 - u^2) / eta) / s (bounded; |ds/du| <= ~1 / sqrt(eta log 2) near u = 1).
    """
    u = np.asarray(u, dtype=float)
    return _sphere_depth_q(u, (1.0 - u * u) / eta, eta)


def _sphere_depth_q(u: FloatArray, q: FloatArray, eta: float) -> tuple[FloatArray, FloatArray]:
    """:func:`sphere_depth` of u given q = (1 - u^2) / eta (its caller's own q, computed once)."""
    far = q < -30.0  # beyond the rim: softplus(q) = exp(q) to double precision, written to avoid 0 / 0
    if not far.any():  # every point inside the soft rim (the usual case): the near branch alone, the same bits
        s = np.sqrt(eta * np.logaddexp(0.0, q))
        return s, -u * expit(q) / s
    qn = np.where(far, 0.0, q)
    s_near = np.sqrt(eta * np.logaddexp(0.0, qn))
    s = np.where(far, np.sqrt(eta) * np.exp(0.5 * q), s_near)
    ds = np.where(far, -u * np.exp(0.5 * q) / np.sqrt(eta), -u * expit(qn) / s_near)
    return s, ds


def _unit_disc(n: int) -> FloatArray:
    """n equal-area samples (n, 2) of the unit disc (Vogel's sunflower spiral)."""
    i = np.arange(n) + 0.5
    rho = np.sqrt(i / n)
    ang = i * np.pi * (3.0 - np.sqrt(5.0))
    return np.stack([rho * np.cos(ang), rho * np.sin(ang)], -1)


_DISC = _unit_disc(37)  # the beam's footprint, in units of its radius (37 points: the depth to ~0.04 R_m at k = 1,
#                             0.2 mm on 5 mm markers, beside 10 mm of range noise)
_DISC_DEPTH = np.sqrt(np.maximum(0.0, 1.0 - (_DISC ** 2).sum(1)))  # s on the sphere's own disc (k > 1)
_DISC_INCIDENCE = np.arcsin(np.minimum(1.0, np.sqrt((_DISC ** 2).sum(1))))  # the incidence there (k > 1)

#: what is averaged over a footprint at offsets rho from the centre (q = (1 - rho^2) / eta): its value and d/d rho
_PointValue = Callable[[FloatArray, FloatArray, float], tuple[FloatArray, FloatArray]]


def _incidence_q(rho: FloatArray, q: FloatArray, eta: float) -> tuple[FloatArray, FloatArray]:
    """The incidence angle where a ray at offset rho meets the unit sphere, theta = atan2(rho, s(rho)) (sin theta = rho
    and cos theta = s on the sphere; smooth through the rim, where theta -> pi / 2), and d theta / d rho."""
    s, ds = _sphere_depth_q(rho, q, eta)
    return np.arctan2(rho, s), (s - rho * ds) / (rho * rho + s * s)


def footprint_depth(u: ArrayLike, k: ArrayLike, eta: float = _ETA) -> tuple[FloatArray, FloatArray]:
    """Depth of a unit sphere below its centre plane seen through a beam with a finite footprint, and its
    derivative in u: the mean of s(rho) (:func:`sphere_depth`) over the part of a uniform disc of radius k (the
    footprint, in sphere radii) centred at lateral offset u that hits the sphere. A retroreflective marker
    outshines whatever else the footprint hits, so the mixed return is the mean over the hits alone (lrfsim.lidar's
    mixed pixel). The mean is taken over points of the smaller disc: the footprint's (k <= 1), each weighted by a
    soft hit expit((1 - rho^2) / eta) (the rim of s), or the sphere's (k > 1), each weighted by a soft "inside the
    footprint" expit((k^2 - |y - u|^2) / (eta k^2)). k = 0: :func:`sphere_depth`.

    Args:
        u: (K,) offset of the beam's axis from the sphere's centre, in sphere radii.
        k: (K,) footprint radius at the sphere (range x divergence / 2), in sphere radii; broadcast with u.
    Returns:
        S (K,), dS/du (K,).
    """
    return _over_footprint(u, k, eta, _sphere_depth_q, _DISC_DEPTH)


def footprint_incidence(u: ArrayLike, k: ArrayLike, eta: float = _ETA) -> tuple[FloatArray, FloatArray]:
    """The beam's mean incidence angle on a unit sphere [rad] (K,) over the same part of its footprint as
    :func:`footprint_depth`, and its derivative in u (K,): what a range's incidence bias sees on a marker."""
    return _over_footprint(u, k, eta, _incidence_q, _DISC_INCIDENCE)


def _over_footprint(u: ArrayLike, k: ArrayLike, eta: float, value: _PointValue, on_disc: FloatArray
                    ) -> tuple[FloatArray, FloatArray]:
    """The mean of ``value`` over the footprint's hits (:func:`footprint_depth`) and its derivative in u;
    ``on_disc``: its values on the sphere's own disc (k > 1)."""
    u, k = np.broadcast_arrays(np.asarray(u, dtype=float), np.asarray(k, dtype=float))
    if not np.any(k > 0):
        return value(u, (1.0 - u * u) / eta, eta)
    S, dS = np.empty(u.shape), np.empty(u.shape)
    x1, x2 = _DISC[:, 0], _DISC[:, 1]
    small = k <= 1.0
    if np.any(small):  # points of the footprint, weighted by hitting the sphere
        us, ks = u[small][:, None], k[small][:, None]
        a = us + ks * x1
        rho = np.sqrt(a * a + (ks * x2) ** 2)
        q = (1.0 - rho * rho) / eta
        s, ds = value(rho, q, eta)
        # d rho / d u (a / rho where rho > 1e-12, the usual case everywhere: no masking then, the same bits)
        drho = a / rho if (rho > 1e-12).all() else np.where(rho > 1e-12, a / np.maximum(rho, 1e-12), 1.0)
        S[small], dS[small] = _weighted_mean(s, ds * drho, q, -2.0 * rho * drho / eta)
    if np.any(~small):  # points of the sphere's disc, weighted by lying in the footprint
        ub, kb = u[~small][:, None], k[~small][:, None]
        s = np.broadcast_to(on_disc, (ub.shape[0], on_disc.size))
        dx = x1 - ub
        q = (kb * kb - dx * dx - x2 * x2) / (eta * kb * kb)
        S[~small], dS[~small] = _weighted_mean(s, np.zeros_like(s), q, 2.0 * dx / (eta * kb * kb))
    return S, dS


def _weighted_mean(v: FloatArray, dv: FloatArray, q: FloatArray, dq: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Mean of v (K, P) over P points with weights expit(q) (K, P), and its derivative given dv, dq (K, P)."""
    logw = -np.logaddexp(0.0, -q)  # log expit(q), without underflow far from the region
    w = np.exp(logw - logw.max(-1, keepdims=True))
    dw = w * expit(-q) * dq
    W = w.sum(-1)
    m = (w * v).sum(-1) / W
    return m, ((w * dv).sum(-1) + (dw * v).sum(-1) - m * dw.sum(-1)) / W


__all__ = ["footprint_depth", "footprint_incidence", "sphere_depth"]

"""The scanner's intrinsics: the range it reports of a true range, and the true bearing of a declared one.

    r = range_scale r_true + range_offset + marker_range_bias [marker returns only] + incidence_bias theta
    mu_true = beam_scale mu          (mu = angle_min + i angle_increment as the scan declares it; beta, the DH
                                      angle, absorbs any constant, so a wrongly declared increment is a scale)

theta is the beam's incidence on the surface it meets [rad] (0 head-on), which each observation model knows from its
geometry (a plane's normal, where the beam meets a sphere): a range read longer the more obliquely a surface is met
(docs/sensor_errors.md, "incidence"). :func:`true_range` has no geometry and leaves that term out.

The range observation models predict a beam's true range r_hat from the geometry and compare the reported range
with :func:`reported_range` of it: the scale multiplies the prediction, never the measurement, so the range noise
stays out of the Jacobian. (A scale on the measured range is an errors-in-variables model: its column carries the
noise, which correlates with the residual; with 10 mm noise and the planes free, which make a scale nearly a gauge,
it stepped the range scale's score test 2.5 % from 1, 30-46 sigma, on clean recordings.) :func:`true_range` inverts
it, for the reprojection and the paper's point model. The partial derivatives are the range and bearing columns of
every observation model's Jacobian, so an unknown acting on the range or the bearing is written here once.

A beam whose footprint straddles a jump edge (a near surface's edge against a far one behind it) reports a range
between the two, on neither surface (a mixed pixel, or veil point): :func:`jump_edges` finds the returns beside such
an edge from the ranges alone, as ROS's laser_filters ScanShadowsFilter does along the scan
(github.com/ros-perception/laser_filters, src/scan_shadows_filter.cpp: a return whose segment to a neighbouring
return makes an angle below ``min_angle`` with its beam), and across it: the footprint is a disc, and where the motor
turns the scan plane over an edge a few scans straddle it too.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from lrfcal.model.motor import motor_angles
from lrfcal.model.unknowns import BSCALE, INC, MBIAS, ROFF, RSCALE

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Reported:
    """The reported ranges r (K,) predicted from true ones, dr/dr_true (the range scale, a scalar) and, per unknown
    acting on them, (core index, dr/dtheta (K,))."""

    r: FloatArray
    scale: float
    partials: tuple[tuple[int, FloatArray], ...]


def reported_range(th: FloatArray, r_true: FloatArray, on_marker: bool, incidence: FloatArray | None = None
                   ) -> Reported:
    """The range the scanner reports of the true ranges ``r_true`` (K,) at the unknowns ``th`` (module docstring);
    ``on_marker``: the returns are from retroreflective markers (their range bias applies); ``incidence``: each
    beam's incidence on its surface [rad] (K,) (None: not known, the incidence bias left out). The partials are those
    at a fixed incidence: the observation model adds the incidence's own change (incidence_bias d theta)."""
    r_true = np.asarray(r_true, dtype=float)
    k = float(th[RSCALE])
    one = np.ones(r_true.shape)
    r = (r_true if k == 1.0 else k * r_true) + th[ROFF]
    partials: tuple[tuple[int, FloatArray], ...] = ((ROFF, one), (RSCALE, r_true))
    if on_marker:
        r, partials = r + th[MBIAS], (*partials, (MBIAS, one))
    if incidence is not None:
        r, partials = (r if th[INC] == 0.0 else r + th[INC] * incidence), (*partials, (INC, incidence))
    return Reported(r, k, partials)


@dataclass(frozen=True)
class TrueRange:
    """The true ranges r (K,) of reported ones and their partials: (core index, dr_true/dtheta (K,)) per unknown."""

    r: FloatArray
    partials: tuple[tuple[int, FloatArray], ...]


def true_range(th: FloatArray, r: FloatArray, on_marker: bool) -> TrueRange:
    """The true range of the reported ranges ``r`` (K,): :func:`reported_range` inverted,
    r_true = (r - range_offset [- marker_range_bias]) / range_scale."""
    r = np.asarray(r, dtype=float)
    k = float(th[RSCALE])
    less = r - th[ROFF] - (th[MBIAS] if on_marker else 0.0)
    rt = less if k == 1.0 else less / k
    inv = np.full(r.shape, -1.0 / k)
    offsets = ((ROFF, inv), (MBIAS, inv)) if on_marker else ((ROFF, inv),)
    return TrueRange(rt, (*offsets, (RSCALE, -rt / k)))


@dataclass(frozen=True)
class TrueBearing:
    """The bearings mu_true (K,) and their partials: (core index, dmu_true/dtheta (K,)) per unknown acting on them."""

    mu: FloatArray
    partials: tuple[tuple[int, FloatArray], ...]


def true_bearing(th: FloatArray, mu: FloatArray) -> TrueBearing:
    """mu_true of the declared bearings ``mu`` (K,) at the unknowns ``th`` (module docstring)."""
    mu = np.asarray(mu, dtype=float)
    return TrueBearing(th[BSCALE] * mu, ((BSCALE, mu),))


def true_returns(th: FloatArray, r: FloatArray, q: FloatArray, mu: FloatArray, on_marker: bool = False
                 ) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Returns as the model has them at the intrinsics of ``th``: the true ranges of the reported ``r`` (K,), the
    motor angles of the joint angles ``q`` (K,) (interpolated at the clock offset already; lrfcal.model.motor) and
    the true bearings of the declared ``mu`` (K,); for reprojecting them (lrfcal.model.kinematics.points_M)."""
    return (true_range(th, r, on_marker).r, motor_angles(th, np.asarray(q, dtype=float), None, None).lam,
            true_bearing(th, mu).mu)


#: a return whose range differs from a neighbouring return's by more than the cotangent of this angle times their
#: spacing across the beam sits beside a jump edge (the segment between them lies within this angle of the beam:
#: laser_filters ScanShadowsFilter's usual min_angle; a plane met at the default 65 deg limit of incidence makes
#: 25 deg with the beam) [rad]
JUMP_EDGE_ANGLE_RAD = float(np.radians(10.0))
#: ... and by more than this many sigma of the difference of two returns' noise (sqrt(2) range sigma): range noise
#: alone is no edge where neighbours lie closer than the noise (near returns, fine steps of the motor)
JUMP_EDGE_NOISE_SIGMA = 4.0


def jump_edges(ranges_m: FloatArray, mu_rad: FloatArray, lam_rad: FloatArray | None = None, noise_m: float = 0.0,
               min_angle_rad: float = JUMP_EDGE_ANGLE_RAD) -> NDArray[np.bool_]:
    """The returns (S, N) beside a jump edge (module docstring): those whose range differs from a neighbour's by
    more than cot(``min_angle_rad``) times their spacing across the beam and by more than JUMP_EDGE_NOISE_SIGMA
    sqrt(2) ``noise_m``. Neighbours are the next and the previous beam of the scan (spacing r |d mu|, ``mu_rad`` the
    declared bearings (N,) or (S, N)) and, with ``lam_rad`` (S,) the scans' motor angles, the same beam of the next
    and the previous scan (spacing about r |d lambda|: the footprint is a disc, and it straddles an edge across the
    scan plane as it does along it). ``ranges_m`` (S, N) as reported: NaN (an invalid reading) is never judged nor
    makes its neighbours judged; +inf (nothing within range, REP 117) is the farthest background, so a return beside
    it sits beside a jump edge."""
    r = np.asarray(ranges_m, dtype=float)
    slope = 1.0 / math.tan(min_angle_rad)
    floor = JUMP_EDGE_NOISE_SIGMA * math.sqrt(2.0) * noise_m
    edge = np.zeros(r.shape, dtype=bool)
    # (one side, the other side, their angular step): beside along the scan, then across the scans
    pairs = [(edge[:, :-1], edge[:, 1:], r[:, :-1], r[:, 1:], np.abs(np.diff(np.asarray(mu_rad, dtype=float))))]
    if lam_rad is not None and r.shape[0] > 1:
        pairs.append((edge[:-1], edge[1:], r[:-1], r[1:], np.abs(np.diff(np.asarray(lam_rad, dtype=float)))[:, None]))
    for one, other, a, b, step in pairs:
        with np.errstate(invalid="ignore"):
            d = np.abs(b - a)
            jump = (d > slope * np.fmin(a, b) * step) & (d > floor)  # NaN (no return) compares False
        one |= jump  # views of edge
        other |= jump
    return edge & np.isfinite(r)  # a return (no reading is one)


__all__ = ["JUMP_EDGE_ANGLE_RAD", "JUMP_EDGE_NOISE_SIGMA", "Reported", "TrueBearing", "TrueRange", "jump_edges",
           "reported_range", "true_bearing", "true_range", "true_returns"]

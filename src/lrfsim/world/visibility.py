"""What the sweep or spin of a scenario can see, and whether a layout determines the four DH parameters (the
labels of :mod:`lrfsim.testing.random_scenarios`'s broad random truths).

* :func:`visible_markers`: the markers some beam within the field of view meets at some motor angle (geometry
  only); :func:`beam_through` / :func:`visible_in_M`: the same for directions in the motor frame;
* :func:`wide_dh_sigma`, :func:`axial_spread_m`, :func:`wide_dh_determined`: the determinability label;
* :func:`scans_near_markers`: the scans some beam of which can pass near a marker (`lrfsim plan`'s sparse cast).

The geometry takes the optical centre on the motor axis, at its axial coordinate b cos(alpha) (eq. 3: the
optical centre in M is Rz(lambda) (a, -b sin alpha, b cos alpha)); the radial offset (a, -b sin alpha), a few cm,
is left out.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from lrfsim.sensors.servo import covered_angles_rad

if TYPE_CHECKING:
    from lrfcal.model.kinematics import Params
    from lrfsim.scenario.file import Scenario
    from lrfsim.scenario.sections import ServoConfig

#: margin inside the scanner's field of view and the sweep for a marker to count as visible
VIS_MARGIN_RAD = math.radians(3.0)
#: half field of view of the UTM-30LX (270 deg)
HALF_FOV_RAD = math.radians(135.0)


def visible_markers(scenario: Scenario) -> np.ndarray:
    """(n,) bool: the markers the sweep can see (within the field of view at some motor angle of the sweep,
    3 deg margin; geometry only: no occlusion, range or intensity model)."""
    from .geometry import marker_centres_W

    dh = scenario.rig.dh
    lo, hi = motor_range_rad(scenario.servo)
    return visible_in_M(directions_M(scenario, marker_centres_W(scenario)), dh.alpha, dh.beta, lo, hi)


def directions_M(scenario: Scenario, points_W: np.ndarray) -> np.ndarray:
    """(k, 3): points (k, 3) in W as seen from the optical centre's point on the motor axis, in M (truth)."""
    T = scenario.rig.mount.to_pose().matrix()
    dh = scenario.rig.dh
    return (points_W - T[:3, 3]) @ T[:3, :3] - np.array([0.0, 0.0, dh.b * math.cos(dh.alpha)])


def motor_range_rad(servo: ServoConfig) -> tuple[float, float]:
    """The motor angles the servo covers (lrfsim.sensors.servo.covered_angles_rad) as the visibility tests take them
    (their candidate angles lie within [-7 pi / 2, 9 pi / 2]): a sweep's (and a step and scan's) as they are; a
    spin's moved by whole turns to start in [-pi, pi); a spin that turns a full circle beyond the margins: (-pi, pi)
    widened by the margin, the whole circle."""
    lo, hi = covered_angles_rad(servo)
    if servo.mode != "spin":  # a sweep, a step and scan
        return lo, hi
    if hi - lo >= 2 * math.pi + 2 * VIS_MARGIN_RAD:
        return -math.pi - VIS_MARGIN_RAD, math.pi + VIS_MARGIN_RAD
    shift = 2 * math.pi * math.floor((lo + math.pi) / (2 * math.pi))
    return lo - shift, hi - shift


def beam_through(u_M: np.ndarray, alpha: float, beta: float, lam_lo: float, lam_hi: float,
                 margin: float = VIS_MARGIN_RAD) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For directions u_M (k, 3) (from the optical centre, taken on the motor axis): (visible (k,), lambda (k,),
    mu (k,)) of one beam through each within the field of view (|mu| <= 135 deg - margin) at a motor angle in
    [lam_lo + margin, lam_hi - margin], the first solution found; NaN where there is none. The scan plane at
    lambda is Rz(lambda) span{x, (0, cos alpha, sin alpha)} (eq. 3 with a = b = 0)."""
    k = len(u_M)
    lam_out, mu_out = np.full(k, np.nan), np.full(k, np.nan)
    u = u_M / np.linalg.norm(u_M, axis=1, keepdims=True)
    theta, rho = np.arctan2(u[:, 1], u[:, 0]), np.hypot(u[:, 0], u[:, 1])
    sa, ca = math.sin(alpha), math.cos(alpha)
    with np.errstate(divide="ignore", invalid="ignore"):
        q = -ca * u[:, 2] / (rho * sa)
    asq = np.arcsin(np.clip(q, -1, 1))
    for lam in (theta + asq, theta + math.pi - asq):
        for shift in (-2 * math.pi, 0.0, 2 * math.pi):
            lk = lam + shift
            c, s = np.cos(lk), np.sin(lk)
            w = np.column_stack([c * u[:, 0] + s * u[:, 1], -s * u[:, 0] + c * u[:, 1], u[:, 2]])
            mu = np.remainder(np.arctan2(w[:, 1] * ca + w[:, 2] * sa, w[:, 0]) - beta + math.pi, 2 * math.pi) - math.pi
            ok = (np.abs(q) <= 1) & (lk >= lam_lo + margin) & (lk <= lam_hi - margin)
            ok &= (np.abs(mu) <= HALF_FOV_RAD - margin) & np.isnan(lam_out)
            lam_out[ok], mu_out[ok] = lk[ok], mu[ok]
    return ~np.isnan(lam_out), lam_out, mu_out


def visible_in_M(u_M: np.ndarray, alpha: float, beta: float, lam_lo: float, lam_hi: float,
                 margin: float = VIS_MARGIN_RAD) -> np.ndarray:
    """(k,) bool: is direction u_M (k, 3) on some beam within the field of view at some motor angle of
    [lam_lo, lam_hi] (:func:`beam_through`, its margins)?"""
    return beam_through(u_M, alpha, beta, lam_lo, lam_hi, margin)[0]


def wide_dh_sigma(scenario: Scenario, sigma_m: float | None = None) -> np.ndarray:
    """(4,) 1-sigma of (a, alpha, b, beta) [m, rad, m, rad] that the layout allows in the paper's point model:
    one return per visible marker and pass at the beam through its centre, a 3D point residual with isotropic
    noise ``sigma_m`` (default: the first range noise band's), the mount (position and a local rotation vector,
    free of Euler singularities) estimated jointly. inf when the 10 parameters are not determined."""
    from lrfcal.model.kinematics import DH, points_M

    from .geometry import marker_centres_W

    sigma = sigma_m if sigma_m is not None else scenario.sensor.noise_bands[0].sigma_m
    C = marker_centres_W(scenario)
    T = scenario.rig.mount.to_pose().matrix()
    R0, t0 = T[:3, :3], T[:3, 3]
    dh0 = scenario.rig.dh
    lo, hi = motor_range_rad(scenario.servo)
    vis, lam, mu = beam_through(directions_M(scenario, C), dh0.alpha, dh0.beta, lo, hi)
    if vis.sum() < 4:
        return np.full(4, np.inf)
    C, lam, mu = C[vis], lam[vis], mu[vis]
    r = np.linalg.norm(C - t0, axis=1)
    x0 = np.array([dh0.a, dh0.alpha, dh0.b, dh0.beta])

    def model(v: np.ndarray) -> np.ndarray:
        p_M = points_M(r, lam, mu, DH(*map(float, v[:4])))
        return (p_M @ (R0 @ rotvec(v[7:10])).T + t0 + v[4:7]).ravel()

    v0 = np.concatenate([x0, np.zeros(6)])
    J = np.empty((3 * len(C), 10))
    for i in range(10):
        h = 1e-6
        dv = np.zeros(10)
        dv[i] = h
        J[:, i] = (model(v0 + dv) - model(v0 - dv)) / (2 * h)
    scale = np.linalg.norm(J, axis=0)
    Js = J / np.where(scale > 0, scale, 1.0)
    sv = np.linalg.svd(Js, compute_uv=False)
    if sv[-1] < 1e-9 * sv[0]:
        return np.full(4, np.inf)
    servo = scenario.servo  # a sweep sees each marker once a pass, a spin (at least) once a turn
    looks = max(1.0, servo.revolutions) if servo.mode == "spin" else servo.passes
    cov = np.linalg.inv(Js.T @ Js) / np.outer(scale, scale) * sigma**2 / looks
    return np.sqrt(np.diag(cov)[:4])


#: a layout determines the DH parameters when the point model's 1-sigma stays below these (a, alpha, b, beta).
#: The point model is 3-120x more pessimistic than the calibration's own sigma (which uses every beam on a
#: marker and the surfaces; measured on 8 wide scenarios: calibrated sigma(b) 0.2-14 mm where the point model
#: gives 10-50 mm), so these limits flag ill-conditioned geometry, not the final accuracy.
WIDE_SIGMA_LIMITS = (0.05, math.radians(3.0), 0.05, math.radians(3.0))


#: visible markers whose axial coordinates (along the motor axis) spread less than this (std) are "at one
#: axial distance": d alpha * D then moves the returns as d b does
WIDE_MIN_AXIAL_SPREAD_M = 0.10


def axial_spread_m(scenario: Scenario) -> float:
    """Standard deviation [m] of the visible markers' coordinates along the motor axis (z_M, truth)."""
    from .geometry import marker_centres_W

    T = scenario.rig.mount.to_pose().matrix()
    z = ((marker_centres_W(scenario) - T[:3, 3]) @ T[:3, 2])[visible_markers(scenario)]
    return float(z.std()) if z.size else 0.0


def wide_dh_determined(scenario: Scenario) -> bool:
    """Should the layout determine all four DH parameters? At least 6 visible markers, spread along the motor
    axis (:func:`axial_spread_m` >= WIDE_MIN_AXIAL_SPREAD_M: not all at one axial distance, as on a V on the
    wall the motor axis points at, or a board across the axis), and the point model's 1-sigma
    (:func:`wide_dh_sigma`, at the scenario's range noise) within WIDE_SIGMA_LIMITS (False when the markers
    fill too small a part of the sweep for another combination of parameters)."""
    if int(visible_markers(scenario).sum()) < 6 or axial_spread_m(scenario) < WIDE_MIN_AXIAL_SPREAD_M:
        return False
    return bool(np.all(wide_dh_sigma(scenario) <= np.array(WIDE_SIGMA_LIMITS)))


#: bearings (fractions of the field of view) at which :func:`scans_near_markers` samples each scan's plane
NEAR_SAMPLES = (0.0, 0.25, 0.5, 0.75, 1.0)


def scans_near_markers(params: Params, beam_lambda_rad: np.ndarray, mu_rad: np.ndarray, centres_W: np.ndarray,
                       reach_m: float, spread_rad: float) -> np.ndarray:
    """(S,) bool: the scans (true motor angle of every beam (S, N), bearings (N,), true Params) whose scan plane
    passes within reach of a marker (centres (m, 3) in W): within ``reach_m`` + ``spread_rad`` times the distance
    of the marker from the beam's origin, at one of the :data:`NEAR_SAMPLES` bearings, or on both sides of it
    (the plane turns smoothly within a scan); and one scan on each side of such a scan. A superset of the scans
    with a return on a marker: `lrfsim plan` casts them (the marker beams as the full cast has them) and skips most
    others."""
    from lrfcal.model.kinematics import beam_rays_W

    S, N = beam_lambda_rad.shape
    if S == 0 or not len(centres_W):
        return np.zeros(S, dtype=bool)
    cols = sorted({round(f * (N - 1)) for f in NEAR_SAMPLES})
    lam = beam_lambda_rad[:, cols].ravel()  # (S P,)
    o, d0 = beam_rays_W(params, lam, np.zeros_like(lam))
    _, d1 = beam_rays_W(params, lam, np.full_like(lam, 0.5 * math.pi))
    n = np.cross(d0, d1)  # the scan plane's normal at each sampled beam's motor angle
    side = (n @ centres_W.T - np.einsum("ij,ij->i", n, o)[:, None]).reshape(S, len(cols), -1)  # (S, P, m)
    far = np.linalg.norm(centres_W[None] - o[:, None], axis=-1).reshape(S, len(cols), -1)
    close = (np.abs(side) < reach_m + spread_rad * far).any(axis=1) | (np.ptp(np.sign(side), axis=1) > 0)
    hit = close.any(axis=1)
    near = hit.copy()
    near[1:] |= hit[:-1]
    near[:-1] |= hit[1:]
    return near


def rotvec(w: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) of the rotation vector w (3,) (Rodrigues)."""
    t = float(np.linalg.norm(w))
    if t < 1e-15:
        return np.eye(3)
    k = w / t
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(t) * K + (1 - math.cos(t)) * K @ K

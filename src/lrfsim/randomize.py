"""Seeded random scenarios for the parameter-recovery tests: DH sets, mount poses, marker layouts and noise levels
for a servo-turned UTM-30LX-EW.

* :func:`random_scenario`: the recovery suite's generator (tunnel, markers on walls, floor and ceiling, motor
  axis along the tunnel, alpha = -beta = +-90 deg);
* :func:`random_scenario_wide`: a broader one (V on one or both walls, scattered markers, a board; either sign
  of alpha and beta, beta 0 or +-90 deg; motor axis along, across or vertical; 1-4 passes), with
  :func:`wide_dh_determined` labelling whether a layout determines the four DH parameters.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from lrfcal.model.kinematics import Pose

from .scenario import Scenario, parse_scenario
from .servo import covered_angles_rad

if TYPE_CHECKING:
    from .simresult import SimResult


def random_scenario(seed: int, *, sweep_speed_deg_s: float = 20.0, passes: int = 1) -> Scenario:
    """A tunnel scenario with random truth, a perturbed nominal start, and markers scattered on the walls,
    floor and ceiling. Deterministic in ``seed``."""
    rng = np.random.default_rng(seed)
    width = rng.uniform(0.7, 1.2)
    height = rng.uniform(1.8, 2.6)
    plate_x = rng.uniform(1.8, 3.0)
    # The front beam (mu = 0) must look down the tunnel: its direction in M is
    # [cos beta, sin beta cos alpha, sin beta sin alpha] -> -z_M needs sign(alpha) = -sign(beta); the mount
    # turns -z_M to +x_W, so the scanner's 90 deg blind sector faces the robot, not the plate.
    sign_alpha = float(rng.choice([-1.0, 1.0]))
    sign_beta = -sign_alpha
    dh = {
        "a": rng.uniform(-0.02, 0.02),
        "alpha": sign_alpha * math.pi / 2 + math.radians(rng.uniform(-3, 3)),
        "b": rng.uniform(0.0, 0.04),
        "beta": sign_beta * math.pi / 2 + math.radians(rng.uniform(-3, 3)),
    }
    mount = {
        "x": rng.uniform(-0.1, 0.1),
        "y": rng.uniform(-0.1, 0.1) * width,
        "z": height * rng.uniform(0.4, 0.6),
        # about rpy (pi/2, 0, -pi/2): z_M along -x_W, away from the pitch = +-pi/2 gimbal lock of RPY
        "roll": math.pi / 2 + math.radians(rng.uniform(-8, 8)),
        "pitch": math.radians(rng.uniform(-8, 8)),
        "yaw": -math.pi / 2 + math.radians(rng.uniform(-8, 8)),
    }
    nominal_dh = {
        "a": dh["a"] + rng.uniform(-0.003, 0.003),
        "alpha": sign_alpha * math.pi / 2,
        "b": dh["b"] + rng.uniform(-0.003, 0.003),
        "beta": sign_beta * math.pi / 2,
    }
    nominal_mount = _perturbed_mount(rng, mount)
    radius = 0.005
    n_markers = int(rng.integers(10, 21))
    positions = _markers_on_walls(rng, n_markers, width, height, plate_x, radius)
    noise_bands = _random_noise_bands(rng)
    data = {
        "name": f"random_{seed}",
        "seed": seed,
        "rig": {"dh": dh, "mount": mount, "nominal_dh": nominal_dh, "nominal_mount": nominal_mount},
        "sensor": {"noise_bands": noise_bands},
        "servo": {"speed_rad_s": math.radians(sweep_speed_deg_s), "passes": passes},
        "scene": {"tunnel": {"width_m": width, "height_m": height, "plate_x_m": plate_x, "x_min_m": -1.0}},
        "markers": {"radius_m": radius, "layout": {"kind": "points", "positions": positions}},
    }
    return parse_scenario(_plain(data), f"random_scenario({seed})")


def _markers_on_walls(
    rng: np.random.Generator, n: int, width: float, height: float, plate_x: float, radius: float
) -> list[list[float]]:
    """n sphere centres one radius off the side walls, floor or ceiling, at least 10 cm apart."""
    out: list[np.ndarray] = []
    while len(out) < n:
        surface = rng.choice(["left", "right", "floor", "ceiling"], p=[0.35, 0.35, 0.15, 0.15])
        x = rng.uniform(0.3, plate_x - 0.2)
        if surface in ("left", "right"):
            y = (width / 2 - radius) * (1 if surface == "left" else -1)
            p = np.array([x, y, rng.uniform(0.2, height - 0.2)])
        else:
            z = radius if surface == "floor" else height - radius
            p = np.array([x, rng.uniform(-width / 2 + 0.1, width / 2 - 0.1), z])
        if all(np.linalg.norm(p - q) > 0.10 for q in out):
            out.append(p)
    return [[float(v) for v in p] for p in out]


def _plain(x: object) -> object:
    """numpy scalars -> Python floats, recursively (pydantic strict-ish validation and YAML dumps)."""
    if isinstance(x, dict):
        return {k: _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, np.generic):
        return x.item()
    return x


# --- the broad random-truth generator ---------------------------------------------------------------------------

#: layouts of :func:`random_scenario_wide`
WIDE_LAYOUTS = ("v_one_wall", "v_both_walls", "scattered", "board")
#: motor axis directions in W (the tunnel runs along x): along the tunnel, across it, vertical
WIDE_AXES = {"along": (1.0, 0.0, 0.0), "across": (0.0, 1.0, 0.0), "vertical": (0.0, 0.0, 1.0)}
#: nominal DH beta before its jitter: the front beam across the motor axis (0) or along it (+-90 deg)
WIDE_BETAS_DEG = (0.0, 90.0, -90.0)
#: margin inside the scanner's field of view and the sweep for a marker to count as visible
_VIS_MARGIN_RAD = math.radians(3.0)
#: half field of view of the UTM-30LX (270 deg)
_HALF_FOV_RAD = math.radians(135.0)


def random_scenario_wide(
    seed: int,
    *,
    layout: str | None = None,
    axis: str | None = None,
    beta_deg: float | None = None,
    passes: int | None = None,
) -> Scenario:
    """A broad random truth (deterministic in ``seed``; pass ``layout``/``axis``/``beta_deg``/``passes`` to fix
    one choice):

    * layout (WIDE_LAYOUTS): a V on one tunnel wall, a V on both walls, markers scattered on the walls, floor and
      ceiling, or a board beside the rig (no tunnel) extending ALONG the motor axis; 6-30 markers of radius
      5-10 mm;
    * DH: alpha = +-90 deg (either sign) and beta = 0 or +-90 deg, each +-3 deg; a in +-2 cm, |b| <= 4 cm with
      either sign. (alpha near 0 is not generated: the scan plane would be perpendicular to the motor axis,
      and turning it would not scan in 3D.);
    * motor axis (WIDE_AXES) along the tunnel, across it or vertical, either direction; the rotation about
      the axis is chosen (from 12, ties at random) so that the most markers are in view: outside the
      scanner's 90 deg blind sector, which sits around -+z_M when beta ~ +-90 deg; mount rotation jittered by
      up to 5 deg, position by a few cm;
    * 1-4 passes at 10-20 deg/s over +-90 deg; range noise sigma 5, 10 or 15 mm;
    * nominal start: a, b within 3 mm of the truth, alpha, beta within 3 deg, mount within 3 cm / 3 deg.

    Label the result with :func:`wide_dh_determined`; :func:`visible_markers` says which markers the sweep
    can see (geometry only).
    """
    rng = np.random.default_rng([seed, 0x77696465])  # "wide": a stream apart from random_scenario's
    layout = layout if layout is not None else str(rng.choice(WIDE_LAYOUTS))
    axis = axis if axis is not None else str(rng.choice(list(WIDE_AXES)))
    if layout not in WIDE_LAYOUTS or axis not in WIDE_AXES:
        raise ValueError(f"layout must be one of {WIDE_LAYOUTS}, axis one of {tuple(WIDE_AXES)}")
    sign_alpha = float(rng.choice([-1.0, 1.0]))
    beta0 = math.radians(beta_deg if beta_deg is not None else float(rng.choice(WIDE_BETAS_DEG)))
    dh = {
        "a": rng.uniform(-0.02, 0.02),
        "alpha": sign_alpha * math.pi / 2 + math.radians(rng.uniform(-3, 3)),
        "b": float(rng.choice([-1.0, 1.0])) * rng.uniform(0.0, 0.04),
        "beta": beta0 + math.radians(rng.uniform(-3, 3)),
    }
    radius = float(rng.uniform(0.005, 0.010))
    e_axis = np.array(WIDE_AXES[axis])
    scene: dict[str, object]
    markers: dict[str, object]
    if layout == "board":
        origin = np.array([0.0, 0.0, 1.0]) + rng.uniform(-0.05, 0.05, 3)
        scene, markers = _board_beside(rng, origin, e_axis, radius)
        positions = _board_centres(scene, markers, radius, seed)
    else:
        width, height, plate_x = rng.uniform(0.7, 1.2), rng.uniform(1.8, 2.6), rng.uniform(1.8, 3.0)
        origin = np.array([rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1) * width, height * rng.uniform(0.4, 0.6)])
        scene = {"tunnel": {"width_m": width, "height_m": height, "plate_x_m": plate_x, "x_min_m": -1.0}}
        if layout == "scattered":
            positions = _markers_on_walls(rng, int(rng.integers(6, 31)), width, height, plate_x, radius)
        else:
            walls = [str(rng.choice(["left", "right"]))] if layout == "v_one_wall" else ["left", "right"]
            per_arm = int(rng.integers(4, 16)) if len(walls) == 1 else int(rng.integers(2, 9))
            positions = _v_points(rng, walls, per_arm, width, height, plate_x, radius)
        markers = {"radius_m": radius, "layout": {"kind": "points", "positions": positions}}
    speed_deg_s = rng.uniform(10.0, 20.0)
    n_passes = passes if passes is not None else int(rng.integers(1, 5))
    servo = {"speed_rad_s": math.radians(speed_deg_s), "passes": n_passes}
    R = _best_mount_rotation(rng, np.asarray(positions, dtype=float), origin, e_axis, dh)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, origin
    mount = _pose_dict(T)
    nominal_dh = {k: v + (rng.uniform(-0.003, 0.003) if k in ("a", "b") else math.radians(rng.uniform(-3, 3)))
                  for k, v in dh.items()}
    nominal_mount = {k: (math.remainder(v, 2 * math.pi) if k not in "xyz" else v)
                     for k, v in _perturbed_mount(rng, mount).items()}
    nominal_mount["pitch"] = max(-math.pi / 2, min(math.pi / 2, nominal_mount["pitch"]))
    noise_bands = _random_noise_bands(rng)
    data = {
        "name": f"wide_{seed}_{layout}_{axis}_beta{round(math.degrees(beta0)):+d}",
        "seed": seed,
        "rig": {"dh": dh, "mount": mount, "nominal_dh": nominal_dh, "nominal_mount": nominal_mount},
        "sensor": {"noise_bands": noise_bands},
        "servo": servo,
        "scene": scene,
        "markers": markers,
    }
    return parse_scenario(_plain(data), f"random_scenario_wide({seed})")


def _v_points(rng: np.random.Generator, walls: list[str], per_arm: int, width: float, height: float,
              plate_x: float, radius: float) -> list[list[float]]:
    """A V per wall (two arms meeting at the lowest point, the apex shared): 2 per_arm - 1 markers per wall."""
    x0, x1 = rng.uniform(0.3, 0.6), rng.uniform(plate_x - 0.5, plate_x - 0.2)
    z_apex, z_top = rng.uniform(0.2, 0.7), rng.uniform(height - 0.6, height - 0.2)
    xa = 0.5 * (x0 + x1)
    arm1 = np.column_stack([np.linspace(x0, xa, per_arm), np.linspace(z_top, z_apex, per_arm)])
    arm2 = np.column_stack([np.linspace(xa, x1, per_arm), np.linspace(z_apex, z_top, per_arm)])[1:]
    xz = np.vstack([arm1, arm2])
    out = []
    for wall in walls:
        y = (width / 2 - radius) * (1 if wall == "left" else -1)
        out += [[float(x), float(y), float(z)] for x, z in xz]
    return out


def _perpendicular_basis(e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (3,) completing the unit vector e to a right-handed frame (p1, p2, e)."""
    helper = np.array([0.0, 0.0, 1.0]) if abs(e[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    p1 = np.cross(helper, e)
    p1 /= np.linalg.norm(p1)
    return p1, np.cross(e, p1)


def _board_beside(rng: np.random.Generator, origin: np.ndarray, e_axis: np.ndarray, radius: float
                  ) -> tuple[dict[str, object], dict[str, object]]:
    """A board beside the rig, its width along the motor axis (markers at many axial distances), facing the
    rig: centre 0.3-1.0 m along the axis and 0.5-1.2 m off it, in a random direction."""
    p1, p2 = _perpendicular_basis(e_axis)
    ang = rng.uniform(0, 2 * math.pi)
    n = math.cos(ang) * p1 + math.sin(ang) * p2  # from the axis towards the board
    width, height = rng.uniform(0.9, 1.5), rng.uniform(0.6, 1.0)
    centre = origin + rng.uniform(0.5, 1.2) * n + rng.uniform(0.3, 1.0) * float(rng.choice([-1, 1])) * e_axis
    ex, ez = e_axis, -n  # board width along the axis, front face (local +z) towards the rig
    R = np.column_stack([ex, np.cross(ez, ex), ez])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, centre
    cols = int(rng.integers(3, 7))
    rows = int(rng.integers(max(2, -(-6 // cols)), min(5, 30 // cols) + 1))
    spacing = min(0.2, (width - 0.1) / (cols - 1), (height - 0.1) / max(rows - 1, 1))
    scene = {"board": {"pose": _pose_dict(T), "width_m": width, "height_m": height,
                       "thickness_m": 0.01}}
    markers = {"radius_m": radius, "layout": {"kind": "board", "rows": rows, "cols": cols, "spacing_m": spacing,
                                              "jitter_m": min(0.02, spacing / 4)}}
    return scene, markers


def _board_centres(scene: dict[str, object], markers: dict[str, object], radius: float, seed: int) -> np.ndarray:
    """The marker centres (n, 3) the simulator will put on that board."""
    from .scenario_sections import BoardConfig, BoardLayout
    from .scene_geometry import board_markers

    return board_markers(BoardLayout.model_validate(markers["layout"]),
                          BoardConfig.model_validate(_plain(scene["board"])), radius, seed)


def _visible_in_M(u_M: np.ndarray, alpha: float, beta: float, lam_lo: float, lam_hi: float,
                  margin: float = _VIS_MARGIN_RAD) -> np.ndarray:
    """(k,) bool: is direction u_M (k, 3) (from the optical centre, taken at the origin of M) on some beam within
    the field of view (|mu| <= 135 deg - margin) at some motor angle in [lam_lo + margin, lam_hi - margin]?
    The scan plane at lambda is Rz(lambda) span{x, (0, cos alpha, sin alpha)} (eq. 3 with a = b = 0)."""
    u = u_M / np.linalg.norm(u_M, axis=1, keepdims=True)
    theta, rho = np.arctan2(u[:, 1], u[:, 0]), np.hypot(u[:, 0], u[:, 1])
    sa, ca = math.sin(alpha), math.cos(alpha)
    with np.errstate(divide="ignore", invalid="ignore"):
        q = -ca * u[:, 2] / (rho * sa)
    ok_q = np.abs(q) <= 1
    asq = np.arcsin(np.clip(q, -1, 1))
    seen = np.zeros(len(u), dtype=bool)
    for lam in (theta + asq, theta + math.pi - asq):
        for shift in (-2 * math.pi, 0.0, 2 * math.pi):
            lk = lam + shift
            in_sweep = (lk >= lam_lo + margin) & (lk <= lam_hi - margin)
            c, s = np.cos(lk), np.sin(lk)
            w = np.column_stack([c * u[:, 0] + s * u[:, 1], -s * u[:, 0] + c * u[:, 1], u[:, 2]])
            phi = np.arctan2(w[:, 1] * ca + w[:, 2] * sa, w[:, 0])
            mu = np.remainder(phi - beta + math.pi, 2 * math.pi) - math.pi
            seen |= ok_q & in_sweep & (np.abs(mu) <= _HALF_FOV_RAD - margin)
    return seen


def _best_mount_rotation(rng: np.random.Generator, positions: np.ndarray, origin: np.ndarray, e_axis: np.ndarray,
                         dh: dict[str, float], n_roll: int = 12) -> np.ndarray:
    """R_W_M (3, 3) with z_M = +-e_axis (jittered up to 5 deg) that sees the most markers over the default
    +-90 deg sweep; ties broken at random."""
    jitter = _rotvec(rng.normal(size=3) * math.radians(5.0) / math.sqrt(3))
    best: list[np.ndarray] = []
    best_n = -1
    for sign in (1.0, -1.0):
        z = sign * e_axis
        p1, p2 = _perpendicular_basis(z)
        for k in range(n_roll):
            psi = 2 * math.pi * k / n_roll
            x = math.cos(psi) * p1 + math.sin(psi) * p2
            R = jitter @ np.column_stack([x, np.cross(z, x), z])
            u_M = (positions - origin) @ R  # R^T (p - o) row-wise
            n = int(_visible_in_M(u_M, dh["alpha"], dh["beta"], -math.pi / 2, math.pi / 2).sum())
            if n > best_n:
                best, best_n = [R], n
            elif n == best_n:
                best.append(R)
    return best[int(rng.integers(len(best)))]


def _pose_dict(T: np.ndarray) -> dict[str, float]:
    """x, y, z, roll, pitch, yaw of T (4, 4), also at the pitch = +-90 deg gimbal lock (then roll absorbs yaw)."""
    pose = Pose.from_matrix(T).as_dict()
    R = T[:3, :3]
    if abs(R[2, 0]) > 1 - 1e-9:
        s = -float(np.sign(R[2, 0]))  # sin(pitch)
        pose.update(pitch=s * math.pi / 2, yaw=0.0, roll=math.atan2(s * R[0, 1], s * R[0, 2]))
    assert np.allclose(Pose(**pose).matrix(), T, atol=1e-9), "rpy conversion"
    return pose


def _rotvec(w: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) of the rotation vector w (3,) (Rodrigues)."""
    t = float(np.linalg.norm(w))
    if t < 1e-15:
        return np.eye(3)
    k = w / t
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(t) * K + (1 - math.cos(t)) * K @ K


def _perturbed_mount(rng: np.random.Generator, mount: dict[str, float]) -> dict[str, float]:
    """A tape-measured nominal mount: the true one off by up to 3 cm and 3 deg per component."""
    return {k: v + (rng.uniform(-0.03, 0.03) if k in "xyz" else math.radians(rng.uniform(-3, 3)))
            for k, v in mount.items()}


def _random_noise_bands(rng: np.random.Generator) -> list[dict[str, float]]:
    """Range noise of 5, 10 or 15 mm to 10 m (three times that beyond), as scenario noise_bands."""
    sigma = float(rng.choice([0.005, 0.010, 0.015]))
    return [{"up_to_m": 10.0, "sigma_m": sigma}, {"up_to_m": 60.0, "sigma_m": 3 * sigma}]


def detected_markers(result: SimResult, scenario: Scenario) -> set[int]:
    """Indices of the markers on which the calibration's detection (lrfcal.detection.detect) finds a blob in a
    simulated recording; each blob's owner comes from the truth (lrfsim.faults.marker_returns)."""
    from lrfcal.detection import detect
    from lrfcal.types import Scans

    from .faults import marker_returns

    s = scenario.sensor
    det = detect(Scans(result.scan_stamps_s, result.ranges_m, result.intensities, result.mu_rad,
                       s.time_increment_s, s.scan_period_s, s.range_min_m, s.range_max_m))
    owner = marker_returns(result, scenario)
    return {int(m) for b in det.blobs for m in owner[b.scan_idx, b.beam_idx] if m >= 0}


def visible_markers(scenario: Scenario) -> np.ndarray:
    """(n,) bool: the markers the sweep can see (within the field of view at some motor angle of the sweep,
    3 deg margin; geometry only: no occlusion, range or intensity model)."""
    from .scene_geometry import marker_centres_W

    C = marker_centres_W(scenario)
    T = scenario.rig.mount.to_pose().matrix()
    dh = scenario.rig.dh
    u_M = (C - T[:3, 3]) @ T[:3, :3]
    lo, hi = _motor_range_rad(scenario)
    return _visible_in_M(u_M, dh.alpha, dh.beta, lo, hi)


def _motor_range_rad(scenario: Scenario) -> tuple[float, float]:
    """The motor angles the servo covers (lrfsim.servo.covered_angles_rad) as the visibility tests take them
    (their candidate angles lie within [-7 pi / 2, 9 pi / 2]): a sweep's as they are; a spin's moved by whole
    turns to start in [-pi, pi); a spin that turns a full circle beyond the margins: (-pi, pi) widened by the
    margin, the whole circle."""
    lo, hi = covered_angles_rad(scenario.servo)
    if scenario.servo.mode == "sweep":
        return lo, hi
    if hi - lo >= 2 * math.pi + 2 * _VIS_MARGIN_RAD:
        return -math.pi - _VIS_MARGIN_RAD, math.pi + _VIS_MARGIN_RAD
    shift = 2 * math.pi * math.floor((lo + math.pi) / (2 * math.pi))
    return lo - shift, hi - shift


def _beam_through(u_M: np.ndarray, alpha: float, beta: float, lam_lo: float, lam_hi: float
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For directions u_M (k, 3): (visible (k,), lambda (k,), mu (k,)) of one beam through each (a = b = 0),
    the first solution found; NaN where not visible."""
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
            ok = (np.abs(q) <= 1) & (lk >= lam_lo + _VIS_MARGIN_RAD) & (lk <= lam_hi - _VIS_MARGIN_RAD)
            ok &= (np.abs(mu) <= _HALF_FOV_RAD - _VIS_MARGIN_RAD) & np.isnan(lam_out)
            lam_out[ok], mu_out[ok] = lk[ok], mu[ok]
    return ~np.isnan(lam_out), lam_out, mu_out


def wide_dh_sigma(scenario: Scenario, sigma_m: float | None = None) -> np.ndarray:
    """(4,) 1-sigma of (a, alpha, b, beta) [m, rad, m, rad] that the layout allows in the paper's point model:
    one return per visible marker and pass at the beam through its centre, a 3D point residual with isotropic
    noise ``sigma_m`` (default: the first range noise band's), the mount (position and a local rotation vector,
    free of Euler singularities) estimated jointly. inf when the 10 parameters are not determined."""
    from lrfcal.model.kinematics import DH, points_M

    from .scene_geometry import marker_centres_W

    sigma = sigma_m if sigma_m is not None else scenario.sensor.noise_bands[0].sigma_m
    C = marker_centres_W(scenario)
    T = scenario.rig.mount.to_pose().matrix()
    R0, t0 = T[:3, :3], T[:3, 3]
    dh0 = scenario.rig.dh
    lo, hi = _motor_range_rad(scenario)
    vis, lam, mu = _beam_through((C - t0) @ R0, dh0.alpha, dh0.beta, lo, hi)
    if vis.sum() < 4:
        return np.full(4, np.inf)
    C, lam, mu = C[vis], lam[vis], mu[vis]
    r = np.linalg.norm(C - t0, axis=1)
    x0 = np.array([dh0.a, dh0.alpha, dh0.b, dh0.beta])

    def model(v: np.ndarray) -> np.ndarray:
        p_M = points_M(r, lam, mu, DH(*map(float, v[:4])))
        return (p_M @ (R0 @ _rotvec(v[7:10])).T + t0 + v[4:7]).ravel()

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
    looks = servo.passes if servo.mode == "sweep" else max(1.0, servo.revolutions)
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
    from .scene_geometry import marker_centres_W

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

"""Seeded random scenarios for the parameter-recovery tests: DH sets, mount poses, marker layouts and noise levels
for a servo-turned UTM-30LX-EW.

* :func:`random_scenario`: the recovery suite's generator (tunnel, markers on walls, floor and ceiling, motor
  axis along the tunnel, alpha = -beta = +-90 deg);
* :func:`random_scenario_wide`: a broader one (V on one or both walls, scattered markers, a board
  (:mod:`lrfsim.testing.boards`: beside the rig, or, named, the one the motor axis points at); either sign
  of alpha and beta, beta 0 or +-90 deg; motor axis along, across or vertical; 1-4 passes; with ``alpha_kind``
  or ``broad=True`` also scan planes tilted 20-70 deg or near perpendicular to the motor axis, markers placed on
  their beams), with :func:`wide_dh_determined` (lrfsim.world.visibility, re-exported here) labelling whether a
  layout determines the four DH parameters and :func:`alpha_kind_of` naming the scan plane's attitude;
* :func:`detected_markers`: the markers the calibration's detection finds in a simulated recording (whether the
  markers the labels count as visible are seen).

Only the tests and the benchmarks use this module (no command does): it is in lrfsim's ``testing`` room, not under
tests/, so that the benchmarks import it as the tests do; it sits above the simulation (it reads a simulated
result) and nothing in lrfsim imports it.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from lrfsim.scenario.file import Scenario, parse_scenario
from lrfsim.testing.boards import board_beside, board_on_axis, perpendicular_basis, pose_dict
from lrfsim.world.visibility import (
    HALF_FOV_RAD,
    VIS_MARGIN_RAD,
    WIDE_MIN_AXIAL_SPREAD_M,
    WIDE_SIGMA_LIMITS,
    axial_spread_m,
    motor_range_rad,
    rotvec,
    visible_in_M,
    visible_markers,
    wide_dh_determined,
    wide_dh_sigma,
)

if TYPE_CHECKING:
    from lrfsim.simulation.result import SimResult


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
#: layouts it makes only when named (``layout=``), never drawn: the board the motor axis points at
#: (lrfsim.testing.boards.board_on_axis), added after WIDE_LAYOUTS' seeds were in use
NAMED_LAYOUTS = ("board_on_axis",)
#: motor axis directions in W (the tunnel runs along x): along the tunnel, across it, vertical
WIDE_AXES = {"along": (1.0, 0.0, 0.0), "across": (0.0, 1.0, 0.0), "vertical": (0.0, 0.0, 1.0)}
#: nominal DH beta before its jitter: the front beam across the motor axis (0) or along it (+-90 deg)
WIDE_BETAS_DEG = (0.0, 90.0, -90.0)


#: scan-plane attitudes of :func:`random_scenario_wide` (``alpha_kind``), by the plane's angle from perpendicular to
#: the motor axis: along it (|alpha| = 90 +- 3 deg), tilted (|alpha| 20-70 deg) and near perpendicular (|alpha|
#: 0-15 deg, where b and the mount's offset along the motor axis become one quantity)
ALPHA_KINDS = ("axis", "tilted", "near_perpendicular")
#: |alpha| ranges [deg] of the tilted and near-perpendicular kinds (either sign is drawn)
ALPHA_RANGES_DEG = {"tilted": (20.0, 70.0), "near_perpendicular": (0.0, 15.0)}


def broad_alpha_kind(seed: int) -> str:
    """The attitude ``random_scenario_wide(seed, broad=True)`` draws: ALPHA_KINDS in turn by seed (a third each
    over consecutive seeds)."""
    return ALPHA_KINDS[seed % len(ALPHA_KINDS)]


def alpha_kind_of(scenario: Scenario) -> str:
    """The ALPHA_KINDS entry of a scenario's true alpha: near_perpendicular within 15 deg of perpendicular to the
    motor axis, axis within 15 deg of along it, tilted between."""
    tilt = math.degrees(math.asin(min(1.0, abs(math.sin(scenario.rig.dh.alpha)))))
    return "near_perpendicular" if tilt < 15.0 else "axis" if tilt > 75.0 else "tilted"


def random_scenario_wide(
    seed: int,
    *,
    layout: str | None = None,
    axis: str | None = None,
    beta_deg: float | None = None,
    passes: int | None = None,
    alpha_kind: str | None = None,
    broad: bool = False,
) -> Scenario:
    """A broad random truth (deterministic in ``seed``; pass ``layout``/``axis``/``beta_deg``/``passes`` to fix
    one choice; ``alpha_kind`` (ALPHA_KINDS) the scan plane's attitude, default "axis", or ``broad=True`` to take
    it from the seed, :func:`broad_alpha_kind`):

    * layout (WIDE_LAYOUTS): a V on one tunnel wall, a V on both walls, markers scattered on the walls, floor and
      ceiling, or a board beside the rig (no tunnel) extending ALONG the motor axis; 6-30 markers of radius
      5-10 mm. That board leaves b undetermined (every marker at about one distance from the motor axis, b one
      with the mount's turn about it: lrfsim.testing.boards); ``layout="board_on_axis"`` (NAMED_LAYOUTS, only when
      named) is a board the motor axis points at, turned 40-65 deg from across it, which determines b;
    * DH: alpha = +-90 deg (either sign) and beta = 0 or +-90 deg, each +-3 deg; a in +-2 cm, |b| <= 4 cm with
      either sign;
    * motor axis (WIDE_AXES) along the tunnel, across it or vertical, either direction; the rotation about
      the axis is chosen (from 12, ties at random) so that the most markers are in view: outside the
      scanner's 90 deg blind sector, which sits around -+z_M when beta ~ +-90 deg; mount rotation jittered by
      up to 5 deg, position by a few cm;
    * 1-4 passes at 10-20 deg/s over +-90 deg; range noise sigma 5, 10 or 15 mm;
    * nominal start: a, b within 3 mm of the truth, alpha, beta within 3 deg, mount within 3 cm / 3 deg.

    alpha_kind "tilted" or "near_perpendicular" (a stream of draws of their own): |alpha| in ALPHA_RANGES_DEG
    instead, markers "scattered" (the only layout) where the true beams meet the tunnel (:func:`_markers_on_beams`),
    the rotation about the motor axis at random; a near-perpendicular plane spins (servo.mode spin, 1-2 turns at
    0.6-1.2 rad/s, either way), a tilted one sweeps as above or spins, at random. Defaults draw as before.

    Label the result with :func:`wide_dh_determined` and :func:`alpha_kind_of`; :func:`visible_markers` says
    which markers the sweep can see (geometry only).
    """
    kind = alpha_kind if alpha_kind is not None else broad_alpha_kind(seed) if broad else "axis"
    if kind not in ALPHA_KINDS:
        raise ValueError(f"alpha_kind must be one of {ALPHA_KINDS}")
    if kind != "axis":
        return _random_scenario_tilted(seed, kind, layout=layout, axis=axis, beta_deg=beta_deg, passes=passes)
    rng = np.random.default_rng([seed, 0x77696465])  # "wide": a stream apart from random_scenario's
    layout = layout if layout is not None else str(rng.choice(WIDE_LAYOUTS))
    axis = axis if axis is not None else str(rng.choice(list(WIDE_AXES)))
    if layout not in WIDE_LAYOUTS + NAMED_LAYOUTS or axis not in WIDE_AXES:
        raise ValueError(f"layout must be one of {WIDE_LAYOUTS + NAMED_LAYOUTS}, axis one of {tuple(WIDE_AXES)}")
    dh, beta0 = _wide_dh(rng, kind, beta_deg)
    radius = float(rng.uniform(0.005, 0.010))
    e_axis = np.array(WIDE_AXES[axis])
    scene: dict[str, object]
    markers: dict[str, object]
    if layout in ("board", "board_on_axis"):
        origin = np.array([0.0, 0.0, 1.0]) + rng.uniform(-0.05, 0.05, 3)
        scene, markers = (board_beside if layout == "board" else board_on_axis)(rng, origin, e_axis, radius)
        positions = _board_centres(scene, markers, radius, seed)
    else:
        scene, origin = _tunnel_and_origin(rng)
        width, height, plate_x = (scene["tunnel"][k] for k in ("width_m", "height_m", "plate_x_m"))
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
    name = f"wide_{seed}_{layout}_{axis}_beta{round(math.degrees(beta0)):+d}"
    return _wide_scenario(rng, seed, name, dh, R, origin, {"servo": servo, "scene": scene, "markers": markers})


def _wide_dh(rng: np.random.Generator, kind: str, beta_deg: float | None) -> tuple[dict[str, float], float]:
    """The true DH set of an ALPHA_KINDS attitude (the sign of alpha, then beta's nominal, a, alpha, b, beta's
    jitter drawn in that order) and beta's nominal [rad]."""
    sign_alpha = float(rng.choice([-1.0, 1.0]))
    beta0 = math.radians(beta_deg if beta_deg is not None else float(rng.choice(WIDE_BETAS_DEG)))
    a = rng.uniform(-0.02, 0.02)
    if kind == "axis":
        alpha = sign_alpha * math.pi / 2 + math.radians(rng.uniform(-3, 3))
    else:
        alpha = sign_alpha * math.radians(rng.uniform(*ALPHA_RANGES_DEG[kind]))
    dh = {"a": a, "alpha": alpha, "b": float(rng.choice([-1.0, 1.0])) * rng.uniform(0.0, 0.04),
          "beta": beta0 + math.radians(rng.uniform(-3, 3))}
    return dh, beta0


def _tunnel_and_origin(rng: np.random.Generator) -> tuple[dict[str, dict[str, float]], np.ndarray]:
    """A random tunnel (scene section) and the rig's position in it (3,)."""
    width, height, plate_x = rng.uniform(0.7, 1.2), rng.uniform(1.8, 2.6), rng.uniform(1.8, 3.0)
    origin = np.array([rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1) * width, height * rng.uniform(0.4, 0.6)])
    return {"tunnel": {"width_m": width, "height_m": height, "plate_x_m": plate_x, "x_min_m": -1.0}}, origin


def _wide_scenario(rng: np.random.Generator, seed: int, name: str, dh: dict[str, float], R: np.ndarray,
                   origin: np.ndarray, sections: dict[str, object]) -> Scenario:
    """The scenario of a drawn truth (mount rotation R (3, 3) at origin (3,); the servo, scene and markers
    sections), with its nominal start and range noise drawn last."""
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, origin
    mount = pose_dict(T)
    nominal_dh = {k: v + (rng.uniform(-0.003, 0.003) if k in ("a", "b") else math.radians(rng.uniform(-3, 3)))
                  for k, v in dh.items()}
    nominal_mount = {k: (math.remainder(v, 2 * math.pi) if k not in "xyz" else v)
                     for k, v in _perturbed_mount(rng, mount).items()}
    nominal_mount["pitch"] = max(-math.pi / 2, min(math.pi / 2, nominal_mount["pitch"]))
    noise_bands = _random_noise_bands(rng)
    data = {
        "name": name,
        "seed": seed,
        "rig": {"dh": dh, "mount": mount, "nominal_dh": nominal_dh, "nominal_mount": nominal_mount},
        "sensor": {"noise_bands": noise_bands},
        "servo": sections["servo"],
        "scene": sections["scene"],
        "markers": sections["markers"],
    }
    return parse_scenario(_plain(data), f"random_scenario_wide({seed})")


def _random_scenario_tilted(seed: int, kind: str, *, layout: str | None, axis: str | None,
                            beta_deg: float | None, passes: int | None) -> Scenario:
    """random_scenario_wide for a tilted or near-perpendicular scan plane (its docstring)."""
    if layout not in (None, "scattered"):
        raise ValueError(f"layout must be 'scattered' with alpha_kind {kind!r} (markers where the beams meet the "
                         "tunnel)")
    rng = np.random.default_rng([seed, 0x77696465, ALPHA_KINDS.index(kind)])
    axis = axis if axis is not None else str(rng.choice(list(WIDE_AXES)))
    if axis not in WIDE_AXES:
        raise ValueError(f"axis must be one of {tuple(WIDE_AXES)}")
    dh, beta0 = _wide_dh(rng, kind, beta_deg)
    radius = float(rng.uniform(0.005, 0.010))
    scene, origin = _tunnel_and_origin(rng)
    servo: dict[str, object]
    if kind == "near_perpendicular" or rng.random() < 0.5:
        servo = {"mode": "spin", "start_rad": rng.uniform(-math.pi, math.pi), "revolutions": rng.uniform(1.0, 2.0),
                 "spin_direction": int(rng.choice([1, -1])), "speed_rad_s": rng.uniform(0.6, 1.2)}
    else:
        servo = {"speed_rad_s": math.radians(rng.uniform(10.0, 20.0)),
                 "passes": passes if passes is not None else int(rng.integers(1, 5))}
    R = _axis_frame(float(rng.choice([-1.0, 1.0])) * np.array(WIDE_AXES[axis]), rng.uniform(0, 2 * math.pi))
    R = rotvec(rng.normal(size=3) * math.radians(5.0) / math.sqrt(3)) @ R
    positions = _markers_on_beams(rng, int(rng.integers(6, 31)), scene["tunnel"], R, origin, dh, servo, radius)
    markers = {"radius_m": radius, "layout": {"kind": "points", "positions": positions}}
    name = (f"wide_{seed}_scattered_{axis}_beta{round(math.degrees(beta0)):+d}_{kind}_"
            f"{servo.get('mode', 'sweep')}")
    return _wide_scenario(rng, seed, name, dh, R, origin, {"servo": servo, "scene": scene, "markers": markers})


def _markers_on_beams(rng: np.random.Generator, n: int, tunnel: dict[str, float], R: np.ndarray,
                      origin: np.ndarray, dh: dict[str, float], servo: dict[str, object], radius: float
                      ) -> list[list[float]]:
    """Up to n sphere centres, each on a true beam (eq. 3 with the true DH; motor angle and bearing drawn within
    the sweep or spin and the field of view, 3 deg margins) and touching the tunnel surface that beam meets (a
    wall, the floor, the ceiling or the plate; not the open end behind the rig), at incidence within 70 deg of
    its normal, 0.3 m or more from the optical centre, 10 cm or more apart, and visible to the labels' geometry
    (:func:`lrfsim.world.visibility.visible_markers`). Fewer when 40 batches of 512 beams find no more room."""
    from lrfcal.model.kinematics import DH, beam_rays_M
    from lrfsim.scenario.sections import ServoConfig

    lo, hi = motor_range_rad(ServoConfig.model_validate(_plain(servo)))
    box_lo = np.array([tunnel["x_min_m"], -tunnel["width_m"] / 2, 0.0])
    box_hi = np.array([tunnel["plate_x_m"], tunnel["width_m"] / 2, tunnel["height_m"]])
    axial = np.array([0.0, 0.0, dh["b"] * math.cos(dh["alpha"])])  # the optical centre on the motor axis
    out: list[np.ndarray] = []
    for _ in range(40):
        lam = rng.uniform(lo + VIS_MARGIN_RAD, hi - VIS_MARGIN_RAD, 512)
        mu = rng.uniform(-1.0, 1.0, 512) * (HALF_FOV_RAD - VIS_MARGIN_RAD)
        o_M, d_M = beam_rays_M(lam, mu, DH(**dh))
        o, d = o_M @ R.T + origin, d_M @ R.T
        with np.errstate(divide="ignore", invalid="ignore"):
            t_face = np.where(d > 0, (box_hi - o) / d, (box_lo - o) / d)  # along the beam to each bounding plane
        t_face[~np.isfinite(t_face)] = np.inf
        face = np.argmin(t_face, axis=1)
        rows = np.arange(len(lam))
        cos_i = np.maximum(np.abs(d[rows, face]), 1e-9)
        t_c = t_face[rows, face] - radius / cos_i  # the centre one radius off that surface
        centres = o + t_c[:, None] * d
        ok = ~((face == 0) & (d[:, 0] < 0)) & (cos_i >= math.cos(math.radians(70.0))) & (t_c >= 0.3)
        ok &= np.all((centres >= box_lo + radius - 1e-9) & (centres <= box_hi - radius + 1e-9), axis=1)
        ok &= visible_in_M((centres - origin) @ R - axial, dh["alpha"], dh["beta"], lo, hi)
        for c in centres[ok]:
            if all(np.linalg.norm(c - q) > 0.10 for q in out):
                out.append(c)
            if len(out) == n:
                return [[float(v) for v in p] for p in out]
    return [[float(v) for v in p] for p in out]


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


def _axis_frame(z: np.ndarray, psi: float) -> np.ndarray:
    """The rotation (3, 3) with z axis z (unit) and x axis at angle psi from perpendicular_basis(z)'s first."""
    p1, p2 = perpendicular_basis(z)
    x = math.cos(psi) * p1 + math.sin(psi) * p2
    return np.column_stack([x, np.cross(z, x), z])


def _board_centres(scene: dict[str, object], markers: dict[str, object], radius: float, seed: int) -> np.ndarray:
    """The marker centres (n, 3) the simulator will put on that board."""
    from lrfsim.scenario.scene_sections import BoardConfig
    from lrfsim.scenario.sections import BoardLayout
    from lrfsim.world.geometry import board_markers

    return board_markers(BoardLayout.model_validate(markers["layout"]),
                          BoardConfig.model_validate(_plain(scene["board"])), radius, seed)


def _best_mount_rotation(rng: np.random.Generator, positions: np.ndarray, origin: np.ndarray, e_axis: np.ndarray,
                         dh: dict[str, float], n_roll: int = 12) -> np.ndarray:
    """R_W_M (3, 3) with z_M = +-e_axis (jittered up to 5 deg) that sees the most markers over the default
    +-90 deg sweep; ties broken at random."""
    jitter = rotvec(rng.normal(size=3) * math.radians(5.0) / math.sqrt(3))
    best: list[np.ndarray] = []
    best_n = -1
    for sign in (1.0, -1.0):
        z = sign * e_axis
        for k in range(n_roll):
            R = jitter @ _axis_frame(z, 2 * math.pi * k / n_roll)
            u_M = (positions - origin) @ R  # R^T (p - o) row-wise
            n = int(visible_in_M(u_M, dh["alpha"], dh["beta"], -math.pi / 2, math.pi / 2).sum())
            if n > best_n:
                best, best_n = [R], n
            elif n == best_n:
                best.append(R)
    return best[int(rng.integers(len(best)))]


def _perturbed_mount(rng: np.random.Generator, mount: dict[str, float]) -> dict[str, float]:
    """A tape-measured nominal mount: the true one off by up to 3 cm and 3 deg per component."""
    return {k: v + (rng.uniform(-0.03, 0.03) if k in "xyz" else math.radians(rng.uniform(-3, 3)))
            for k, v in mount.items()}


def _random_noise_bands(rng: np.random.Generator) -> list[dict[str, float]]:
    """Range noise of 5, 10 or 15 mm to 10 m (three times that beyond), as scenario noise_bands."""
    sigma = float(rng.choice([0.005, 0.010, 0.015]))
    return [{"up_to_m": 10.0, "sigma_m": sigma}, {"up_to_m": 60.0, "sigma_m": 3 * sigma}]


def detected_markers(result: SimResult, scenario: Scenario) -> set[int]:
    """Indices of the markers on which the calibration's detection (lrfcal.stages.detection.detect) finds a blob in a
    simulated recording; each blob's owner comes from the truth (lrfsim.simulation.faults.marker_returns): whether the
    markers the labels count as visible are seen."""
    from lrfsim.simulation.faults import detected_mask, marker_returns

    owner = marker_returns(result, scenario, among=detected_mask(result, scenario))
    return {int(m) for m in np.unique(owner[owner >= 0])}


__all__ = ["ALPHA_KINDS", "ALPHA_RANGES_DEG", "NAMED_LAYOUTS", "WIDE_AXES", "WIDE_BETAS_DEG", "WIDE_LAYOUTS",
           "WIDE_MIN_AXIAL_SPREAD_M", "WIDE_SIGMA_LIMITS", "alpha_kind_of", "axial_spread_m", "broad_alpha_kind",
           "detected_markers", "random_scenario", "random_scenario_wide", "visible_markers", "wide_dh_determined",
           "wide_dh_sigma"]

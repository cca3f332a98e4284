"""Seeded random scenarios for the parameter-recovery test suite: DH sets, mount poses, marker layouts and
noise levels across realistic ranges for a servo-turned UTM-30LX-EW in a box-girder tunnel."""

from __future__ import annotations

import math

import numpy as np

from .scenario import Scenario, parse_scenario


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
    nominal_mount = {
        k: v + (rng.uniform(-0.03, 0.03) if k in "xyz" else math.radians(rng.uniform(-3, 3)))
        for k, v in mount.items()
    }
    radius = 0.005
    n_markers = int(rng.integers(10, 21))
    positions = _markers_on_walls(rng, n_markers, width, height, plate_x, radius)
    sigma = float(rng.choice([0.005, 0.010, 0.015]))
    data = {
        "name": f"random_{seed}",
        "seed": seed,
        "rig": {"dh": dh, "mount": mount, "nominal_dh": nominal_dh, "nominal_mount": nominal_mount},
        "sensor": {
            "noise_bands": [{"up_to_m": 10.0, "sigma_m": sigma}, {"up_to_m": 60.0, "sigma_m": 3 * sigma}]
        },
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

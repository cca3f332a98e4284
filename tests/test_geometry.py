"""Stage 8: RANSAC planes and tunnel dimensions on synthetic clouds."""

from __future__ import annotations

import numpy as np
import pytest

from lrfcal.model.kinematics import rpy_matrix
from lrfcal.stages.geometry import extract_planes, fit_plane_lsq, tunnel_geometry

WIDTH, HEIGHT, PLATE = 0.78, 2.30, 2.24
MANHOLE_R = 0.30


def tunnel_cloud(n=200_000, noise_m=0.010, seed=0, rpy=(0.3, -0.2, 0.7), offset=(0.05, -0.12, 0.9),
                 back_wall=True, clutter=0.05):
    """Points on a tunnel (frame T: x along the axis, y left, z up, floor z=0, walls y=+-W/2) expressed in M.

    The sensor (origin of M) sits at T-position ``offset``; the plate is PLATE ahead of it along x with a round
    manhole opening; range noise is along the line of sight. Returns (points_M (n, 3), axis_M (3,)).
    """
    rng = np.random.default_rng(seed)
    o = np.asarray(offset)
    x0, x1 = o[0] - 4.0, o[0] + PLATE
    areas = {"walls": 2 * HEIGHT * (x1 - x0), "fc": 2 * WIDTH * (x1 - x0), "plate": WIDTH * HEIGHT}
    if back_wall:
        areas["back"] = WIDTH * HEIGHT
    tot = sum(areas.values())
    n_clutter = int(clutter * n)
    parts = []
    for name, a in areas.items():
        k = int((n - n_clutter) * a / tot)
        if name == "walls":
            p = np.c_[rng.uniform(x0, x1, k), rng.choice([-WIDTH / 2, WIDTH / 2], k), rng.uniform(0, HEIGHT, k)]
        elif name == "fc":
            p = np.c_[rng.uniform(x0, x1, k), rng.uniform(-WIDTH / 2, WIDTH / 2, k), rng.choice([0, HEIGHT], k)]
        else:
            p = np.c_[np.full(k, x1 if name == "plate" else x0), rng.uniform(-WIDTH / 2, WIDTH / 2, k),
                      rng.uniform(0, HEIGHT, k)]
            if name == "plate":  # manhole: no plate there; see a far wall through it instead
                hole = np.hypot(p[:, 1], p[:, 2] - 1.0) < MANHOLE_R
                p[hole, 0] += rng.uniform(1.0, 3.0, hole.sum())
        parts.append(p)
    # clutter: a robot body near the sensor and scattered stray returns
    parts.append(o + rng.uniform(-0.25, 0.25, (n_clutter // 2, 3)) - [0.4, 0, 0.3])
    parts.append(np.c_[rng.uniform(x0, x1, n_clutter - n_clutter // 2),
                       rng.uniform(-WIDTH / 2, WIDTH / 2, n_clutter - n_clutter // 2),
                       rng.uniform(0, HEIGHT, n_clutter - n_clutter // 2)])
    p_T = np.vstack(parts)
    ray = p_T - o
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    p_T = p_T + ray * rng.normal(0, noise_m, (len(p_T), 1))
    R = rpy_matrix(*rpy)  # T_M_T rotation: M = R^T (T - o)
    p_M = (p_T - o) @ R
    return p_M, R.T @ np.array([1.0, 0, 0])


def test_fit_plane_lsq():
    rng = np.random.default_rng(1)
    n = np.array([0.2, -0.3, 0.9])
    n /= np.linalg.norm(n)
    u = np.cross(n, [1, 0, 0])
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    p = -1.5 * n + rng.normal(size=(500, 1)) * u + rng.normal(size=(500, 1)) * v
    m, d = fit_plane_lsq(p)
    assert d == pytest.approx(1.5)
    np.testing.assert_allclose(m, -n, atol=1e-9)


def test_tunnel_dimensions_within_1mm():
    pts, axis = tunnel_cloud()
    g = tunnel_geometry(pts, axis_hint_M=axis)
    assert g.width_m == pytest.approx(WIDTH, abs=1e-3)
    assert g.height_m == pytest.approx(HEIGHT, abs=1e-3)
    assert g.plate_distance_m == pytest.approx(PLATE, abs=1e-3)
    labels = sorted(p.label for p in g.planes if p.label != "other")
    assert labels == ["floor/ceiling", "floor/ceiling", "plate", "wall", "wall"]
    plate = next(p for p in g.planes if p.label == "plate")
    assert plate.normal @ axis > 0.99


def test_tunnel_without_hint_and_other_orientation():
    pts, _ = tunnel_cloud(seed=3, rpy=(1.2, 0.4, -2.0), offset=(0.0, 0.2, 0.5), back_wall=False)
    g = tunnel_geometry(pts)
    assert g.width_m == pytest.approx(WIDTH, abs=1e-3)
    assert g.height_m == pytest.approx(HEIGHT, abs=1e-3)
    assert g.plate_distance_m == pytest.approx(PLATE, abs=1e-3)


def test_200k_points():
    """A cloud of 200,000 points gives the tunnel's dimensions (its speed: benchmarks/)."""
    pts, axis = tunnel_cloud(n=200_000, seed=5)
    g = tunnel_geometry(pts, axis_hint_M=axis)
    assert g.width_m == pytest.approx(WIDTH, abs=1e-3) and g.height_m == pytest.approx(HEIGHT, abs=1e-3)


def test_board_only_scene_gives_none():
    rng = np.random.default_rng(2)
    p = np.c_[np.full(30_000, 1.5), rng.uniform(-0.5, 0.5, 30_000), rng.uniform(-0.4, 0.4, 30_000)]
    p[:, 0] += rng.normal(0, 0.01, len(p))
    g = tunnel_geometry(p)
    assert g.width_m is None and g.height_m is None and g.plate_distance_m is None
    assert len(g.planes) >= 1 and g.planes[0].label == "other"
    assert g.planes[0].offset_m == pytest.approx(1.5, abs=1e-3)


def test_empty_cloud():
    g = tunnel_geometry(np.zeros((0, 3)))
    assert g.width_m is None and g.planes == ()
    assert extract_planes(np.zeros((10, 3))) == []

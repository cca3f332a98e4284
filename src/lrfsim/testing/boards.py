"""The marker boards of :func:`lrfsim.testing.random_scenarios.random_scenario_wide` (its "board" and "board_on_axis"
layouts) and the frame helpers they share with it.

Which board determines b (the scan plane's offset from the motor axis, DH b with alpha about +-90 deg)? A marker
at distance d from the motor axis moves by b across the scan plane when b changes, and by d times the angle when
the mount turns about the motor axis: the same direction at every motor angle (the scan plane holds the axis and the
marker). So the data tell b from the mount's turn about its axis only by markers at different distances from the
axis. A board beside the rig facing the axis (:func:`board_beside`) has all its markers at about one such distance
(within 0.5-4 % on random_scenario_wide's seeds 2005-2009): b's marker-only 1-sigma is 14-55 mm there (5 mm is the
limit, lrfcal.estimate.observability.LIMITS), 3-6.5 mm with the mount's turn about the axis held, 12-55 mm with its
position held. A board the motor axis points at (:func:`board_on_axis`) has markers from near the axis to its edge;
straight across the axis it still puts them all at one distance along it, where a turn of alpha moves them as b does
(b 6-70 mm on ten seeds), so it is turned. Turned 25-50 deg from across the axis, with the axis through its middle,
the calibration's score test would free the motor's angle scale on a third of the seeds (the marker returns' lateral
residuals pull it below 1 to shrink the crossings of markers near the axis), and b went undetermined on 5 of 40;
turned 40-65 deg, the axis meeting it anywhere within 60 % of its half sizes from its centre, plan determines 40 of
seeds 2000-2039 (the scale freed on 11 while the marker model took each return's lateral offset as noise; on none
since it keeps their means, lrfcal.model.coverage).
"""

from __future__ import annotations

import math

import numpy as np

from lrfcal.model.kinematics import Pose

#: the board the motor axis points at: the axis meets it this far ahead of the rig [m] (at least), within this
#: fraction of its half sizes from its centre, its face turned this far from perpendicular to the axis [deg]
ON_AXIS_DISTANCE_M = (0.6, 1.1)
ON_AXIS_PIERCE = 0.6
ON_AXIS_TILT_DEG = (40.0, 65.0)
#: its nearest corner at least this far ahead of the rig, along the axis [m]
ON_AXIS_CLEARANCE_M = 0.2


def perpendicular_basis(e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (3,) completing the unit vector e to a right-handed frame (p1, p2, e)."""
    helper = np.array([0.0, 0.0, 1.0]) if abs(e[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    p1 = np.cross(helper, e)
    p1 /= np.linalg.norm(p1)
    return p1, np.cross(e, p1)


def pose_dict(T: np.ndarray) -> dict[str, float]:
    """x, y, z, roll, pitch, yaw of T (4, 4), also at the pitch = +-90 deg gimbal lock (then roll absorbs yaw)."""
    pose = Pose.from_matrix(T).as_dict()
    R = T[:3, :3]
    if abs(R[2, 0]) > 1 - 1e-9:
        s = -float(np.sign(R[2, 0]))  # sin(pitch)
        pose.update(pitch=s * math.pi / 2, yaw=0.0, roll=math.atan2(s * R[0, 1], s * R[0, 2]))
    assert np.allclose(Pose(**pose).matrix(), T, atol=1e-9), "rpy conversion"
    return pose


def board_beside(rng: np.random.Generator, origin: np.ndarray, e_axis: np.ndarray, radius: float
                 ) -> tuple[dict[str, object], dict[str, object]]:
    """A board beside the rig, its width along the motor axis (markers at many axial distances), facing the
    rig: centre 0.3-1.0 m along the axis and 0.5-1.2 m off it, in a random direction. Its markers are all at about
    one distance from the axis: b is not determined (the module docstring)."""
    p1, p2 = perpendicular_basis(e_axis)
    ang = rng.uniform(0, 2 * math.pi)
    n = math.cos(ang) * p1 + math.sin(ang) * p2  # from the axis towards the board
    width, height = rng.uniform(0.9, 1.5), rng.uniform(0.6, 1.0)
    centre = origin + rng.uniform(0.5, 1.2) * n + rng.uniform(0.3, 1.0) * float(rng.choice([-1, 1])) * e_axis
    ex, ez = e_axis, -n  # board width along the axis, front face (local +z) towards the rig
    return _board(rng, centre, ex, ez, width, height, radius, max_spacing=0.2)


def board_on_axis(rng: np.random.Generator, origin: np.ndarray, e_axis: np.ndarray, radius: float
                  ) -> tuple[dict[str, object], dict[str, object]]:
    """A board the motor axis points at, standing obliquely in front of the rig: 0.9-1.5 x 0.6-1.0 m, its face turned
    ON_AXIS_TILT_DEG from perpendicular to the axis (+-e_axis, either way) about a random direction across it, the
    axis meeting it ON_AXIS_DISTANCE_M ahead of the rig (further where its nearest corner would come closer than
    ON_AXIS_CLEARANCE_M, along the axis) at a random point within ON_AXIS_PIERCE of its half sizes from its centre;
    the markers' grid spread over the board (up to 0.35 m apart). Every scan plane, holding the axis, crosses it:
    its markers lie at several distances from the axis (b told from the mount's turn about it) and along it (b told
    from alpha)."""
    e = e_axis * float(rng.choice([-1.0, 1.0]))
    p1, p2 = perpendicular_basis(e)
    width, height = rng.uniform(0.9, 1.5), rng.uniform(0.6, 1.0)
    tilt = math.radians(rng.uniform(*ON_AXIS_TILT_DEG))
    ang = rng.uniform(0, 2 * math.pi)
    k = math.cos(ang) * p1 + math.sin(ang) * p2  # the board turns about k, across the axis
    ez = -math.cos(tilt) * e + math.sin(tilt) * np.cross(k, -e)  # its front face towards the rig, turned about k
    ex = k if rng.random() < 0.5 else np.cross(ez, k)  # its width along k, or its height
    ey = np.cross(ez, ex)
    uv = rng.uniform(-ON_AXIS_PIERCE, ON_AXIS_PIERCE, 2) * np.array([width, height]) / 2  # where the axis meets it
    corners = [(su * width / 2 - uv[0]) * ex + (sv * height / 2 - uv[1]) * ey for su in (-1, 1) for sv in (-1, 1)]
    dist = max(rng.uniform(*ON_AXIS_DISTANCE_M), ON_AXIS_CLEARANCE_M - min(float(c @ e) for c in corners))
    centre = origin + dist * e - uv[0] * ex - uv[1] * ey
    return _board(rng, centre, ex, ez, width, height, radius, max_spacing=0.35)


def _board(rng: np.random.Generator, centre: np.ndarray, ex: np.ndarray, ez: np.ndarray, width: float,
           height: float, radius: float, max_spacing: float) -> tuple[dict[str, object], dict[str, object]]:
    """The scene and markers sections of a board at centre (3,), its width along ex, its front face (local +z)
    along ez (unit, perpendicular): a jittered grid of 6-30 markers, max_spacing [m] or less apart."""
    R = np.column_stack([ex, np.cross(ez, ex), ez])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, centre
    cols = int(rng.integers(3, 7))
    rows = int(rng.integers(max(2, -(-6 // cols)), min(5, 30 // cols) + 1))
    spacing = min(max_spacing, (width - 0.1) / (cols - 1), (height - 0.1) / max(rows - 1, 1))
    scene: dict[str, object] = {"board": {"pose": pose_dict(T), "width_m": width, "height_m": height,
                                          "thickness_m": 0.01}}
    markers = {"radius_m": radius, "layout": {"kind": "board", "rows": rows, "cols": cols, "spacing_m": spacing,
                                              "jitter_m": min(0.02, spacing / 4)}}
    return scene, markers


"""What ``lrfsim plan`` casts: the scans whose plane passes near a marker (their marker returns as the full cast gives
them, bit for bit) and every SURFACE_SCAN_STEP-th other scan for the surface returns, without noise."""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from lrfcal.model.kinematics import Params
from lrfsim.cast.forked import Forked
from lrfsim.scenario.file import Scenario

if TYPE_CHECKING:
    from lrfsim.simulation.simulate import Geometry

FloatArray = NDArray[np.float64]


#: plan's sparse cast (:func:`sparse_scans`) casts every this-many-th scan for the surface returns
SURFACE_SCAN_STEP = 4
#: the label of the returns plan's surface sample leaves out (lrfcal.stages.surfaces.observe_surfaces: not a surface
#: return)
NOT_SAMPLED = 1 << 30
#: and every scan whose plane passes within this much (plus the footprint's spread) of a marker's centre
NEAR_MARKER_M = 0.005


def sparse_scans(scenario: Scenario, beam_lambda_rad: FloatArray) -> NDArray[np.bool_]:
    """(S,) bool: the scans plan casts (:func:`sparse_geometry`): those whose plane passes near
    a marker (lrfsim.world.visibility.scans_near_markers: the marker's radius and NEAR_MARKER_M plus the footprint's
    ring, a superset of the scans with a marker return) and every SURFACE_SCAN_STEP-th scan, for the surface
    returns (plan uses a subsample of them, as the calibration does)."""
    from lrfsim.sensors.lidar import beam_angles, ring_half_angle
    from lrfsim.world.geometry import marker_centres_W
    from lrfsim.world.visibility import scans_near_markers

    if scenario.markers is None:
        return np.ones(beam_lambda_rad.shape[0], dtype=bool)
    params = Params(scenario.rig.mount.to_pose(), scenario.rig.dh.to_dh())
    reach = float(scenario.markers.radius_m) + NEAR_MARKER_M
    near = scans_near_markers(params, beam_lambda_rad, beam_angles(scenario.sensor), marker_centres_W(scenario),
                              reach, 2.0 * ring_half_angle(scenario.sensor))
    return near | (np.arange(beam_lambda_rad.shape[0]) % SURFACE_SCAN_STEP == 0)


def sparse_geometry(scenario: Scenario, rest_of: Geometry | None = None,
                    meanwhile: Callable[[], object] | None = None) -> Geometry:
    """Plan's noise-free cast of the scans :func:`sparse_scans` picks (the others without a return); with
    ``rest_of`` (such a cast), the other scans cast and joined to it: the full cast.

    The cast's chunks are shared with a forked helper process where one can be forked (lrfsim.cast.forked: this
    cast of many short ``mj_multiRay`` calls holds the GIL most of its time, so threads do not overlap it; the
    result is the same), and ``meanwhile()`` runs here while the helper casts (`lrfsim plan` imports the
    prediction's modules there)."""
    from lrfsim.simulation.simulate import cast_geometry, joined

    helper = Forked(meanwhile)
    if rest_of is None:
        return cast_geometry(scenario, noise=False, scans=partial(sparse_scans, scenario), threads=helper)
    rest = cast_geometry(scenario, noise=False, scans=lambda lam: ~sparse_scans(scenario, lam), threads=helper)
    return joined(rest_of, rest)

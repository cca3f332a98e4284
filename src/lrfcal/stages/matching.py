"""Stage 4's starting point: the blobs matched to the marker map (lrfcal.stages.association) with their centres
reprojected from the nominal DH or from the candidates of the correspondence-free DH search (lrfcal.stages.start),
for the marker way (lrfcal.stages.markers)."""

from __future__ import annotations

from typing import Protocol

import numpy as np

from lrfcal.errors import CalibrationError
from lrfcal.model.kinematics import DH
from lrfcal.stages import association, detection, start
from lrfcal.types import Association, Detections, MarkerMap, Nominal, Observations


class MatchConfig(Protocol):
    """The configuration the matching reads: its slice of lrfcal.config.CalibConfig (which satisfies it)."""

    @property
    def association_gate_m(self) -> float: ...


def associate_at(returns: Observations, detections: Detections, markers: MarkerMap, dh: DH, radius_m: float,
             config: MatchConfig) -> Association | None:
    """Stage 4 with the blob centres reprojected with ``dh``; None when nothing matches."""
    centres = detection.blob_centres_M(returns, dh, radius_m, n_blobs=len(detections.blobs))
    try:
        return association.associate(centres, markers, gate_m=config.association_gate_m)
    except CalibrationError:
        return None


def associate_nominal(returns: Observations, detections: Detections, markers: MarkerMap, nominal: Nominal,
                       config: MatchConfig) -> Association | None:
    return associate_at(returns, detections, markers, nominal.dh, nominal.marker_radius_m, config)


#: the share of the blobs an association matches for it to be the rig's (:func:`good`, :func:`associate_search`)
MOST_BLOBS = 0.9


def matches_most(assoc: Association, returns: Observations) -> bool:
    """Whether an association matches most blobs (MOST_BLOBS of them)."""
    return assoc.n_matched >= MOST_BLOBS * len(np.unique(returns.blob))


def good(assoc: Association, returns: Observations, config: MatchConfig) -> bool:
    """An association that leaves nothing to search for: most blobs matched, tight alignment."""
    return matches_most(assoc, returns) and assoc.rms_m <= 0.25 * config.association_gate_m


def associate_search(returns: Observations, detections: Detections, markers: MarkerMap, nominal: Nominal,
                      config: MatchConfig, from_nominal: Association | None, every_attitude: bool = True
                      ) -> tuple[DH, Association | None]:
    """The association from the candidates of the correspondence-free DH search (lrfcal.stages.start) or from the
    nominal
    DH, the best by (matched blobs, alignment RMS); returns the DH it used and the association (None: none). The
    search covers the basin around the nominal first, and every attitude of the scan plane (the coarse global start)
    when no candidate there matches most blobs: a nominal DH far from the rig's is then found, not landed on. (An
    association that matches most blobs loosely, e.g. with a marker moved after taping, is the rig's: the solve
    refines it, and the global search, seconds with many blobs, would find nothing better.) ``every_attitude``
    False: the basin only (the servo's other direction, once the declared one has a solution)."""
    best_dh, best = nominal.dh, from_nominal
    for span in (start.ANGLE_SPAN_RAD, start.GLOBAL_SPAN_RAD) if every_attitude else (start.ANGLE_SPAN_RAD,):
        for dh in start.dh_candidates(returns, len(detections.blobs), markers, nominal.dh, nominal.marker_radius_m,
                                      span_rad=span):
            found = associate_at(returns, detections, markers, dh, nominal.marker_radius_m, config)
            if found is not None and (best is None or (found.n_matched, -found.rms_m) > (best.n_matched, -best.rms_m)):
                best_dh, best = dh, found
        if best is not None and matches_most(best, returns):
            break
    return best_dh, best


__all__ = ["MOST_BLOBS", "MatchConfig", "associate_at", "associate_nominal", "associate_search", "good", "matches_most"]

"""What `lrfsim plan` predicts for one scenario (:class:`Plan`): the predicted covariance and sigma of every
calibrated parameter, the observability verdict by the rule `lrfcal calibrate` refuses on
(lrfcal.estimate.observability.Verdict), the tolerances, the held scales and the smallest drift `lrfcal check`
detects; as JSON (`lrfsim plan --json`). The prediction itself: lrfsim.plan.prediction."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from lrfcal import DEFAULT_FALSE_ALARM, SCALE_Z_LIMIT, Observability, Verdict, detectable_drift
from lrfcal.model.kinematics import DH_NAMES, ESTIMATE_NAMES
from lrfcal.model.unknowns import BY_NAME

FloatArray = NDArray[np.float64]

#: a tolerance counts as reachable when it is at least this many predicted sigmas
REACHABLE_K = 4.0
#: what enters the information (printed with the plan)
SOURCE_MARKERS = "marker returns (sphere model, stage 6)"
SOURCE_SURFACES = "marker returns (sphere model) and surface returns with plane priors (stages 6 and 6b)"


@dataclass(frozen=True)
class ToleranceCheck:
    """One tolerance of the scenario against the prediction: ``predicted_m_or_rad`` is the predicted 1-sigma of
    that quantity (for the mount position and rotation, the RMS of the error's norm, sqrt of the trace)."""

    name: str
    tolerance: float
    predicted: float

    @property
    def reachable(self) -> bool:
        return bool(self.tolerance >= REACHABLE_K * self.predicted)


@dataclass(frozen=True)
class Plan:
    """The prediction for one scenario.

    names: the estimated parameters in order (ESTIMATE_NAMES [+ clock_offset]); covariance (k, k) over them in SI
    units (the rotation as a rotation vector in frame M); sigma: name -> predicted 1-sigma; observability: the DH
    verdict of the calibration from the marker returns (lrfcal.estimate.observability); tolerances: the scenario's
    tolerances against 4 sigma;
    n_returns / n_markers_seen: the marker returns the information is built from; range_sigma_m: the noise model.
    """

    scenario: str
    names: tuple[str, ...]
    covariance: FloatArray
    sigma: dict[str, float]
    observability: Observability
    tolerances: tuple[ToleranceCheck, ...]
    n_returns: int
    n_markers_seen: int
    n_markers: int
    clock_estimated: bool
    range_sigma_m: float
    seconds: float
    information_source: str = SOURCE_MARKERS
    n_surface_returns: int = 0
    notes: tuple[str, ...] = field(default=())
    #: the DH verdict from all the returns the calibration solves with (the surfaces' too): what the calibration's
    #: "observability" check reports after solving (None: the same as ``observability``, markers only)
    observability_solved: Observability | None = None
    #: name -> the 1-sigma the model's own errors contribute (lrfcal.estimate.information.model_error_at), included in
    #: ``sigma`` (added in variance)
    model_sigma: dict[str, float] = field(default_factory=dict)
    #: name -> the 1-sigma the marker map's own uncertainty (the tape's noise) contributes
    #: (lrfcal.estimate.information.map_error_at), included in ``sigma``
    map_sigma: dict[str, float] = field(default_factory=dict)
    #: scale name (lrfcal.stages.joint.SCALES) -> its statistical 1-sigma if freed: the calibration holds each scale at
    #: 1
    #: and estimates it where its score test steps SCALE_Z_LIMIT of this (or more) from 1
    scale_sigma: dict[str, float] = field(default_factory=dict)
    range_correlation: float = 0.0  #: the range noise's correlation between neighbouring beams (sandwich term)
    #: whether the rig file's nominal tells the rig from its mirror image (lrfcal's mirror check on the true DH and
    #: the sigma predicted here), and the words; None: not judged
    mirror: tuple[bool, str] | None = None
    #: the names of ``covariance``'s rows: ``names`` and, with the surface returns, the range offset and the marker
    #: range bias after them (the calibration estimates both; () : ``names``)
    covariance_names: tuple[str, ...] = ()

    def check_detects(self, false_alarm: float = DEFAULT_FALSE_ALARM, power: float = 0.95) -> dict[str, float]:
        """For this scenario used as `lrfcal check`'s new recording against a calibration of the same layout and sweep
        (whose covariance is then this one too: C = 2 x the predicted covariance over the parameters the check
        tests, the DH, the clock offset and the intrinsics estimated), the smallest drift of each tested parameter
        alone that the check's joint test detects with probability ``power`` at ``false_alarm``
        (lrfcal.estimate.drift.detectable_drift); inf where the DH are not determined."""
        names = self.covariance_names or self.names
        tested = [n for n in names if n not in ESTIMATE_NAMES[:6]]
        if not self.determined:
            return {n: math.inf for n in tested}
        i = [names.index(n) for n in tested]
        delta = detectable_drift(2.0 * self.covariance[np.ix_(i, i)], false_alarm, power)
        return {n: float(v) for n, v in zip(tested, delta, strict=True)}

    @property
    def final_observability(self) -> Observability:
        """What `lrfcal calibrate`'s observability check will report (after the joint solve)."""
        return self.observability_solved if self.observability_solved is not None else self.observability

    @property
    def verdict(self) -> Verdict:
        """Determined or not by the rule calibrate refuses on (lrfcal.estimate.observability.Verdict): the marker
        returns alone at the start, and the covariance predicted here (:attr:`final_observability`)."""
        return Verdict(self.observability, self.final_observability, self.mirror)

    @property
    def determined(self) -> bool:
        return self.verdict.determined and all(math.isfinite(self.sigma[n]) for n in DH_NAMES)

    @property
    def tolerances_reachable(self) -> bool:
        return self.determined and all(t.reachable for t in self.tolerances)

    @property
    def weakest(self) -> str:
        return self.final_observability.describe()

    @property
    def strengthen(self) -> str:
        """What would strengthen the weakest direction, in words."""
        hint = self.observability.hint()
        return f"{hint}; more passes of the sweep (turns of a spin) shrink every sigma by about 1/sqrt(passes)"

    def to_json(self) -> dict[str, Any]:
        """The plan as one JSON-able mapping (SI units; infinity as null)."""

        def num(v: float) -> float | None:
            return float(v) if math.isfinite(v) else None

        return {
            "scenario": self.scenario,
            "sigma": {n: num(self.sigma[n]) for n in self.names},
            "model_error_sigma": {n: num(self.model_sigma[n]) for n in self.names if n in self.model_sigma},
            "tape_sigma": {n: num(self.map_sigma[n]) for n in self.names if n in self.map_sigma},
            "units": {n: _unit(n) for n in self.names},
            "weakest": self.weakest,
            "weakest_sigma_in_limits": num(self.final_observability.weakest_sigma_in_limits),
            "weakest_sigma_in_limits_markers_only": num(self.observability.weakest_sigma_in_limits),
            "strengthen": self.strengthen,
            "determined": self.determined,
            "verdict": self.verdict.reason() or "determined: the marker returns alone and the predicted covariance",
            "tolerances_reachable": self.tolerances_reachable,
            "tolerances": {t.name: {"tolerance": t.tolerance, "predicted_sigma": num(t.predicted),
                                    "reachable": t.reachable} for t in self.tolerances},
            "clock_offset_estimated": self.clock_estimated,
            "n_returns": self.n_returns,
            "n_markers_seen": self.n_markers_seen,
            "n_markers": self.n_markers,
            "n_surface_returns": self.n_surface_returns,
            "range_sigma_m": self.range_sigma_m, "range_noise_correlation": self.range_correlation,
            "held_scale_sigma": {n: num(v) for n, v in self.scale_sigma.items()},
            "held_scale_found_beyond": {n: num(SCALE_Z_LIMIT * v) for n, v in self.scale_sigma.items()},
            "information": self.information_source,
            "seconds": self.seconds,
            "notes": list(self.notes),
            "check_detects_95": {n: num(v) for n, v in self.check_detects().items()},
        }


def _unit(name: str) -> str:
    if name in BY_NAME and BY_NAME[name].kind == "intrinsic":
        return BY_NAME[name].unit
    if name in ("x", "y", "z", "a", "b"):
        return "m"
    return "s" if name == "clock_offset" else "rad"



def format_value(name: str, value: float) -> str:
    """A parameter's value in display units (mm, deg, ms)."""
    if not math.isfinite(value):
        return "unbounded"
    unit = _unit(name)
    if unit == "m/rad":  # the incidence bias
        return f"{value * 1000:.3g} mm/rad"
    if unit == "m":
        return f"{value * 1000:.3g} mm"
    if unit == "s":
        return f"{value * 1000:.3g} ms"
    if unit == "1":
        return f"{value * 1e6:.3g} ppm"
    return f"{math.degrees(value):.3g} deg"


__all__ = ["REACHABLE_K", "SOURCE_MARKERS", "SOURCE_SURFACES", "Plan", "ToleranceCheck", "format_value"]

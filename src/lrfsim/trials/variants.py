"""Scenario variants of a study (lrfsim.trials.study): one field set (``--vary``), the perturbed start of a trial
(``--perturb-start``) and its drawn truth (``--truth-spread``; lrfsim.trials.study's module docstring has the draws)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import yaml
from numpy.typing import NDArray

from lrfcal.errors import InputError
from lrfsim.scenario.file import Scenario, parse_scenario
from lrfsim.scenario.sections import DHConfig, DHToleranceConfig, PoseConfig

#: --perturb-start 1: half-widths of the uniform perturbation of each nominal value (SI units: m, rad)
PERTURB_HALF_WIDTH: dict[str, float] = {
    "a": 0.005, "alpha": math.radians(1.0), "b": 0.005, "beta": math.radians(1.0),
    "x": 0.02, "y": 0.02, "z": 0.02, "roll": math.radians(1.0), "pitch": math.radians(1.0), "yaw": math.radians(1.0),
}
#: the perturbed start's random stream ("star"; lrfsim.simulation.simulate's are "phas", "nois", ...)
_RNG_START = 0x73746172
#: --truth-spread 1: half-widths of the uniform draw of each true DH parameter around the nominal (SI units: m, rad):
#: a real build is a few mm and a degree or two off its drawing
TRUTH_HALF_WIDTH: dict[str, float] = {"a": 0.005, "alpha": math.radians(1.5), "b": 0.005, "beta": math.radians(1.5)}
#: the drawn truth's random stream ("true")
_RNG_TRUTH = 0x74727565


def with_field(scenario: Scenario, dotted: str, value: Any) -> Scenario:
    """The scenario with one field (dotted path, e.g. ``servo.passes``) set to ``value`` (validated).

    Raises:
        InputError: unknown path or invalid value (naming the field).
    """
    data = scenario.model_dump(mode="python")
    node: Any = data
    *head, last = dotted.split(".")
    for k in head:
        if not isinstance(node, dict) or k not in node or not isinstance(node[k], dict):
            raise InputError(f"--vary: {dotted!r}: no section {k!r} in the scenario")
        node = node[k]
    if not isinstance(node, dict) or last not in node:
        raise InputError(f"--vary: {dotted!r}: no field {last!r} in the scenario")
    node[last] = value
    return parse_scenario(data, f"{scenario.name} with {dotted}={value!r}")


def parse_vary(text: str) -> tuple[str, list[Any]]:
    """``KEY=V1,V2,...`` -> (KEY, [values]); each value is read as YAML (numbers, true/false, text)."""
    key, sep, values = text.partition("=")
    key = key.strip()
    if not sep or not key or not values.strip():
        raise InputError(f"--vary: expected KEY=V1,V2,... (e.g. servo.passes=1,2,4), got {text!r}")
    out = []
    for v in values.split(","):
        v = v.strip()
        if not v:
            raise InputError(f"--vary: empty value in {text!r}")
        try:
            out.append(yaml.safe_load(v))
        except yaml.YAMLError:
            raise InputError(f"--vary: cannot read the value {v!r}") from None
    return key, out


def perturbed_start(scenario: Scenario, seed: int, scale: float) -> Scenario:
    """The scenario with its nominal DH and mount (``rig.nominal_dh``, ``rig.nominal_mount``: the trial's
    nominal.yaml) each moved by an independent uniform draw in +-``scale`` x :data:`PERTURB_HALF_WIDTH`, drawn
    from ``seed`` alone (module docstring); angles wrapped to [-pi, pi]. ``scale`` = 0 returns ``scenario``.

    Raises:
        InputError: a negative or non-finite scale.
    """
    u = _uniform(seed, _RNG_START, scale, len(PERTURB_HALF_WIDTH), "--perturb-start")
    if u is None:
        return scenario
    step = dict(zip(PERTURB_HALF_WIDTH, scale * u * np.array(list(PERTURB_HALF_WIDTH.values())), strict=True))
    rig = scenario.rig

    def moved(config: DHConfig | PoseConfig) -> dict[str, float]:
        out = {}
        for k, v in config.model_dump().items():
            v = float(v + step[k])
            out[k] = math.remainder(v, 2 * math.pi) if k in ("alpha", "beta", "roll", "pitch", "yaw") else v
        return out

    new_rig = rig.model_copy(update={"nominal_dh": DHConfig(**moved(rig.nominal_dh)),
                                     "nominal_mount": PoseConfig(**moved(rig.nominal_mount))})
    return scenario.model_copy(update={"rig": new_rig})


def drawn_truth(scenario: Scenario, seed: int, scale: float) -> Scenario:
    """The scenario with its true DH (``rig.dh``) drawn around its nominal DH (``rig.nominal_dh``), each parameter
    uniform in +-``scale`` x :data:`TRUTH_HALF_WIDTH`, from ``seed`` alone (a stream of its own), and the nominal's
    1-sigma (``rig.nominal_dh_tolerance``, the rig file's ``dh_tolerance``) that spread's: the calibration is told
    how well the drawing knows the rig, as its user would be. The mount and the nominal values unchanged.
    ``scale`` = 0 returns ``scenario``.

    Raises:
        InputError: a negative or non-finite scale.
    """
    u = _uniform(seed, _RNG_TRUTH, scale, len(TRUTH_HALF_WIDTH), "--truth-spread")
    if u is None:
        return scenario
    nominal = scenario.rig.nominal_dh.model_dump()
    dh = {k: float(nominal[k] + scale * w * u[i]) for i, (k, w) in enumerate(TRUTH_HALF_WIDTH.items())}
    for k in ("alpha", "beta"):
        dh[k] = math.remainder(dh[k], 2 * math.pi)
    # the drawing's +-scale x half width, the truth uniform within: its 1-sigma (JCGM 100:2008 4.3.7)
    tolerance = DHToleranceConfig(**{k: scale * w / math.sqrt(3.0) for k, w in TRUTH_HALF_WIDTH.items()})
    return scenario.model_copy(update={"rig": scenario.rig.model_copy(
        update={"dh": DHConfig(**dh), "nominal_dh_tolerance": tolerance})})


def _uniform(seed: int, stream: int, scale: float, n: int, option: str) -> NDArray[np.float64] | None:
    """``n`` independent uniform draws in [-1, 1] from ``seed`` alone (the stream ``stream`` of its own), or None
    where ``scale`` is 0 (nothing is drawn).

    Raises:
        InputError: a negative or non-finite scale (``option`` names it).
    """
    if not (math.isfinite(scale) and scale >= 0):
        raise InputError(f"{option}: expected a scale >= 0, got {scale}")
    if scale == 0:
        return None
    return np.random.default_rng([int(seed), stream]).uniform(-1.0, 1.0, n)


@dataclass(frozen=True)
class TrialDesign:
    """How each trial differs from the scenario besides its noise. ``recast``: cast every trial anew (the laser
    phase drawn from the trial's seed too). ``perturb_start``: the scale of each trial's perturbed start
    (:func:`perturbed_start`; 0: the scenario's nominal values). ``new_layout``: build every trial's scene from its
    own seed too (a board's jittered grid, a random layout: a new marker layout per trial; implies ``recast``), to
    average over layouts rather than over the noise of one. ``truth_spread``: the scale of each trial's true DH drawn
    around the nominal (:func:`drawn_truth`; 0: the scenario's truth); a drawn truth builds its own scene and cast
    (the true DH is in the scene's model). ``force``: every trial calibrates as ``lrfcal calibrate --force`` does
    (a marker-less one with ``--targetless``): a failed check recorded, not refused, so the RMS of error / sigma is
    over the trials the checks would have refused too, not only over those they passed."""

    recast: bool = False
    perturb_start: float = 0.0
    new_layout: bool = False
    truth_spread: float = 0.0
    force: bool = False

    @property
    def own_scene(self) -> bool:
        """Every trial builds its scene from its own scenario (a layout or a truth of its own)."""
        return self.new_layout or self.truth_spread > 0

    @property
    def own_cast(self) -> bool:
        """Every trial casts its own rays (no cast shared between trials)."""
        return self.recast or self.own_scene


__all__ = ["PERTURB_HALF_WIDTH", "TRUTH_HALF_WIDTH", "TrialDesign", "drawn_truth", "parse_vary", "perturbed_start",
           "with_field"]

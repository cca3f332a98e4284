"""Scenario files: the top-level model (one field per section, the sections in :mod:`lrfsim.scenario.sections`, and
the checks across sections), reading and validating a file (errors name the file, the field and, for an unknown key,
the nearest valid one), the memory a scenario needs, and the effective scenario written back as YAML.

A scenario fully determines a simulated recording (with its seed). Units are SI; angles in rad unless the
field name says ``_deg``. Frames: W is the simulator world, z up, floor at z = 0 (for a tunnel: x along the
tunnel towards the plate, y to the left, walls at y = +-width/2; a room is placed in W by its floor centre and yaw).
"""

from __future__ import annotations

import copy
import difflib
import math
import os
from pathlib import Path
from typing import Annotated, Any, get_args

import yaml
from pydantic import BaseModel, ValidationError, model_validator

from lrfcal.errors import InputError
from lrfcal.io.yamlfile import read_yaml

from .scene_sections import SceneConfig
from .sections import (
    FaultsConfig,
    MarkersConfig,
    RigConfig,
    Section,
    SensorConfig,
    ServoConfig,
    TapeConfig,
    Tolerances,
    doc,
)
from .servo_timing import servo_run_time_s, step_move_s


class Scenario(Section):
    """A scenario file: everything a simulated recording depends on (units SI, angles in rad)."""

    name: Annotated[str, doc("name of the run (runs/<name>/)")]
    seed: Annotated[int, doc("random seed of every noise stream [1]", ge=0)] = 0
    rig: Annotated[RigConfig, doc("true and nominal rig geometry")]
    sensor: Annotated[SensorConfig, doc("the laser scanner")] = SensorConfig()
    servo: Annotated[ServoConfig, doc("the servo sweep and joint states")] = ServoConfig()
    scene: Annotated[SceneConfig, doc("what the laser sees")]
    markers: Annotated[MarkersConfig | None, doc(
        "the markers; none (omitted or null): a marker-less scene, written without distances.csv (targetless "
        "calibration)")] = None
    tape: Annotated[TapeConfig, doc("the tape-measured marker distances (unused without markers)")] = TapeConfig()
    tolerances: Annotated[Tolerances, doc("what lrfsim run requires of the recovery")] = Tolerances()
    faults: Annotated[FaultsConfig, doc("faults injected into the recording (lrfsim.simulation.faults); none by "
                                        "default")] = FaultsConfig()

    @model_validator(mode="after")
    def _check(self) -> Scenario:
        if self.servo.mode == "step":
            _check_step_and_scan(self.servo, self.sensor)
        if self.markers is None:
            if self.faults.tape_outliers:
                raise ValueError("faults.tape_outliers needs markers (the scenario has none)")
            if self.faults.occluded_markers:
                raise ValueError("faults.occluded_markers needs markers (the scenario has none)")
            return self
        if self.markers.layout.kind == "board" and self.scene.board is None:
            raise ValueError("markers.layout is 'board' but scene.board is missing")
        if self.markers.layout.kind == "v" and self.scene.tunnel is None:
            raise ValueError("markers.layout is 'v' but scene.tunnel is missing")
        return self

    @property
    def marker_radius_m(self) -> float | None:
        """The markers' sphere radius [m]; None for a marker-less scene."""
        return None if self.markers is None else self.markers.radius_m


def _check_step_and_scan(servo: ServoConfig, sensor: SensorConfig) -> None:
    """Mode step: one scan per step (step_period_s = sensor.scan_period_s), and each step's move fits in the time
    the laser does not scan, so that every beam of a scan sees the motor stand still."""
    if abs(servo.step_period_s - sensor.scan_period_s) > 1e-9 * sensor.scan_period_s:
        raise ValueError(f"servo.step_period_s {servo.step_period_s:g} s must equal sensor.scan_period_s "
                         f"{sensor.scan_period_s:g} s (mode step: one scan per step)")
    move_s = step_move_s(servo)
    beams_s = (sensor.n_beams - 1) * sensor.time_increment_s
    if move_s + beams_s > sensor.scan_period_s:
        raise ValueError(f"servo: a step's move takes {move_s * 1e3:.3g} ms (step_rad, speed_rad_s, accel_rad_s2) and "
                         f"the beams {beams_s * 1e3:.3g} ms of each {sensor.scan_period_s * 1e3:.3g} ms scan period: "
                         "the servo would move while the laser scans (mode step); raise speed_rad_s or accel_rad_s2")


def _field_path(loc: tuple[int | str, ...]) -> str:
    """Dotted field path; drops the tag pydantic inserts after a discriminated union (markers.layout.v.x)."""
    parts: list[str] = []
    for i, p in enumerate(loc):
        if i > 0 and loc[i - 1] == "layout" and p in ("v", "board", "points"):
            continue
        if isinstance(p, int) and parts:
            parts[-1] += f"[{p}]"
            continue
        parts.append(str(p))
    return ".".join(parts) if parts else "(top level)"


def _models_in(annotation: object) -> list[type[BaseModel]]:
    """The pydantic models an annotation may hold (through Optional, unions and tuples)."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    out: list[type[BaseModel]] = []
    for arg in get_args(annotation):
        out += _models_in(arg)
    return out


def _fields_at(loc: tuple[int | str, ...]) -> list[str]:
    """The valid keys of the section that holds the last element of a pydantic error location."""
    models: list[type[BaseModel]] = [Scenario]
    for part in loc[:-1]:
        if isinstance(part, int):
            continue
        tagged = [m for m in models if part in ("v", "board", "points") and
                  m.model_fields.get("kind") is not None and m.model_fields["kind"].default == part]
        if tagged:
            models = tagged
            continue
        nxt: list[type[BaseModel]] = []
        for m in models:
            if part in m.model_fields:
                nxt += _models_in(m.model_fields[part].annotation)
        models = nxt
    return sorted({f for m in models for f in m.model_fields})


def parse_scenario(data: object, source: str) -> Scenario:
    """Validate a scenario mapping; raise :class:`InputError` naming ``source``, the field and, for an unknown
    key, the nearest valid one."""
    try:
        return Scenario.model_validate(data)
    except ValidationError as e:
        err = e.errors()[0]
        loc = tuple(err["loc"])
        field = _field_path(loc)
        value = err.get("input")
        msg = err["msg"]
        if err["type"] == "extra_forbidden" and loc:
            valid = _fields_at(loc)
            near = difflib.get_close_matches(str(loc[-1]), valid, n=1, cutoff=0.6)
            hint = f"did you mean {near[0]!r}? " if near else ""
            raise InputError(f"{source}: {field}: unknown key ({hint}valid keys: {', '.join(valid)})") from None
        if err["type"] == "finite_number":
            msg = "must be a finite number (NaN and infinity are not allowed)"
        shown = "" if isinstance(value, dict) else f" (got {value!r})"
        raise InputError(f"{source}: {field}: {msg}{shown}") from None


#: Memory a simulated beam costs over the whole run (simulation, recording, calibration; measured on tunnel_v:
#: 680 MB peak for 1.6 M beams) [bytes], and per footprint ray of a chunk of scans in flight [bytes].
BYTES_PER_BEAM = 320
BYTES_PER_CHUNK_RAY = 200
#: Refused above this estimate [bytes] (or 80 % of the machine's memory, if smaller).
MAX_SCENARIO_BYTES = 8 * 2**30


def estimate_memory_bytes(scenario: Scenario) -> tuple[int, int]:
    """(number of scans, bytes) a scenario needs: scans x beams x BYTES_PER_BEAM + a chunk's footprint rays."""
    se = scenario.sensor
    n_scans = int(math.ceil(servo_run_time_s(scenario.servo) / se.scan_period_s)) + 1
    chunk_rays = 16 * se.n_beams * se.footprint_rays
    return n_scans, n_scans * se.n_beams * BYTES_PER_BEAM + chunk_rays * BYTES_PER_CHUNK_RAY


def _memory_limit_bytes() -> int:
    try:
        physical = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return MAX_SCENARIO_BYTES
    return int(min(MAX_SCENARIO_BYTES, 0.8 * physical))


def check_resources(scenario: Scenario, source: str) -> None:
    """Refuse a scenario whose recording would not fit in memory, with the estimate and its factors."""
    n_scans, need = estimate_memory_bytes(scenario)
    limit = _memory_limit_bytes()
    if need > limit:
        se, sv = scenario.sensor, scenario.servo
        key, value = ("revolutions", sv.revolutions) if sv.mode == "spin" else ("passes", sv.passes)
        raise InputError(
            f"{source}: sensor/servo: this scenario needs about {need / 2**30:.3g} GiB ({n_scans:,} scans x "
            f"{se.n_beams:,} beams x {BYTES_PER_BEAM} bytes; scan_period_s {se.scan_period_s:g}, servo.{key} "
            f"{value:g}), more than the {limit / 2**30:.3g} GiB allowed: use fewer beams, {key} or a longer "
            "scan_period_s")


def require_markers(scenario: Scenario, command: str, reason: str) -> None:
    """Refuse a marker-less scenario for ``command`` (e.g. "lrfsim plan"), which needs markers because of
    ``reason``: InputError naming the scenario and the ``markers`` section."""
    if scenario.markers is None:
        raise InputError(f"{scenario.name}: markers: the scenario has no markers; {command} {reason} "
                         "(`lrfsim simulate` writes its recording)")


def with_changes(data: dict[str, Any], changes: dict[str, Any]) -> dict[str, Any]:
    """A deep copy of a scenario mapping with dotted-key changes applied, e.g. ``{"servo.passes": 4}``
    (missing sections are created); validate the result with :func:`parse_scenario`."""
    out = copy.deepcopy(data)
    for key, value in changes.items():
        node = out
        *path, last = key.split(".")
        for k in path:
            node = node.setdefault(k, {})
        node[last] = value
    return out


def load_scenario(path: str | Path) -> Scenario:
    """Read and validate a scenario YAML file. Relative mesh paths are resolved against the file's folder.

    Raises:
        InputError: unreadable or non-UTF-8 file, YAML syntax error (line and column), a field that is missing,
            unknown (the nearest valid key is suggested) or out of range, NaN or infinity, a recording that would
            not fit in memory.
    """
    path = Path(path)
    data = read_yaml(path, "scenario")
    if not isinstance(data, dict):
        raise InputError(f"{path}: expected a mapping of sections (name, rig, scene, markers, ...), got "
                         f"{type(data).__name__}")
    scenario = parse_scenario(data, str(path))
    check_resources(scenario, str(path))
    if scenario.scene.meshes:
        meshes = tuple(
            m.model_copy(
                update={"file": m.file if m.file.is_absolute() else (path.parent / m.file).resolve()}
            )
            for m in scenario.scene.meshes
        )
        scenario = scenario.model_copy(update={"scene": scenario.scene.model_copy(update={"meshes": meshes})})
    return scenario


def scenario_inputs(scenario: Scenario, path: str | Path) -> dict[str, Path]:
    """The files a scenario reads, ``{label: path}``: the scenario file and its meshes (no output may overlap
    them)."""
    out: dict[str, Path] = {"scenario": Path(path)}
    for i, m in enumerate(scenario.scene.meshes):
        out[f"scene.meshes[{i}].file"] = Path(m.file)
    return out


def dump_scenario(scenario: Scenario) -> str:
    """The effective scenario (all defaults filled in) as YAML."""
    return yaml.safe_dump(scenario.model_dump(mode="json"), sort_keys=False)

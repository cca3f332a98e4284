"""`lrfsim run`: simulate a scenario, calibrate the recording as a real one, compare with the ground truth.

DIR/recording/     what the simulated rig recorded (docs/formats.md)
DIR/calibration/   what `lrfcal calibrate` writes (calibration.yaml, rig.urdf, clouds, report, figures)
DIR/comparison.md  Tables I and III against the truth
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from rich.console import Console
from rich.table import Table

from lrfcal import CalibConfig, CalibrationResult
from lrfsim.scenario.file import Scenario
from lrfsim.scenario.sections import SensorConfig

from .compare import Comparison, compare, load_truth


@dataclass(frozen=True)
class LoopReport:
    out_dir: Path
    comparison: Comparison
    result: CalibrationResult
    timings_s: dict[str, float] = field(default_factory=dict)


def run_loop(
    scenario: Scenario,
    out_dir: Path,
    *,
    overwrite: bool = False,
    rrd_path: Path | None = None,
    spawn: bool = False,
    progress: Callable[[int, int], None] | None = None,
    stage_progress: Callable[[str], None] | None = None,
    warn: Callable[[str], None] | None = None,
) -> LoopReport:
    """Simulate, write the recording, calibrate it from disk as a real one, compare with the truth.

    Everything is built in a temporary folder beside ``out_dir`` and renamed into place when complete.
    ``rrd_path`` defaults to ``out_dir/rerun.rrd``. ``progress(done_scans, total)`` while simulating,
    ``stage_progress(stage)`` while calibrating; ``warn(line)`` when ``spawn`` is asked for but no viewer can
    start (the .rrd is saved all the same).
    """
    from lrfcal import calibrate_folder, viewer_can_spawn
    from lrfcal.io.files import atomic_folder
    from lrfsim.simulation.recording import check_output, write_recording
    from lrfsim.simulation.simulate import simulate
    from lrfsim.world.scene import build_scene

    out_dir = Path(out_dir)
    check_output(out_dir, overwrite)
    spawn = viewer_can_spawn(spawn, rrd_path or out_dir / "rerun.rrd", warn)
    timings: dict[str, float] = {}
    with atomic_folder(out_dir, "lrfsim run") as tmp:
        t0 = time.perf_counter()
        scene = build_scene(scenario)
        sim = simulate(scenario, progress, scene=scene)
        write_recording(sim, scenario, tmp / "recording")
        timings["simulate + write"] = time.perf_counter() - t0

        truth = load_truth(tmp / "recording" / "ground_truth.yaml")
        t0 = time.perf_counter()
        rrd_tmp = None if rrd_path is not None else tmp / "rerun.rrd"
        # the tunnel's dimensions (Table III) are measured only where the scene is a tunnel
        config = CalibConfig(geometry=scenario.scene.tunnel is not None)
        result = calibrate_folder(
            tmp / "recording", tmp / "calibration", truth=truth, rrd_path=rrd_path or rrd_tmp, spawn=spawn,
            scene=scene, progress=stage_progress, warn=warn, config=config,
        )
        timings["calibrate + write"] = time.perf_counter() - t0
        timings.update({f"  {k}": v for k, v in result.timings_s.items()})

        comparison = compare(result, truth, scenario.tolerances)
        (tmp / "comparison.md").write_text(comparison_markdown(comparison))
    return LoopReport(out_dir, comparison, result, timings)


def sensor_errors_line(sensor: SensorConfig) -> str:
    """One line for `lrfsim run`'s summary: whether the simulated scanner had systematic range errors (which, with
    their magnitudes) and where their cost is measured (docs/sensor_errors.md)."""
    c = sensor.systematic
    parts = [f"{what} {v * 1000:+g} {unit}" for what, v, unit in (
        ("offset", c.range_offset_m, "mm"), ("intensity", c.intensity_bias_m_per_decade, "mm/decade"),
        ("incidence", c.incidence_bias_m, "mm/rad"), ("drift", c.drift_amplitude_m, "mm")) if v != 0.0]
    if c.drift_amplitude_m != 0.0:
        parts[-1] += f" (tau {c.drift_time_constant_s:g} s)"
    if c.beam_wiggle_m != 0.0:
        parts.append(f"wiggle along the scan {c.beam_wiggle_m * 1000:g} mm every {c.beam_wiggle_period_beams:g} "
                     "beams")
    if c.range_wiggle_m != 0.0:
        parts.append(f"cyclic {c.range_wiggle_m * 1000:g} mm every {c.range_wiggle_period_m * 1000:g} mm of range")
    echoes = f"; multi-echo returns on {sensor.echoes.topic}" if sensor.echoes.enabled else ""
    if parts:
        return f"sensor: systematic range errors ON ({', '.join(parts)}){echoes}; their cost: docs/sensor_errors.md"
    return (f"sensor: idealised, no systematic range errors simulated{echoes}; their cost on a real scanner: "
            "docs/sensor_errors.md")


def _mm(v: float | None) -> str:
    return "-" if v is None else f"{v * 1000:+.2f}"


def _deg(v: float | None) -> str:
    return "-" if v is None else f"{math.degrees(v):+.4f}"


def _fmt(name: str, v: float | None) -> str:
    return _mm(v) if name in ("a", "b") else _deg(v)


def table_rows(c: Comparison) -> tuple[list[list[str]], list[list[str]]]:
    """Rows of Table I and Table III as strings (mm and deg)."""
    t1 = []
    for r in c.dh_rows:
        unit = "mm" if r.unit == "m" else "deg"
        t1.append(
            [
                f"{r.name} ({unit})",
                _fmt(r.name, r.truth),
                _fmt(r.name, r.ours),
                _fmt(r.name, r.error),
                _fmt(r.name, r.paper),
                _fmt(r.name, r.paper_error),
                "ok" if r.ok else "MISS",
            ]
        )
    if math.isfinite(c.mount_position_error_m):  # a targetless calibration estimates no mount
        t1.append(["mount xyz (mm)", "", "", _mm(c.mount_position_error_m), "", _mm(c.paper_mount_position_error_m),
                   "ok" if c.mount_position_error_m <= c.tolerances.position_m else "MISS"])
        t1.append(["mount rot (deg)", "", "", _deg(c.mount_rotation_error_rad), "",
                   _deg(c.paper_mount_rotation_error_rad),
                   "ok" if c.mount_rotation_error_rad <= c.tolerances.rotation_rad else "MISS"])
    t3 = [
        [
            f"{r.name.replace('_distance', '').replace('_', ' ')} (mm)",
            f"{r.truth * 1000:.1f}",
            "-" if r.calibrated is None else f"{r.calibrated * 1000:.1f}",
            "-" if r.calibrated is None else f"{(r.calibrated - r.truth) * 1000:+.1f}",
            "-" if r.nominal is None else f"{r.nominal * 1000:.1f}",
            "-" if r.nominal is None else f"{(r.nominal - r.truth) * 1000:+.1f}",
            "ok" if r.ok else "MISS",
        ]
        for r in c.tunnel_rows
    ]
    return t1, t3


T1_HEAD = ["parameter", "truth", "estimate", "error", "paper's method", "its error", "check"]
T3_HEAD = ["dimension", "truth", "calibrated", "error", "nominal", "error", "check"]


def comparison_markdown(c: Comparison) -> str:
    t1, t3 = table_rows(c)

    def md(head: list[str], rows: list[list[str]]) -> str:
        lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        lines += ["| " + " | ".join(r) + " |" for r in rows]
        return "\n".join(lines)

    parts = [
        "# Recovery against the ground truth",
        "",
        "## Table I: DH parameters and mount pose",
        "",
        md(T1_HEAD, t1),
        "",
    ]
    if t3:
        parts += ["## Table III: tunnel dimensions from the reprojected cloud", "", md(T3_HEAD, t3), ""]
    parts += ["Result: " + ("all within tolerance" if c.ok else "MISSED: " + "; ".join(c.failures)), ""]
    return "\n".join(parts)


def print_comparison(c: Comparison, console: Console) -> None:
    t1, t3 = table_rows(c)
    for title, head, rows in (
        ("Table I: DH parameters and mount pose", T1_HEAD, t1),
        ("Table III: tunnel dimensions from the clouds", T3_HEAD, t3),
    ):
        if not rows:
            continue
        table = Table(title=title)
        for h in head:
            table.add_column(h, justify="right" if h not in ("parameter", "dimension") else "left",
                             no_wrap=h in ("parameter", "dimension"))
        for r in rows:
            table.add_row(*r, style=None if r[-1] == "ok" else "red")
        console.print(table)

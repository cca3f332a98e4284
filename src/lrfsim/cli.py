"""``lrfsim``: simulate recordings of the rotating laser range finder.

    lrfsim simulate SCENARIO -o DIR [--overwrite]   write a recording folder (docs/formats.md)
    lrfsim run SCENARIO [-o DIR] [--rrd FILE]        simulate, calibrate, compare with the truth (Tables I, III)
    lrfsim plan SCENARIO [--json]                    predicted 1-sigma of every parameter (no calibration)
    lrfsim study SCENARIO --trials N [-o DIR]        Monte-Carlo study: errors, sigmas, refusals
    lrfsim schema                                    the scenario format as JSON Schema (docs/scenario.md)

Usage errors and the errors the project raises on purpose (lrfcal.errors.LrfError) become one line
``error: <message>`` on stderr and the exit code of lrfcal.errors (2 bad input). Heavy modules (mujoco,
rosbags) are imported inside the commands.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from lrfcal import Command, QuietOpt, finite_between, make_app, progress_display, run_app

if TYPE_CHECKING:
    from .scenario.file import Scenario
    from .simulation.result import SimResult

app = make_app("MuJoCo testbench of a servo-turned Hokuyo UTM-30LX-EW: simulate recordings, calibrate them and "
               "compare with the ground truth. Scenario format: docs/scenario.md or 'lrfsim schema'.", "lrfsim")

ScenarioArg = Annotated[Path, typer.Argument(help="Scenario YAML file (see scenarios/, docs/scenario.md).",
                                             metavar="SCENARIO", show_default=False)]


def _summary(result: SimResult, path: Path) -> None:
    """Print the recording's summary table to stdout."""
    import numpy as np
    from rich.console import Console
    from rich.table import Table

    s = result.stats
    S, N = result.ranges_m.shape
    valid = float(np.isfinite(result.ranges_m).mean())
    table = Table(title=f"recording {path.name}", show_header=False)
    rows = [
        ("scenario", result.name),
        ("scans", f"{S}"),
        ("beams per scan", f"{N}"),
        ("valid returns", f"{100 * valid:.1f} %"),
        ("joint states", f"{result.joints.stamps_s.size}"),
        ("markers", f"{len(result.truth.marker_ids)}"),
        ("tape pairs", f"{result.tape.pairs.shape[0]}"),
        ("duration", f"{result.duration_s:.2f} s"),
        ("rays cast", f"{s.n_rays:,} in {s.n_calls:,} mj_multiRay calls"),
        ("rays/s", f"{s.rays_per_s:,.0f} (lidar {s.lidar_time_s:.2f} s, simulate {s.total_time_s:.2f} s)"),
        ("batching", f"origin error <= {1e9 * s.max_origin_error_m:.0f} nm, direction error "
                     f"{s.max_direction_error_rad:.1e} rad"),
    ]
    for k, v in rows:
        table.add_row(k, v)
    console = Console()
    console.print(table)
    console.print(f"wrote {path}", markup=False)


@app.command(cls=Command)
def simulate(
    scenario: ScenarioArg,
    out: Annotated[Path, typer.Option("-o", "--out", metavar="DIR", show_default=False,
                                      help="Recording folder to write (atomically).")],
    overwrite: Annotated[bool, typer.Option("--overwrite",
                                            help="Replace a recording folder lrfsim wrote before.")] = False,
    quiet: QuietOpt = False,
) -> None:
    """Simulate SCENARIO and write a recording folder.

    The folder holds the bag, the tape distances, the nominal values and the ground truth (docs/formats.md).
    """
    from lrfcal.io.files import check_no_overlap

    from .scenario.file import load_scenario, scenario_inputs
    from .simulation.to_folder import simulate_to_folder

    sc = load_scenario(scenario)
    check_no_overlap({"-o": out}, scenario_inputs(sc, scenario))
    with progress_display(f"simulating {sc.name}", quiet=quiet) as hooks:
        result, path = simulate_to_folder(sc, out, overwrite=overwrite, progress=hooks.scans)
    _summary(result, path)


@app.command(cls=Command)
def run(
    scenario: ScenarioArg,
    out: Annotated[Path | None, typer.Option("-o", "--out", metavar="DIR", show_default=False,
                                             help="Output folder  [default: runs/<scenario name>]")] = None,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace an -o folder lrfsim wrote before.")
                         ] = False,
    rrd: Annotated[Path | None, typer.Option("--rrd", metavar="FILE", show_default=False,
                                             help="Save the rerun recording here  [default: DIR/rerun.rrd]")] = None,
    spawn: Annotated[bool, typer.Option("--spawn", help="Open the rerun viewer too.")] = False,
    quiet: QuietOpt = False,
) -> None:
    """Simulate, calibrate, compare with the truth.

    Simulates SCENARIO, calibrates the recording and compares with the ground truth (Tables I and III).

    Exit code 1 when the recovery misses the tolerances the scenario declares. Without -o, the folder
    runs/<name> of an earlier run is replaced, but only if lrfsim wrote everything in it.
    """
    from rich.console import Console

    from lrfcal import print_summary
    from lrfcal.io.files import check_no_overlap

    from .scenario.file import load_scenario, scenario_inputs
    from .trials.closed_loop import print_comparison, run_loop, sensor_errors_line

    sc = load_scenario(scenario)
    default_out = out is None
    if out is None:
        out, overwrite = Path("runs") / sc.name, True
    check_no_overlap({"-o": out, "--rrd": rrd}, scenario_inputs(sc, scenario))
    check_no_overlap({"--rrd": rrd}, {"output folder": out})
    replaced = default_out and out.is_dir() and any(out.iterdir())
    with progress_display(f"simulating {sc.name}", quiet=quiet) as hooks:
        report = run_loop(sc, out, overwrite=overwrite, rrd_path=rrd, spawn=spawn, progress=hooks.scans,
                          stage_progress=hooks.stage, warn=lambda line: print(f"warning: {line}", file=sys.stderr))
    console = Console()
    print_summary(report.result, console)
    print_comparison(report.comparison, console)
    console.print(sensor_errors_line(sc.sensor), markup=False, soft_wrap=True)
    console.print("timings: " + ", ".join(f"{k} {v:.2f} s" for k, v in report.timings_s.items()
                                          if not k.startswith(" ")), markup=False)
    console.print(f"wrote {report.out_dir} (recording/, calibration/, comparison.md"
                  + (", rerun.rrd)" if rrd is None else f"); rerun: {rrd}")
                  + (" replacing the previous run" if replaced else ""), markup=False)
    if not report.comparison.ok:
        console.print("MISSED: " + "; ".join(report.comparison.failures), style="red", markup=False)
        raise typer.Exit(1)


@app.command(cls=Command)
def plan(
    scenario: ScenarioArg,
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object (SI units) instead of the table.")
                       ] = False,
    range_sigma: Annotated[float | None, typer.Option(
        "--range-sigma", metavar="M", callback=finite_between(1e-5, 1.0, "m"), show_default=False,
        help="Range noise 1-sigma [m]  [default: the scenario's sensor noise at the marker returns, 0.01 for "
             "the UTM-30LX-EW]")] = None,
    markers_only: Annotated[bool, typer.Option(
        "--markers-only", help="Predict from the marker returns alone (without the surface returns).")] = False,
    false_alarm: Annotated[float, typer.Option(
        "--false-alarm", metavar="P", callback=finite_between(1e-6, 0.49, ""),
        help="The false-alarm rate of `lrfcal check` for the smallest drift it detects.")] = 0.05,
    quiet: QuietOpt = False,
) -> None:
    """Predict the accuracy of a layout and sweep before building it.

    Casts the scenario's rays once without noise and inverts the Fisher information of the calibration's own
    observation model at the true parameters: the predicted 1-sigma of x, y, z, rx, ry, rz (rotation vector in
    frame M), a, alpha, b, beta and the clock offset (when the sweep goes both ways), the weakest direction and
    what would strengthen it, whether the scenario's tolerances are reachable (>= 4 predicted sigma), and, for
    SCENARIO as the new recording of `lrfcal check` against a calibration of the same layout, the smallest drift of
    each tested parameter the check detects with 95 % probability at --false-alarm.

    Exit code 3 when the DH parameters are not determined (the calibration would refuse).
    """
    import json
    import time
    from dataclasses import replace

    from .plan.sparse_cast import sparse_geometry
    from .scenario.file import load_scenario, require_markers

    sc = load_scenario(scenario)
    require_markers(sc, "lrfsim plan", "predicts from the marker returns")
    with progress_display(f"planning {sc.name}: casting the rays, inverting the information", quiet=quiet):
        t0 = time.perf_counter()
        # the prediction's modules (scipy, lrfcal's estimate) are imported while a forked helper casts
        geometry = sparse_geometry(sc, meanwhile=_import_prediction)
        from .plan.prediction import plan as make_plan
        from .plan.text import format_plan

        result = make_plan(sc, range_sigma_m=range_sigma, surfaces=not markers_only, geometry=geometry)
        result = replace(result, seconds=time.perf_counter() - t0)  # the cast's time too
    if as_json:
        data = result.to_json()
        data["check_detects_95"] = {n: (v if v != float("inf") else None)
                                    for n, v in result.check_detects(false_alarm).items()}
        data["check_false_alarm"] = false_alarm
        print(json.dumps(data, indent=2))
    else:
        print(format_plan(result, false_alarm))
    if not result.determined:  # calibrate's rule (lrfcal.estimate.observability.Verdict), its reason
        why = result.verdict.reason() or "a DH parameter has no finite sigma"
        print(f"error: {result.scenario}: the calibration would refuse: {why}", file=sys.stderr)
        raise typer.Exit(3)


def _import_prediction() -> None:
    """Import what `lrfsim plan` predicts with: lrfsim.plan.prediction, the parts of lrfcal it uses and the
    calibration's marker detection (lrfsim.simulation.faults.detected_mask), which imports scipy.ndimage. scipy's BLAS
    is limited as it loads (the thread policy's variables, set as the command started: lrfcal.runtime.threads)."""
    import lrfcal
    import lrfsim.plan.prediction  # noqa: F401

    _ = lrfcal.detect


@app.command(cls=Command)
def study(
    scenario: ScenarioArg,
    trials: Annotated[int, typer.Option("--trials", "-n", metavar="N", min=1, max=100000, show_default=False,
                                        help="Number of Monte-Carlo trials (per varied value).")],
    out: Annotated[Path | None, typer.Option("-o", "--out", metavar="DIR", show_default=False,
                                             help="Output folder  [default: runs/<scenario name>_study]")] = None,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace an -o folder lrfsim wrote before.")
                         ] = False,
    workers: Annotated[int, typer.Option("--workers", "-j", metavar="K", min=1, max=1024,
                                         help="Local worker processes (1: in this process)  [default: 1]",
                                         show_default=False)] = 1,
    dask: Annotated[str | None, typer.Option("--dask", metavar="ADDRESS", show_default=False,
                                             help="Run the trials on this dask.distributed scheduler "
                                                  "(e.g. tcp://host:8786), in batches of trials.")] = None,
    vary: Annotated[str | None, typer.Option("--vary", metavar="KEY=V1,V2,...", show_default=False,
                                             help="Sweep one scenario field (dotted path), e.g. "
                                                  "servo.passes=1,2,4 or faults.range_noise_scale=1,2.")] = None,
    seed0: Annotated[int | None, typer.Option("--seed0", metavar="S", min=0, show_default=False,
                                              help="Seed of trial 0; trial k uses S + k  [default: the "
                                                   "scenario's seed]")] = None,
    recast: Annotated[bool, typer.Option("--recast", help="Cast the rays anew for every trial (a new laser phase "
                                         "per trial) instead of reusing one noise-free cast.")] = False,
    new_layout: Annotated[bool, typer.Option("--new-layout", help="Build every trial's marker layout from its own "
                                             "seed too (the jitter_m of a board or a V, a random layout) and "
                                             "cast anew: the accuracy over layouts, not of one.")] = False,
    drift: Annotated[list[str] | None, typer.Option(
        "--drift", metavar="NAME=VALUE", show_default=False,
        help="The drift's Monte Carlo (repeatable): N pairs, a recording calibrated and a second one of the rig "
             "changed by NAME=VALUE (a, alpha, b, beta, x, y, z, roll, pitch, yaw, clock_offset, range_offset; "
             "units mm, deg, ms, ...; several joined by commas) checked against it by `lrfcal check`; 'none': no "
             "drift, the false-alarm rate. Works without markers too (targetless).")] = None,
    false_alarm: Annotated[float, typer.Option(
        "--false-alarm", metavar="P", callback=finite_between(1e-6, 0.49, ""),
        help="With --drift: the check's false-alarm rate.")] = 0.05,
    fixed_mount: Annotated[bool, typer.Option("--fixed-mount", help="With --drift: the check tests the mount too.")
                           ] = False,
    perturb_start: Annotated[float, typer.Option(
        "--perturb-start", metavar="S", min=0.0, max=100.0, show_default=False,
        help="Start each trial from the nominal values moved by uniform draws in +-S x (a, b: 5 mm; alpha, beta: "
             "1 deg; mount: 2 cm, 1 deg), drawn from the trial's seed  [default: 0, the scenario's nominal "
             "values]")] = 0.0,
    truth_spread: Annotated[float, typer.Option(
        "--truth-spread", metavar="S", min=0.0, max=100.0, show_default=False,
        help="Draw each trial's true DH around the nominal DH, uniform in +-S x (a, b: 5 mm; alpha, beta: 1.5 "
             "deg), from the trial's seed (each trial builds its scene and casts anew)  [default: 0, the "
             "scenario's truth]")] = 0.0,
    force: Annotated[bool, typer.Option(
        "--force", help="Calibrate every trial as 'lrfcal calibrate --force' does: a failed check recorded, not "
                        "refused, so RMS of error / sigma is over the trials the checks would refuse too (near a "
                        "limit, those with the larger errors)")] = False,
    quiet: QuietOpt = False,
) -> None:
    """Monte-Carlo study: calibrate N noisy recordings of SCENARIO.

    Trial k simulates SCENARIO with seed S + k (new range, intensity, tape and encoder noise; the marker layout
    stays; the rays are cast once and reused, see --recast), writes and reads the recording back and calibrates
    it (a marker-less scenario targetless, as `lrfcal calibrate REC --targetless` does); --perturb-start S also
    moves each trial's nominal values (its nominal.yaml, where the calibration starts), --truth-spread S draws
    each trial's true DH around the nominal. Writes DIR/trials.csv (one row per trial:
    status, reason, P_error and P_sigma in SI units for each DH parameter P), DIR/summary.md (bias, std, RMSE,
    the predicted sigma of 'lrfsim plan', RMSE / predicted, RMS of error / reported sigma, refusal rate) and
    histograms DIR/hist_P.png. The same seeds give the same trials.csv with any --workers or --dask.
    """
    from lrfcal import keep_freed_memory
    from lrfcal.io.files import check_no_overlap, check_replaceable

    from .scenario.file import load_scenario, scenario_inputs
    from .trials.variants import parse_vary, with_field

    sc = load_scenario(scenario)
    if drift:
        _drift_study(sc, scenario, drift, trials, out, overwrite, workers, seed0, false_alarm, fixed_mount, quiet)
        return
    varied = parse_vary(vary) if vary is not None else None
    if out is None:
        out, overwrite = Path("runs") / f"{sc.name}_study", True
    check_no_overlap({"-o": out}, scenario_inputs(sc, scenario))
    check_replaceable(out, overwrite)
    if varied is not None:  # every value must make a valid scenario before any trial runs
        for v in varied[1]:
            with_field(sc, varied[0], v)
    # the trials' modules (the simulator, the calibration) once the inputs are judged: bad input answers without them
    from .trials.study import study as run_study
    from .trials.study_figures import import_figures
    from .trials.study_result import summary_markdown, write_study

    values = [""] if varied is None else [str(v) for v in varied[1]]  # the parts' labels, as lrfsim.trials.study's
    keep_freed_memory()  # the trials' large arrays reused, not faulted in anew (lrfcal.runtime.memory)
    with progress_display(f"study of {sc.name}", quiet=quiet) as hooks:
        result = run_study(sc, trials, seed0=seed0, workers=workers, dask=dask, vary=varied, recast=recast,
                           progress=lambda value, done, _n: hooks.trials(values.index(value) * trials + done,
                                                                        len(values) * trials),
                           perturb_start=perturb_start, new_layout=new_layout, truth_spread=truth_spread,
                           # the figures' imports while the workers run, not after them with one core idle
                           force=force, meanwhile=import_figures)
        hooks.stage("trials.csv, summary.md and figures")
        path = write_study(result, out, overwrite=overwrite)
    print(summary_markdown(result).split("## Figures")[0].rstrip())
    print(f"wrote {path} (trials.csv, summary.md, figures)")


def _drift_study(sc: Scenario, path: Path, drifts: list[str], pairs: int, out: Path | None, overwrite: bool,
                 workers: int, seed0: int | None, false_alarm: float, fixed_mount: bool, quiet: bool) -> None:
    """`lrfsim study --drift`: the drift's Monte Carlo (lrfsim.trials.drift), pairs.csv and summary.md."""
    from lrfcal.io.files import check_no_overlap, check_replaceable

    from .scenario.file import scenario_inputs
    from .trials.drift import drift_study, parse_drift, summary_markdown, write_drift_study

    parsed = [parse_drift(d) for d in drifts]
    if out is None:
        out, overwrite = Path("runs") / f"{sc.name}_drift", True
    check_no_overlap({"-o": out}, scenario_inputs(sc, path))
    check_replaceable(out, overwrite)
    with progress_display(f"drift study of {sc.name}", quiet=quiet) as hooks:
        result = drift_study(sc, parsed, pairs, seed0=seed0, workers=workers, false_alarm=false_alarm,
                             fixed_mount=fixed_mount, progress=lambda done, n: hooks.steps("pairs", done, n))
        written = write_drift_study(result, out, overwrite=overwrite)
    print(summary_markdown(result).rstrip())
    print(f"wrote {written} (pairs.csv, summary.md)")


@app.command(cls=Command)
def schema(
    markdown: Annotated[bool, typer.Option("--markdown", help="Print the page docs/scenario.md instead.")] = False,
) -> None:
    """Print the scenario format (JSON Schema).

    Every field with its unit, default and bounds; --markdown prints docs/scenario.md.
    """
    if markdown:
        from .scenario.markdown_page import scenario_markdown

        print(scenario_markdown(), end="")
        return
    import json

    from .scenario.file import Scenario

    print(json.dumps(Scenario.model_json_schema(), indent=2))


def main(argv: list[str] | None = None) -> None:
    """Entry point: usage errors and any LrfError become one line on stderr and their exit code.

    The program renders nothing with mujoco (it casts rays; rerun draws), so mujoco's OpenGL context (glfw, 0.03 s
    of every command that imports mujoco) is not loaded: MUJOCO_GL=disable, unless the environment sets it. Only
    for the program's own process (``argv`` None: the console script), not for a caller's."""
    if argv is None:
        os.environ.setdefault("MUJOCO_GL", "disable")
    run_app(app, argv, "lrfsim")


if __name__ == "__main__":
    main()

"""`lrfcal`: calibrate a rotating laser range finder from a recording (thin CLI over lrfcal.app)."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated

import typer

from .errors import LrfError

app = typer.Typer(add_completion=False, no_args_is_help=True, help=__doc__)


@app.callback()
def _root() -> None:
    """Calibration of a servo-turned 2D laser range finder from reflective markers."""


@app.command("calibrate")
def calibrate_cmd(
    recording: Annotated[Path, typer.Argument(help="Recording folder (bag/, distances.csv, nominal.yaml).")],
    out: Annotated[Path, typer.Option("-o", "--out", help="Output folder (written atomically).")],
    bag: Annotated[
        Path | None, typer.Option(help="Bag to read instead of RECORDING/bag (ROS 1 .bag or ROS 2).")
    ] = None,
    distances: Annotated[
        Path | None, typer.Option(help="Tape distances CSV (default RECORDING/distances.csv).")
    ] = None,
    nominal: Annotated[
        Path | None, typer.Option(help="Nominal values YAML (default RECORDING/nominal.yaml).")
    ] = None,
    range_sigma: Annotated[
        float, typer.Option(help="Range noise sigma [m] of the scanner.", min=1e-5)
    ] = 0.010,
    clock_offset: Annotated[float, typer.Option(help="Laser stamp minus servo stamp [s], if known.")] = 0.0,
    no_baseline: Annotated[bool, typer.Option("--no-baseline", help="Skip the paper's variant.")] = False,
    overwrite: Annotated[bool, typer.Option(help="Replace an existing output folder.")] = False,
    rrd: Annotated[
        Path | None, typer.Option("--rrd", help="Save a rerun recording (.rrd), headless.")
    ] = None,
    spawn: Annotated[bool, typer.Option("--spawn", help="Open the rerun viewer.")] = False,
) -> None:
    """Calibrate the 10 parameters from RECORDING and write calibration.yaml, rig.urdf, clouds and a report."""
    from rich.console import Console

    from .app import calibrate_folder
    from .pipeline import CalibConfig

    console = Console()
    config = CalibConfig(range_sigma_m=range_sigma, clock_offset_s=clock_offset, baseline=not no_baseline)
    result = calibrate_folder(
        recording,
        out,
        bag=bag,
        distances=distances,
        nominal=nominal,
        config=config,
        overwrite=overwrite,
        rrd_path=rrd,
        spawn=spawn,
    )
    print_summary(result, console)
    console.print(f"wrote {out}")


def print_summary(result, console) -> None:  # type: ignore[no-untyped-def]
    """Estimated parameters with 1-sigma, residual RMS and stage timings."""
    import math

    from rich.table import Table

    from .kinematics import ANGLE_NAMES, PARAM_NAMES

    sol = result.solution
    table = Table(title=f"Calibration ({sol.n_observations} marker returns, {sol.status})")
    for h in ("parameter", "start", "estimate", "1-sigma", "paper's method"):
        table.add_column(h, justify="right")
    start, est = result.start.vector(), sol.params.vector()
    paper = None if result.baseline is None else result.baseline.params.vector()
    for i, n in enumerate(PARAM_NAMES):
        f, unit = (math.degrees, "deg") if n in ANGLE_NAMES else ((lambda v: v * 1000), "mm")
        table.add_row(
            f"{n} ({unit})",
            f"{f(start[i]):.3f}",
            f"{f(est[i]):.3f}",
            f"{f(sol.sigma[i]):.3f}",
            "-" if paper is None else f"{f(paper[i]):.3f}",
        )
    console.print(table)
    console.print(
        f"residual RMS {sol.residual_rms_m * 1000:.2f} mm over {len(set(result.observations.marker.tolist()))} "
        f"markers; stages: " + ", ".join(f"{k} {v:.2f}s" for k, v in result.timings_s.items())
    )


# --- real rigs' bags: inspect and reproject (issue 8) -------------------------------------------------------

ScanTopicOpt = Annotated[str | None, typer.Option(
    "--scan-topic", help="Topic of the scans (rig file scan.topic; default /scan).")]
ScanFieldOpt = Annotated[str | None, typer.Option(
    "--scan-field", help="Dotted path of a LaserScan inside a larger message (scan.field; default: none, the "
    "topic is a sensor_msgs/LaserScan).")]
ScanStampOpt = Annotated[str | None, typer.Option(
    "--scan-stamp", help="header | receive: scan time from header.stamp or the bag's receive time "
    "(scan.stamp; default header).")]
ServoTopicOpt = Annotated[str | None, typer.Option(
    "--servo-topic", help="Topic of the servo angle (servo.topic; default /joint_states).")]
ServoFieldOpt = Annotated[str | None, typer.Option(
    "--servo-field", help="Dotted path of the numeric angle field (servo.field; default data for std_msgs, "
    "current_pos for dynamixel_msgs/JointState).")]
JointOpt = Annotated[str | None, typer.Option(
    "--joint", help="Joint name in sensor_msgs/JointState (servo.joint; default servo).")]
UnitOpt = Annotated[str | None, typer.Option(
    "--unit", help="rad | deg | counts: unit of the recorded angle (servo.unit; default rad).")]
CountsOpt = Annotated[float | None, typer.Option(
    "--counts-per-rev", help="Encoder counts per revolution with --unit counts (e.g. 4096).")]
SignOpt = Annotated[int | None, typer.Option(
    "--sign", help="1 or -1: -1 when the servo turns the other way (servo.sign; default 1).")]
OffsetOpt = Annotated[float | None, typer.Option(
    "--servo-offset", help="Added after unit and sign (rad): the angle at lambda = 0 (servo.offset_rad; "
    "default 0).")]
ServoStampOpt = Annotated[str | None, typer.Option(
    "--servo-stamp", help="header | receive | scan: servo sample time; scan = the angle is a field of the scan's "
    "message (servo.stamp; default header).")]
TfParentOpt = Annotated[str | None, typer.Option(
    "--tf-parent", help="Take the angle from /tf: the parent frame (servo.tf.parent; with --tf-child).")]
TfChildOpt = Annotated[str | None, typer.Option("--tf-child", help="Child frame in /tf (servo.tf.child).")]
TfAxisOpt = Annotated[str | None, typer.Option(
    "--tf-axis", help="x | y | z: rotation axis of the tf joint in the parent frame (default z).")]


@app.command("inspect")
def inspect_cmd(
    bag: Annotated[Path, typer.Argument(help="ROS 1 .bag file or ROS 2 bag folder (sqlite3 or MCAP).")],
    nominal: Annotated[Path | None, typer.Option(
        "--nominal", help="Rig file (nominal.yaml) saying where the data are; default: guess from the bag.")] = None,
    scan_topic: ScanTopicOpt = None, scan_field: ScanFieldOpt = None, scan_stamp: ScanStampOpt = None,
    servo_topic: ServoTopicOpt = None, servo_field: ServoFieldOpt = None, joint: JointOpt = None,
    unit: UnitOpt = None, counts_per_rev: CountsOpt = None, sign: SignOpt = None, servo_offset: OffsetOpt = None,
    servo_stamp: ServoStampOpt = None, tf_parent: TfParentOpt = None, tf_child: TfChildOpt = None,
    tf_axis: TfAxisOpt = None,
) -> None:
    """Show what BAG holds: topics, types, counts, rates, scan geometry, the servo angle's range and rate, the
    clocks and their offset, the problems found, and the rig-file snippet (YAML) that reads it."""
    from rich.console import Console

    from .inspection import inspect_bag
    from .rig import load_rig, with_overrides

    rig = load_rig(nominal) if nominal is not None else None
    scan, servo = with_overrides(
        rig.scan_source() if rig else None, rig.servo_source() if rig else None, scan_topic=scan_topic,
        scan_field=scan_field, scan_stamp=scan_stamp, servo_topic=servo_topic, servo_field=servo_field,
        joint=joint, unit=unit, counts_per_rev=counts_per_rev, sign=sign, servo_offset=servo_offset,
        servo_stamp=servo_stamp, tf_parent=tf_parent, tf_child=tf_child, tf_axis=tf_axis)
    result = inspect_bag(bag, scan, servo, dh=rig.dh.model_dump() if rig else None)  # type: ignore[arg-type]
    print_inspection(result, Console())


def print_inspection(result, console) -> None:  # type: ignore[no-untyped-def]
    """Print a lrfcal.inspection.BagInspection with rich tables."""
    import math

    from rich.syntax import Syntax
    from rich.table import Table

    console.print(f"[bold]{result.path}[/bold]: ROS {result.ros_version} bag, {result.duration_s:.1f} s")
    t = Table(title="Topics")
    for h in ("topic", "type", "messages", "rate [Hz]", "header", "receive - stamp [s]"):
        t.add_column(h, justify="left" if h in ("topic", "type") else "right", overflow="fold")
    for tp in result.topics:
        t.add_row(tp.topic, tp.msgtype, str(tp.count), "-" if tp.rate_hz is None else f"{tp.rate_hz:.2f}",
                  "yes" if tp.has_header else "no",
                  "-" if tp.receive_minus_stamp_s is None else f"{tp.receive_minus_stamp_s:+.3f}")
    console.print(t)
    g = result.geometry
    if g is not None:
        deg = math.degrees
        console.print(
            f"scans: {g.n_messages} messages, {g.beam_count[0]}-{g.beam_count[1]} beams; angle_min "
            f"{deg(g.angle_min_rad[0]):.2f}..{deg(g.angle_min_rad[1]):.2f} deg, angle_max "
            f"{deg(g.angle_max_rad[0]):.2f}..{deg(g.angle_max_rad[1]):.2f} deg, angle_increment "
            f"{deg(g.angle_increment_rad[0]):.4f}..{deg(g.angle_increment_rad[1]):.4f} deg; time_increment "
            f"{g.time_increment_s[0]:.3g}..{g.time_increment_s[1]:.3g} s; scan_time {g.scan_time_s[0]:.3g} s; "
            f"range {g.range_min_m:.3g}..{g.range_max_m:.3g} m; intensities {'yes' if g.has_intensities else 'no'}")
    if result.servo is not None:
        sv = result.servo
        rate = "-" if sv.rate_hz is None else f"{sv.rate_hz:.2f} Hz"
        console.print(f"servo: {sv.n_samples} samples at {rate}, {math.degrees(sv.min_rad):.2f}.."
                      f"{math.degrees(sv.max_rad):.2f} deg, median speed {math.degrees(sv.median_speed_rad_s):.2f} "
                      f"deg/s ({result.servo_source.describe()})")
    if result.report is not None:
        r = result.report
        applied = "applied" if r.clock_offset_applied else "not applied: below 1 s, left to the fine offset"
        console.print(f"clocks: laser-minus-servo offset {r.clock_offset_s:+.6f} s from the receive times "
                      f"({applied}); "
                      f"{result.n_scans_covered} of {r.n_scans} scans covered by the servo samples")
    if result.problems:
        console.print("[bold]problems[/bold]:")
        for p in result.problems:
            console.print(f"  - {p}", markup=False)
    console.print("[bold]rig file[/bold] (nominal.yaml) that reads this bag:")
    console.print(Syntax(result.rig_snippet, "yaml"))


@app.command("reproject")
def reproject_cmd(
    bag: Annotated[Path, typer.Argument(help="ROS 1 .bag file or ROS 2 bag folder (sqlite3 or MCAP).")],
    nominal: Annotated[Path, typer.Option(
        "--nominal", help="Rig file (nominal.yaml): nominal DH and where the data are in the bag.")],
    out: Annotated[Path, typer.Option("-o", "--out", help="Output PLY (binary; x y z (m) in frame M, "
                                      "intensity, time (s), scan, beam per point; written atomically).")],
    calibration: Annotated[Path | None, typer.Option(
        "--calibration", help="calibration.yaml whose dh replaces the rig file's nominal DH.")] = None,
    rrd: Annotated[Path | None, typer.Option("--rrd", help="Also save a rerun recording (.rrd).")] = None,
    bag_out: Annotated[Path | None, typer.Option(
        "--bag-out", help="Also write a ROS 2 bag (MCAP) of sensor_msgs/msg/PointCloud2 on /lrf_cloud, one "
        "cloud per sweep (frame lrf_motor).")] = None,
    clock_offset: Annotated[float, typer.Option(
        "--clock-offset", help="Fine laser-minus-servo clock offset (s) on top of the reader's coarse one "
        "(default 0).")] = 0.0,
    scan_topic: ScanTopicOpt = None, scan_field: ScanFieldOpt = None, scan_stamp: ScanStampOpt = None,
    servo_topic: ServoTopicOpt = None, servo_field: ServoFieldOpt = None, joint: JointOpt = None,
    unit: UnitOpt = None, counts_per_rev: CountsOpt = None, sign: SignOpt = None, servo_offset: OffsetOpt = None,
    servo_stamp: ServoStampOpt = None, tf_parent: TfParentOpt = None, tf_child: TfChildOpt = None,
    tf_axis: TfAxisOpt = None,
) -> None:
    """Turn BAG into a 3D cloud in the motor frame M: every beam at its own time and motor angle, with the
    calibrated DH (--calibration) or the rig file's nominal DH. Needs no tape distances."""
    from rich.console import Console
    from rich.progress import Progress

    from .cloud import reproject_bag

    console = Console(stderr=True)
    options = {k: v for k, v in dict(
        scan_topic=scan_topic, scan_field=scan_field, scan_stamp=scan_stamp, servo_topic=servo_topic,
        servo_field=servo_field, joint=joint, unit=unit, counts_per_rev=counts_per_rev, sign=sign,
        servo_offset=servo_offset, servo_stamp=servo_stamp, tf_parent=tf_parent, tf_child=tf_child,
        tf_axis=tf_axis).items() if v is not None}
    with Progress(console=console, transient=True) as bar:
        tasks: dict[str, object] = {}

        def progress(stage: str, done: int, total: int) -> None:
            if stage not in tasks:
                tasks[stage] = bar.add_task(stage, total=max(total, 1))
            bar.update(tasks[stage], completed=done, total=max(total, 1))  # type: ignore[arg-type]

        summary = reproject_bag(bag, nominal, out, calibration=calibration, rrd=rrd, bag_out=bag_out,
                                clock_offset_s=clock_offset, options=options, progress=progress,
                                warn=lambda text: console.print(f"warning: {text}", markup=False))
    for line in summary:
        console.print(line, markup=False)


def main() -> None:
    """Console entry point: any LrfError becomes one line on stderr and exit code 2."""
    try:
        app(standalone_mode=False)
    except LrfError as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(e.exit_code)
    except typer.Exit as e:
        sys.exit(e.exit_code)
    except Exception as e:  # click usage errors
        import click

        if isinstance(e, click.exceptions.ClickException):
            e.show()
            sys.exit(e.exit_code)
        if isinstance(e, click.exceptions.Abort):
            sys.exit(1)
        raise


if __name__ == "__main__":
    main()

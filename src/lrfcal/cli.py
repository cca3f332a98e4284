"""``lrfcal``: calibrate a servo-turned 2D laser range finder from a recording with reflective markers.

Exit codes: 0 done (``check``: still valid); 2 bad input or usage (one line ``error: ...`` on stderr); 3 the data do
not support a trustworthy calibration (one line naming the check); 4 ``check`` only: the rig drifted.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from lrfcal.terminal.cliutil import Command, QuietOpt, finite_between, make_app, run_app
from lrfcal.terminal.progress import progress_display

if TYPE_CHECKING:  # the types print_inspection prints (imported by the command that runs, not at start-up)
    from rich.console import Console

    from lrfcal.commands.inspect_bag import BagInspection

app = make_app(
    "Calibrate a servo-turned 2D laser range finder from reflective markers (the mount pose [m, rad] and the "
    "DH parameters a, alpha, b, beta of the scan plane) or from the scene's planes (the DH parameters). "
    "Formats: docs/formats.md.", "lrfcal"
)


@app.command("calibrate", cls=Command)
def calibrate_cmd(
    recording: Annotated[Path, typer.Argument(
        help="Recording folder (bag/ or one scan log, distances.csv, nominal.yaml), or a scan log.",
        metavar="RECORDING", show_default=False)],
    out: Annotated[Path, typer.Option("-o", "--out", metavar="DIR", show_default=False,
                                      help="Output folder (written atomically; must not overlap an input).")],
    bag: BagOpt = None,
    distances: DistancesOpt = None,
    nominal: Annotated[Path | None, typer.Option(metavar="YAML", show_default=False,
                                                 help="Nominal values  [default: RECORDING/nominal.yaml]")] = None,
    range_sigma: Annotated[float | None, typer.Option(
        metavar="M", callback=finite_between(1e-5, 1.0, "m"), show_default=False,
        help="Range noise sigma of the scanner [m], 1e-5..1  [default: the rig file's range_sigma_m, else 0.01]")
                           ] = None,
    clock_offset: Annotated[float, typer.Option(metavar="S", callback=finite_between(-10.0, 10.0, "s"),
                                                help="Laser stamp minus servo stamp [s], if known, -10..10.")
                            ] = 0.0,
    no_baseline: Annotated[bool, typer.Option("--no-baseline", help="Skip the paper's method.")] = False,
    overwrite: Annotated[bool, typer.Option("--overwrite",
                                            help="Replace an output folder lrfcal wrote before.")] = False,
    rrd: Annotated[Path | None, typer.Option("--rrd", metavar="FILE", show_default=False,
                                             help="Save a rerun recording (.rrd), headless.")] = None,
    spawn: Annotated[bool, typer.Option("--spawn", help="Open the rerun viewer (else save DIR/rerun.rrd).")
                     ] = False,
    no_range_bias: Annotated[bool, typer.Option(
        "--no-range-bias", help="Hold the range offset and the marker-return range bias at 0 (by default both are "
        "estimated wherever the surfaces the markers sit on separate them).")] = False,
    no_figures: Annotated[bool, typer.Option(
        "--no-figures", help="Do not draw the report's PNG figures (faster, for scripts).")] = False,
    force: Annotated[bool, typer.Option("--force", help="Write the result even when a consistency check fails "
                                        "(the failed checks are recorded in calibration.yaml and the report).")
                     ] = False,
    targetless: Annotated[bool, typer.Option(
        "--targetless", help="Calibrate from the flatness of the scene's planes, without markers (also chosen when "
        "there are no tape distances); the DH parameters the scene does not determine are held and named.")
                          ] = False,
    all_planes: Annotated[bool, typer.Option(
        "--all-planes", help="With markers: every other plane of the scene joins the markers' surfaces in the joint "
        "solve as a free plane (stage 6b generalised; a few seconds more).")] = False,
    compare_targetless: Annotated[bool, typer.Option(
        "--compare-targetless", help="With markers: also calibrate the recording from its planes alone and show the "
        "methods side by side in the report.")] = False,
    range_pattern: Annotated[bool, typer.Option(
        "--range-pattern", help="Targetless: estimate the scanner's range error along the scan with the DH (a range "
        "offset per 6 beams, its slow part held), as the URG-04LX needs (docs/real-data.md); sigma a little wider.")
                             ] = False,
    scan_topic: ScanTopicOpt = None, scan_field: ScanFieldOpt = None, scan_stamp: ScanStampOpt = None,
    servo_topic: ServoTopicOpt = None, servo_field: ServoFieldOpt = None, joint: JointOpt = None,
    unit: UnitOpt = None, counts_per_rev: CountsOpt = None, sign: SignOpt = None, servo_offset: OffsetOpt = None,
    servo_stamp: ServoStampOpt = None, tf_parent: TfParentOpt = None, tf_child: TfChildOpt = None,
    tf_axis: TfAxisOpt = None, quiet: QuietOpt = False,
) -> None:
    """Calibrate the rig from RECORDING (markers and tape distances, or --targetless: the scene's planes).

    Writes calibration.yaml, rig.urdf, the clouds before/after, report.md and its figures into DIR. Exit code 3
    (nothing written) when the data do not support a trustworthy calibration: the one line names the check.
    """
    from rich.console import Console

    from lrfcal.commands.calibrate import calibrate_folder
    from lrfcal.config import CalibConfig
    from lrfcal.report.summary import print_summary

    console = Console()
    config = CalibConfig(range_sigma_m=range_sigma, clock_offset_s=clock_offset, baseline=not no_baseline,
                         force=force, estimate_range_bias=not no_range_bias, targetless=True if targetless else None,
                         compare_targetless=compare_targetless, all_planes=all_planes, range_pattern=range_pattern)
    options = {k: v for k, v in dict(
        scan_topic=scan_topic, scan_field=scan_field, scan_stamp=scan_stamp, servo_topic=servo_topic,
        servo_field=servo_field, joint=joint, unit=unit, counts_per_rev=counts_per_rev, sign=sign,
        servo_offset=servo_offset, servo_stamp=servo_stamp, tf_parent=tf_parent, tf_child=tf_child,
        tf_axis=tf_axis).items() if v is not None}
    with progress_display(f"calibrating {recording.name}", quiet=quiet) as hooks:
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
            progress=hooks.stage,
            warn=lambda line: print(f"warning: {line}", file=sys.stderr),
            options=options,
            figures=not no_figures,
        )
    print_summary(result, console)
    console.print(f"wrote {out}", markup=False)


BagOpt = Annotated[Path | None, typer.Option(
    "--bag", metavar="PATH", show_default=False,
    help="Bag (ROS 1 .bag or ROS 2) or scan log to read  [default: RECORDING/bag]")]
DistancesOpt = Annotated[Path | None, typer.Option(
    "--distances", metavar="CSV", show_default=False, help="Tape distances [m]  [default: RECORDING/distances.csv]")]
ScanTopicOpt = Annotated[str | None, typer.Option(
    "--scan-topic", metavar="TOPIC", show_default=False,
    help="Topic of the scans (rig file scan.topic; default /scan).")]
ScanFieldOpt = Annotated[str | None, typer.Option(
    "--scan-field", metavar="PATH", show_default=False,
    help="Dotted path of a LaserScan inside a larger message (scan.field; default: none, the "
    "topic is a sensor_msgs/LaserScan).")]
ScanStampOpt = Annotated[str | None, typer.Option(
    "--scan-stamp", metavar="MODE", show_default=False,
    help="header | receive: scan time from header.stamp or the bag's receive time "
    "(scan.stamp; default header).")]
ServoTopicOpt = Annotated[str | None, typer.Option(
    "--servo-topic", metavar="TOPIC", show_default=False,
    help="Topic of the servo angle (servo.topic; default /joint_states).")]
ServoFieldOpt = Annotated[str | None, typer.Option(
    "--servo-field", metavar="PATH", show_default=False,
    help="Dotted path of the numeric angle field (servo.field; default data for std_msgs, "
    "current_pos for dynamixel_msgs/JointState).")]
JointOpt = Annotated[str | None, typer.Option(
    "--joint", metavar="NAME", show_default=False,
    help="Joint name in sensor_msgs/JointState (servo.joint; default servo).")]
UnitOpt = Annotated[str | None, typer.Option(
    "--unit", metavar="UNIT", show_default=False,
    help="rad | deg | counts: unit of the recorded angle (servo.unit; default rad).")]
CountsOpt = Annotated[float | None, typer.Option(
    "--counts-per-rev", metavar="N", show_default=False,
    help="Encoder counts per revolution with --unit counts (e.g. 4096).")]
SignOpt = Annotated[int | None, typer.Option(
    "--sign", "--servo-sign", metavar="SIGN", show_default=False,
    help="1 or -1: -1 when the servo turns the other way (servo.sign; default 1).")]
OffsetOpt = Annotated[float | None, typer.Option(
    "--servo-offset", metavar="RAD", show_default=False,
    help="Added after unit and sign [rad]: the angle at lambda = 0 (servo.offset_rad; "
    "default 0).")]
ServoStampOpt = Annotated[str | None, typer.Option(
    "--servo-stamp", metavar="MODE", show_default=False,
    help="header | receive | scan: servo sample time; scan = the angle is a field of the scan's "
    "message (servo.stamp; default header).")]
TfParentOpt = Annotated[str | None, typer.Option(
    "--tf-parent", metavar="FRAME", show_default=False,
    help="Take the angle from /tf: the parent frame (servo.tf.parent; with --tf-child).")]
TfChildOpt = Annotated[str | None, typer.Option("--tf-child", metavar="FRAME", show_default=False,
                                                help="Child frame in /tf (servo.tf.child).")]
TfAxisOpt = Annotated[str | None, typer.Option(
    "--tf-axis", metavar="AXIS", show_default=False,
    help="x | y | z: rotation axis of the tf joint in the parent frame (default z).")]


@app.command("check", cls=Command)
def check_cmd(
    calibration: Annotated[Path, typer.Argument(
        help="The calibration to check: the folder `lrfcal calibrate` wrote, or its calibration.yaml.",
        metavar="CALIBRATION", show_default=False)],
    recording: Annotated[Path, typer.Argument(
        help="A new recording of the same rig: a recording folder, a scan log, or a folder with --bag.",
        metavar="RECORDING", show_default=False)],
    out: Annotated[Path, typer.Option("-o", "--out", metavar="DIR", show_default=False,
                                      help="Output folder: check.yaml, report.md, check.png (written atomically; "
                                      "must not overlap an input).")],
    false_alarm: Annotated[float, typer.Option(
        "--false-alarm", metavar="P", callback=finite_between(1e-6, 0.49, ""),
        help="The joint test's false-alarm rate: the probability of calling an unchanged rig drifted.")] = 0.05,
    fixed_mount: Annotated[bool, typer.Option(
        "--fixed-mount", help="Also test the mount (the rig's pose in the marker frame): only when the rig was not "
        "moved against the markers.")] = False,
    history: Annotated[Path | None, typer.Option(
        "--history", metavar="CSV", show_default=False,
        help="Append this check as one row to CSV (atomically; created when absent; never inside the calibration "
        "folder) and draw each parameter over its rows.")] = None,
    bag: BagOpt = None,
    distances: DistancesOpt = None,
    nominal: Annotated[Path | None, typer.Option(
        metavar="YAML", show_default=False,
        help="A rig file saying where this recording keeps its scans and servo angle (its DH are not used)  "
        "[default: the calibration's own rig file]")] = None,
    targetless: Annotated[bool, typer.Option(
        "--targetless", help="Calibrate the new recording from the scene's planes even when it has tape "
        "distances.")] = False,
    overwrite: Annotated[bool, typer.Option("--overwrite",
                                            help="Replace an output folder lrfcal wrote before.")] = False,
    no_figures: Annotated[bool, typer.Option("--no-figures", help="Do not draw check.png.")] = False,
    quiet: QuietOpt = False,
) -> None:
    """Check whether CALIBRATION still holds for a new RECORDING of the same rig.

    The recording is calibrated on the same path as `lrfcal calibrate`, started from the saved values, and every
    parameter of the rig both estimated (DH, clock offset, intrinsics; the mount with --fixed-mount) is compared:
    change, sigma, z, and one joint test of "nothing changed" at the false-alarm rate. Exit 0: still valid; 4:
    drifted (naming what moved); 3: the recording determines nothing that can be tested (naming why).
    """
    from lrfcal.commands.check import check_inputs, check_recording, write_check
    from lrfcal.errors import EXIT_DRIFTED

    check_inputs(calibration, recording, out, history, bag=bag, distances=distances, nominal=nominal,
                 overwrite=overwrite)
    with progress_display(f"checking {calibration} against {recording.name}", quiet=quiet) as hooks:
        outcome = check_recording(calibration, recording, bag=bag, distances=distances, nominal=nominal,
                                  false_alarm=false_alarm, fixed_mount=fixed_mount, targetless=targetless,
                                  progress=hooks.stage, warn=lambda line: print(f"warning: {line}", file=sys.stderr))
        hooks.stage("check.yaml, report.md" + ("" if no_figures else " and check.png"))
        write_check(outcome, out, overwrite=overwrite, history=history, figures=not no_figures)
    print(outcome.line())
    print(f"wrote {out}" + (f"; appended to {history}" if history is not None else ""))
    if outcome.drifted:
        raise typer.Exit(EXIT_DRIFTED)


@app.command("inspect", cls=Command)
def inspect_cmd(
    bag: Annotated[Path, typer.Argument(help="ROS 1 .bag file or ROS 2 bag folder (sqlite3 or MCAP).",
                                        metavar="BAG", show_default=False)],
    nominal: Annotated[Path | None, typer.Option(
        "--nominal", metavar="YAML", show_default=False,
        help="Rig file (nominal.yaml) saying where the data are; default: guess from the bag.")] = None,
    out: Annotated[Path | None, typer.Option(
        "-o", "--out", metavar="YAML", show_default=False,
        help="Also write the rig file (the snippet printed last) to YAML (atomically).")] = None,
    no_dh: Annotated[bool, typer.Option(
        "--no-dh", help="Do not propose the DH from the scene's planes (a search of 5-20 s): placeholders.")
                     ] = False,
    scan_topic: ScanTopicOpt = None, scan_field: ScanFieldOpt = None, scan_stamp: ScanStampOpt = None,
    servo_topic: ServoTopicOpt = None, servo_field: ServoFieldOpt = None, joint: JointOpt = None,
    unit: UnitOpt = None, counts_per_rev: CountsOpt = None, sign: SignOpt = None, servo_offset: OffsetOpt = None,
    servo_stamp: ServoStampOpt = None, tf_parent: TfParentOpt = None, tf_child: TfChildOpt = None,
    tf_axis: TfAxisOpt = None, quiet: QuietOpt = False,
) -> None:
    """Show what BAG holds: topics, types, counts, rates, scan geometry, the servo angle's range and rate, the
    clocks and their offset, the problems found, and the rig-file snippet (YAML) that reads it, its DH proposed
    from the scene's planes (with their uncertainty) unless the rig file gives them or --no-dh."""
    from rich.console import Console

    from lrfcal.commands.inspect_log import inspect_path
    from lrfcal.io.files import atomic_file, check_outputs
    from lrfcal.io.rig import load_rig, with_overrides

    if out is not None:
        check_outputs([p for p in (bag, nominal) if p is not None], [out])
    rig = load_rig(nominal) if nominal is not None else None
    scan, servo = with_overrides(
        rig.scan_source() if rig else None, rig.servo_source() if rig else None, scan_topic=scan_topic,
        scan_field=scan_field, scan_stamp=scan_stamp, servo_topic=servo_topic, servo_field=servo_field,
        joint=joint, unit=unit, counts_per_rev=counts_per_rev, sign=sign, servo_offset=servo_offset,
        servo_stamp=servo_stamp, tf_parent=tf_parent, tf_child=tf_child, tf_axis=tf_axis)
    with progress_display(f"inspecting {bag.name}", quiet=quiet) as hooks:
        result = inspect_path(bag, scan, servo, dh=rig.dh.model_dump() if rig else None,
                              log=rig.log if rig else None, propose=not no_dh,
                              progress=lambda done, total: hooks.steps("proposing dh", done, total))
    print_inspection(result, Console())
    if out is not None:
        with atomic_file(out) as tmp:
            tmp.write_text(result.rig_snippet)
        print(f"wrote {out}")


def print_inspection(result: BagInspection, console: Console) -> None:
    """Print a lrfcal.commands.inspect_bag.BagInspection with rich tables."""
    import math

    from rich.table import Table

    kind = f"ROS {result.ros_version} bag" if result.ros_version else "scan log"
    console.print(f"[bold]{result.path}[/bold]: {kind}, {result.duration_s:.1f} s")
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
        assert result.servo_source is not None  # the servo's samples were read from it
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
    for note in result.notes:
        console.print(f"note: {note}", markup=False)
    if result.problems:
        console.print("[bold]problems[/bold]:")
        for problem in result.problems:
            console.print(f"  - {problem}", markup=False)
    p = result.proposal
    if p is not None:
        what = (f"proposed from the scene's planes in {p.seconds:.1f} s ({p.n_agreeing} of {p.n_starts} search starts "
                f"agree)" if p.dh is not None else f"not proposed: {p.reason}")
        console.print(f"dh: {what}", markup=False, soft_wrap=True)
    console.print("[bold]rig file[/bold] (nominal.yaml) that reads it:")
    console.out(result.rig_snippet.rstrip("\n"), highlight=False)  # plain: no padding to copy along with it


@app.command("reproject", cls=Command)
def reproject_cmd(
    bag: Annotated[Path, typer.Argument(help="ROS 1 .bag file, ROS 2 bag folder (sqlite3 or MCAP), scan log, or a "
                                        "recording folder holding one.", metavar="BAG", show_default=False)],
    out: Annotated[Path, typer.Option("-o", "--out", metavar="PLY", show_default=False,
        help="Output PLY (binary; x y z (m) in frame M, "
                                      "intensity, time (s), scan, beam per point; written atomically).")],
    nominal: Annotated[Path | None, typer.Option(
        "--nominal", metavar="YAML", show_default=False,
        help="Rig file (nominal.yaml): nominal DH and where the data are in the bag  [default: BAG/nominal.yaml "
        "where BAG is a recording folder]")] = None,
    calibration: Annotated[Path | None, typer.Option(
        "--calibration", metavar="YAML", show_default=False,
        help="calibration.yaml (or the folder `lrfcal calibrate` wrote) whose dh replaces the rig file's nominal "
        "DH.")] = None,
    rrd: Annotated[Path | None, typer.Option("--rrd", metavar="FILE", show_default=False,
        help="Also save a rerun recording (.rrd).")] = None,
    bag_out: Annotated[Path | None, typer.Option(
        "--bag-out", metavar="DIR", show_default=False,
        help="Also write a ROS 2 bag (MCAP) of sensor_msgs/msg/PointCloud2 on /lrf_cloud, one "
        "cloud per sweep (frame lrf_motor).")] = None,
    clock_offset: Annotated[float | None, typer.Option(
        "--clock-offset", metavar="S", callback=finite_between(-10.0, 10.0, "s"), show_default=False,
        help="Fine laser-minus-servo clock offset [s] on top of the reader's coarse one, -10..10  [default: the "
        "calibration's estimate with --calibration, else 0]")] = None,
    scan_topic: ScanTopicOpt = None, scan_field: ScanFieldOpt = None, scan_stamp: ScanStampOpt = None,
    servo_topic: ServoTopicOpt = None, servo_field: ServoFieldOpt = None, joint: JointOpt = None,
    unit: UnitOpt = None, counts_per_rev: CountsOpt = None, sign: SignOpt = None, servo_offset: OffsetOpt = None,
    servo_stamp: ServoStampOpt = None, tf_parent: TfParentOpt = None, tf_child: TfChildOpt = None,
    tf_axis: TfAxisOpt = None, quiet: QuietOpt = False,
) -> None:
    """Turn BAG into a 3D cloud in the motor frame M: every beam at its own time and motor angle, with the
    calibrated DH (--calibration) or the rig file's nominal DH. Needs no tape distances."""
    from rich.console import Console

    from lrfcal.commands.reproject import CloudOutputs, reproject_bag

    console = Console(stderr=True)
    options = {k: v for k, v in dict(
        scan_topic=scan_topic, scan_field=scan_field, scan_stamp=scan_stamp, servo_topic=servo_topic,
        servo_field=servo_field, joint=joint, unit=unit, counts_per_rev=counts_per_rev, sign=sign,
        servo_offset=servo_offset, servo_stamp=servo_stamp, tf_parent=tf_parent, tf_child=tf_child,
        tf_axis=tf_axis).items() if v is not None}
    with progress_display(f"reprojecting {bag.name}", quiet=quiet) as hooks:
        summary = reproject_bag(bag, nominal, CloudOutputs(out, rrd, bag_out), calibration=calibration,
                                clock_offset_s=clock_offset, options=options, progress=hooks.steps,
                                warn=lambda text: console.print(f"warning: {text}", markup=False))
    for line in summary:
        console.print(line, markup=False)


@app.command("convert", cls=Command)
def convert_cmd(
    log: Annotated[Path, typer.Argument(
        help="Scan log: a .txt, .csv or .log file, one row per scan (time, motor angle, ranges; docs/formats.md, "
        "\"Scan logs\").", metavar="LOG", show_default=False)],
    out: Annotated[Path, typer.Option("-o", "--out", metavar="BAG", show_default=False,
                                      help="Output ROS 2 bag folder (MCAP; written atomically).")],
    nominal: Annotated[Path | None, typer.Option(
        "--nominal", metavar="YAML", show_default=False,
        help="Rig file whose log: and servo: sections describe the log  [default: guessed from the log, as "
        "lrfcal inspect does]")] = None,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace an existing bag folder at BAG.")] = False,
) -> None:
    """Convert a scan log into a ROS 2 bag (MCAP): sensor_msgs/LaserScan on /scan and sensor_msgs/JointState
    (joint servo, rad) on /joint_states, one of each per row; prints the rig file that reads the bag."""
    from lrfcal.commands.convert import convert_log

    for line in convert_log(log, out, nominal=nominal, overwrite=overwrite,
                            warn=lambda text: print(f"warning: {text}", file=sys.stderr)):
        print(line)


def main(argv: list[str] | None = None) -> None:
    """Console entry point: usage errors and any LrfError become one line on stderr and their exit code."""
    run_app(app, argv, "lrfcal")


if __name__ == "__main__":
    main()

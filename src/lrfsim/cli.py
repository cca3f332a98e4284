"""``lrfsim``: simulate recordings of the rotating laser range finder.

    lrfsim simulate SCENARIO -o DIR [--overwrite]   write a recording folder (docs/formats.md)
    lrfsim run SCENARIO [-o DIR] [--rrd FILE]        simulate, calibrate, compare with the truth (Tables I, III)

Errors the project raises on purpose (lrfcal.errors.LrfError) become one line ``error: <message>`` on stderr
and exit code 2. Heavy modules (mujoco, rosbags) are imported inside the commands.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, TypeVar

import typer

from lrfcal.errors import LrfError

if TYPE_CHECKING:
    from .simulate import SimResult

T = TypeVar("T")

app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                  help="MuJoCo testbench of a servo-turned Hokuyo UTM-30LX-EW.")

ScenarioArg = Annotated[Path, typer.Argument(help="Scenario YAML file (see scenarios/).", show_default=False)]


def _with_progress(work: Callable[[Callable[[int, int], None]], T], label: str) -> T:
    """Run ``work(progress)`` under a rich progress bar on stderr (scans done / total)."""
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    console = Console(stderr=True)
    with Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), TextColumn("scans"),
                  TimeElapsedColumn(), console=console, transient=True, disable=not console.is_terminal) as bar:
        task = bar.add_task(label, total=None)

        def progress(done: int, total: int) -> None:
            bar.update(task, completed=done, total=total)

        return work(progress)


def _summary(result: SimResult, path: Path) -> None:
    """Print the recording's summary table to stdout."""
    import numpy as np
    from rich.console import Console
    from rich.table import Table

    s = result.stats
    S, N = result.ranges_m.shape
    valid = float(np.isfinite(result.ranges_m).mean())
    table = Table(title=f"recording {path}", show_header=False)
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
    Console().print(table)


@app.command()
def simulate(
    scenario: ScenarioArg,
    out: Annotated[Path, typer.Option("-o", "--out", help="Recording folder to write.", show_default=False)],
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace an existing non-empty folder.")] = False,
) -> None:
    """Simulate SCENARIO and write the recording folder DIR (bag, distances, nominal, ground truth)."""
    from .scenario import load_scenario
    from .simulate import simulate_to_folder

    sc = load_scenario(scenario)
    result, path = _with_progress(lambda p: simulate_to_folder(sc, out, overwrite=overwrite, progress=p),
                                  f"simulating {sc.name}")
    _summary(result, path)


@app.command()
def run(
    scenario: ScenarioArg,
    out: Annotated[Path | None, typer.Option("-o", "--out", help="Output folder [default: runs/<name>, "
                                             "replaced if present].", show_default=False)] = None,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace an existing non-empty -o folder.")] = False,
    rrd: Annotated[Path | None, typer.Option("--rrd", help="Save the rerun recording here [default: DIR/run.rrd].",
                                             show_default=False)] = None,
    spawn: Annotated[bool, typer.Option("--spawn", help="Open the rerun viewer.")] = False,
) -> None:
    """Simulate SCENARIO, calibrate the recording, compare with the ground truth (Tables I and III).

    Exits with code 1 when the recovery misses the tolerances declared in the scenario.
    """
    from rich.console import Console

    from lrfcal.cli import print_summary

    from .loop import print_comparison, run_loop
    from .scenario import load_scenario

    sc = load_scenario(scenario)
    if out is None:
        out, overwrite = Path("runs") / sc.name, True
    target = out
    report = _with_progress(
        lambda p: run_loop(sc, target, overwrite=overwrite, rrd_path=rrd, spawn=spawn, progress=p),
        f"simulating {sc.name}",
    )
    console = Console()
    print_summary(report.result, console)
    print_comparison(report.comparison, console)
    console.print("timings: " + ", ".join(f"{k.strip()} {v:.2f} s" for k, v in report.timings_s.items()))
    console.print(f"wrote {report.out_dir} (recording/, calibration/, comparison.md"
                  + (", run.rrd)" if rrd is None else f"); rerun: {rrd}"))
    if not report.comparison.ok:
        console.print("[red]MISSED: " + "; ".join(report.comparison.failures))
        raise typer.Exit(1)


def main(argv: list[str] | None = None) -> None:
    """Entry point: run the typer app; an LrfError becomes ``error: <message>`` on stderr and exit code 2."""
    try:
        app(args=argv, prog_name="lrfsim")
    except LrfError as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(e.exit_code)


if __name__ == "__main__":
    main()

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

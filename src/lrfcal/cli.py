"""``lrfcal``: calibrate a servo-turned 2D laser range finder from a recording with reflective markers.

Exit codes: 0 done; 2 bad input or usage (one line ``error: ...`` on stderr); 3 the data do not support a
trustworthy calibration (one line naming the check).
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from .cliutil import Command, finite_between, make_app, progress_display, run_app

if TYPE_CHECKING:
    from rich.console import Console

    from .types import CalibrationResult

app = make_app(
    "Calibrate a servo-turned 2D laser range finder from reflective markers: the mount pose [m, rad] and the "
    "DH parameters a, alpha, b, beta of the scan plane. Formats: docs/formats.md."
)


@app.callback()
def _root() -> None:
    """Calibrate a servo-turned 2D laser range finder from reflective markers."""


@app.command("calibrate", cls=Command)
def calibrate_cmd(
    recording: Annotated[Path, typer.Argument(help="Recording folder: bag/, distances.csv, nominal.yaml.",
                                              metavar="RECORDING", show_default=False)],
    out: Annotated[Path, typer.Option("-o", "--out", metavar="DIR", show_default=False,
                                      help="Output folder (written atomically; must not overlap an input).")],
    bag: Annotated[Path | None, typer.Option(metavar="PATH", show_default=False,
                                             help="Bag to read (ROS 1 .bag or ROS 2)  [default: RECORDING/bag]")
                   ] = None,
    distances: Annotated[Path | None, typer.Option(metavar="CSV", show_default=False,
                                                   help="Tape distances [m]  [default: RECORDING/distances.csv]")
                         ] = None,
    nominal: Annotated[Path | None, typer.Option(metavar="YAML", show_default=False,
                                                 help="Nominal values  [default: RECORDING/nominal.yaml]")] = None,
    range_sigma: Annotated[float, typer.Option(metavar="M", callback=finite_between(1e-5, 10.0, "m"),
                                               help="Range noise sigma of the scanner [m], 1e-5..10.")] = 0.010,
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
) -> None:
    """Calibrate the rig from RECORDING.

    Writes calibration.yaml, rig.urdf, the clouds before/after, report.md and its figures into DIR.
    """
    from rich.console import Console

    from .app import calibrate_folder
    from .pipeline import CalibConfig

    console = Console()
    config = CalibConfig(range_sigma_m=range_sigma, clock_offset_s=clock_offset, baseline=not no_baseline)
    with progress_display(f"calibrating {recording.name}") as hooks:
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
        )
    print_summary(result, console)
    console.print(f"wrote {out}", markup=False)


def print_summary(result: CalibrationResult, console: Console) -> None:
    """The estimated parameters with their 1-sigma, the solver status, the residual RMS and stage timings.

    The sigma vector is in :data:`~lrfcal.kinematics.ESTIMATE_NAMES` order: the mount rotation is estimated as a
    small rotation vector (rx, ry, rz), so roll, pitch and yaw are shown without a sigma and the rotation's
    1-sigma gets its own rows.
    """
    import math

    from rich.table import Table

    from .kinematics import ANGLE_NAMES, ESTIMATE_NAMES, PARAM_NAMES
    from .output import residual_summary

    sol = result.solution
    table = Table(title="Calibration")
    for h in ("parameter", "start", "estimate", "1-sigma", "paper's method"):
        table.add_column(h, justify="right")
    start, est = result.start.vector(), sol.params.vector()
    sigma = [float(v) for v in sol.sigma]
    paper = None if result.baseline is None else result.baseline.params.vector()

    def shown(name: str, v: float) -> str:
        return f"{math.degrees(v):.3f}" if name in ANGLE_NAMES else f"{v * 1000:.3f}"

    def sigma_of(name: str) -> str:
        i = ESTIMATE_NAMES.index(name) if name in ESTIMATE_NAMES else -1
        return shown(name, sigma[i]) if 0 <= i < len(sigma) else "-"

    for i, n in enumerate(PARAM_NAMES):
        unit = "deg" if n in ANGLE_NAMES else "mm"
        table.add_row(f"{n} ({unit})", shown(n, start[i]), shown(n, est[i]), sigma_of(n),
                      "-" if paper is None else shown(n, paper[i]))
    for n in ESTIMATE_NAMES:
        if n not in PARAM_NAMES:  # rx, ry, rz: the rotation's uncertainty about M's axes
            table.add_row(f"{n} (deg)", "", "", sigma_of(n), "")
    console.print(table)
    console.print("rx, ry, rz: 1-sigma of the mount rotation about the motor frame's x, y, z axes", markup=False)
    console.print(f"solver: {' '.join(str(sol.status).split())} ({sol.n_iterations} iterations)",
                  markup=False)
    console.print(f"{residual_summary(result)}; stages: "
                  + ", ".join(f"{k} {v:.2f}s" for k, v in result.timings_s.items()), markup=False)


def main(argv: list[str] | None = None) -> None:
    """Console entry point: usage errors and any LrfError become one line on stderr and their exit code."""
    run_app(app, argv, "lrfcal")


if __name__ == "__main__":
    main()

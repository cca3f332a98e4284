"""What the two command-line programs (``lrfcal``, ``lrfsim``) share: the typer app settings, usage lines, the
mapping of errors to one line and an exit code, option checks and the progress display.

Exit codes (the same for every command; see :mod:`lrfcal.errors`): 0 done, 1 ``lrfsim run`` missed its
tolerances, 2 bad input or usage (one line ``error: ...`` on stderr), 3 no trustworthy calibration.

typer >= 0.29 vendors click as ``typer._click``; only typer's public names are used here (``typer.TyperException``
is the base of every usage error, ``typer.BadParameter`` one of them) plus ``typer.core.TyperCommand`` /
``TyperArgument`` / ``TyperOption`` to write usage lines as ``SCENARIO -o DIR`` instead of ``{scenario}``.
"""

from __future__ import annotations

import math
import os
import re
import shutil
import sys
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from typing import TYPE_CHECKING, Annotated, Any, NoReturn

import typer
from typer.core import TyperArgument, TyperCommand, TyperOption

from .errors import LrfError

if TYPE_CHECKING:
    from rich.console import Console

#: Exit code of a usage error or bad input (the same as :class:`lrfcal.errors.InputError`).
EXIT_USAGE = 2


class Command(TyperCommand):
    """A typer command whose usage line names its arguments in capitals (``SCENARIO``, optional ``[X]``) and
    shows its required options (``-o DIR``)."""

    def collect_usage_pieces(self, ctx: Any) -> list[str]:
        pieces = [self.options_metavar] if self.options_metavar else []
        for p in self.get_params(ctx):
            if isinstance(p, TyperArgument):
                name = str(p.metavar or p.name).upper()
                pieces.append(name if p.required else f"[{name}]")
            elif isinstance(p, TyperOption) and p.required:
                pieces.append(f"{p.opts[0]} {p.metavar or str(p.name).upper()}")
        return pieces


    def get_short_help_str(self, limit: int = 45) -> str:
        """The command's first sentence, whole, in the program's list of commands (click cuts it at 45
        characters)."""
        return str(super().get_short_help_str(limit=max(limit, 300)))


def version_text(prog_name: str) -> str:
    """``<prog> <version of the lrf-calib distribution>`` (``unknown`` when it is not installed)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return f"{prog_name} {version('lrf-calib')}"
    except PackageNotFoundError:
        return f"{prog_name} unknown (lrf-calib is not installed)"


def make_app(help_text: str, prog_name: str) -> typer.Typer:
    """A typer app with plain help (no rich markup: brackets such as ``[m]`` and ``[default: ...]`` are kept and
    the text wraps at the terminal width), no completion commands, no pretty tracebacks, and ``--version``."""
    app = typer.Typer(add_completion=False, no_args_is_help=True, rich_markup_mode=None,
                      pretty_exceptions_enable=False, help=help_text)

    def show_version(value: bool) -> None:
        if value:
            print(version_text(prog_name))
            raise typer.Exit()

    @app.callback()
    def _root(version: bool = typer.Option(False, "--version", callback=show_version, is_eager=True,
                                           help="Show the version and exit.")) -> None:
        pass

    _root.__doc__ = help_text
    return app


def one_line(text: str) -> str:
    """``text`` with its lines and runs of blanks joined by single spaces."""
    return " ".join(str(text).split())


def _usage_line(err: Any, prog_name: str) -> str:
    ctx = getattr(err, "ctx", None)
    if ctx is None:
        return f" (see '{prog_name} --help')"
    usage = one_line(ctx.get_usage())
    return f" ({usage}; see '{ctx.command_path} --help')"


def run_app(app: typer.Typer, argv: Sequence[str] | None, prog_name: str) -> NoReturn:
    """Run ``app`` and exit with its code. Never shows a traceback for a usage error or an :class:`LrfError`:

    * no arguments at all: the help on stdout, one line on stderr, exit 2;
    * a usage error (missing argument or option, bad value, unknown option or command): one line
      ``error: <what> (Usage: ...; see '<cmd> --help')`` on stderr, exit 2;
    * an :class:`LrfError`: one line ``error: <message>`` on stderr, exit ``e.exit_code``;
    * an OSError or MemoryError that escaped the checks: one line, exit 2 (the cause is named).

    Before the command runs, the process's BLAS / OpenMP thread pools are limited by the programs' thread policy
    (:func:`lrfcal.threads.apply_thread_policy`).
    """
    from .threads import apply_thread_policy

    try:
        apply_thread_policy()
        rv = app(args=list(argv) if argv is not None else None, prog_name=prog_name, standalone_mode=False)
    except typer.TyperException as e:  # click's usage errors as vendored by typer (NoArgsIsHelpError, ...)
        code = int(getattr(e, "exit_code", EXIT_USAGE) or EXIT_USAGE)
        if type(e).__name__ == "NoArgsIsHelpError":
            print(e.format_message())
            ctx = getattr(e, "ctx", None)
            commands = ", ".join(getattr(ctx.command, "commands", {})) if ctx is not None else ""
            print(f"error: no command given{f' (one of: {commands})' if commands else ''}", file=sys.stderr)
            sys.exit(EXIT_USAGE)
        print(f"error: {one_line(e.format_message())}{_usage_line(e, prog_name)}", file=sys.stderr)
        sys.exit(code)
    except typer.Abort:
        print("error: aborted", file=sys.stderr)
        sys.exit(1)
    except LrfError as e:
        print(f"error: {one_line(str(e))}", file=sys.stderr)
        sys.exit(e.exit_code)
    except MemoryError:
        print("error: out of memory (the input is too large for this machine)", file=sys.stderr)
        sys.exit(EXIT_USAGE)
    except OSError as e:
        where = f"{_shown_path(e.filename)}: " if getattr(e, "filename", None) else ""
        print(f"error: {where}{e.strerror or one_line(str(e))}", file=sys.stderr)
        sys.exit(EXIT_USAGE)
    sys.exit(rv if isinstance(rv, int) else 0)


#: the names of the tools' own temporary files and folders (lrfcal.output, figures, cloud, viz, app)
_TEMP_NAME = re.compile(r"^\.(figures-|lrf-write-probe-|.+\.(tmp|old)-|.+\.tmp$)")


def _shown_path(filename: object) -> str:
    """``filename`` as a message may show it: a temporary path of the tool's own is replaced by the folder it was
    being written in (a user never made it and cannot act on its name)."""
    path = str(filename)
    parent, _, name = path.rpartition(os.sep)
    return (parent or ".") if _TEMP_NAME.match(name) else path


def finite_between(lo: float, hi: float, unit: str) -> Callable[[float | None], float | None]:
    """A typer callback refusing NaN, +-inf and values outside [lo, hi] (``--clock-offset nan``)."""

    def check(value: float | None) -> float | None:
        if value is not None and not (math.isfinite(value) and lo <= value <= hi):
            raise typer.BadParameter(f"must be a finite number from {lo:g} to {hi:g} {unit}, got {value!r}")
        return value

    return check


def spawn_unavailable_reason() -> str | None:
    """Why a rerun viewer cannot be started here (None when it probably can): no ``rerun`` executable, or no
    display on Linux (neither DISPLAY nor WAYLAND_DISPLAY set). Checked before spawning so that ``--spawn``
    never waits for a viewer that cannot come up."""
    exe = shutil.which("rerun") or shutil.which("rerun", path=os.path.dirname(sys.executable))
    if exe is None:
        return "no 'rerun' executable on PATH"
    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        return "no display (DISPLAY and WAYLAND_DISPLAY are unset)"
    return None


#: The ``--quiet`` option of every command that shows a progress display.
QuietOpt = Annotated[bool, typer.Option("--quiet", "-q", help="No progress display on stderr (it is drawn only on a "
                                        "terminal anyway).")]


@dataclass
class ProgressHooks:
    """Callbacks for a long job: ``scans(done, total)`` while simulating, ``stage(name)`` while calibrating,
    ``trials(done, total)`` in a study, ``steps(name, done, total)`` for any other counted step (reading,
    reprojecting). They cost nothing when the display is off."""

    scans: Callable[[int, int], None]
    stage: Callable[[str], None]
    trials: Callable[[int, int], None]
    steps: Callable[[str, int, int], None]


def progress_console() -> Console:
    """The console the progress display draws on: stderr (stdout stays for results)."""
    from rich.console import Console

    return Console(stderr=True)


@contextmanager
def progress_display(label: str, *, quiet: bool = False, console: Console | None = None) -> Iterator[ProgressHooks]:
    """A transient progress line on stderr: the label, a bar (pulsing while the total is unknown), what is being
    done (scans simulated, the calibration's stage of :data:`lrfcal.pipeline.STAGES` or
    :data:`lrfcal.targetless.STAGES`, trials, any other name: what is being written) and the time elapsed.

    Drawn only on a terminal (``console``, default :func:`progress_console`), and not at all with ``quiet``
    (the commands' ``--quiet``): a log file or a pipe gets none of it. The line is erased when the block ends.
    """
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from .pipeline import STAGES
    from .targetless import STAGES as TARGETLESS_STAGES

    console = console if console is not None else progress_console()
    with Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.fields[what]}"),
                  TimeElapsedColumn(), console=console, transient=True,
                  disable=quiet or not console.is_terminal) as bar:
        task = bar.add_task(label, total=None, what="")

        def scans(done: int, total: int) -> None:
            bar.update(task, completed=done, total=total, what=f"{done}/{total} scans")

        def trials(done: int, total: int) -> None:
            bar.update(task, completed=done, total=total, what=f"{done}/{total} trials", refresh=True)

        def steps(name: str, done: int, total: int) -> None:
            bar.update(task, description=f"{label}: {name}", completed=done, total=max(total, 1),
                       what=f"{done}/{total}")

        calibration: list[tuple[str, ...]] = []  # the stages of the calibration that runs (known at its first)

        def stage(name: str) -> None:
            if not calibration:
                calibration.append(TARGETLESS_STAGES if name == TARGETLESS_STAGES[0] else STAGES)
            stages = calibration[0]
            if name in stages:  # a calibration stage: every one is drawn at least once (refresh)
                k = stages.index(name)
                bar.update(task, description=f"calibrating: {name}", completed=k, total=len(stages),
                           what=f"stage {k + 1}/{len(stages)}", refresh=True)
            else:  # after the calibration: writing its outputs
                bar.update(task, description=f"writing {name}", completed=1, total=1, what="", refresh=True)

        yield ProgressHooks(scans=scans, stage=stage, trials=trials, steps=steps)


__all__ = ["EXIT_USAGE", "Command", "ProgressHooks", "QuietOpt", "finite_between", "make_app", "one_line",
           "progress_console", "progress_display", "run_app", "spawn_unavailable_reason", "version_text"]

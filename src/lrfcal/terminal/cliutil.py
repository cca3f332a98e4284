"""What the two command-line programs (``lrfcal``, ``lrfsim``) share: the typer app settings, usage lines, the
mapping of errors to one line and an exit code and option checks (their progress display: lrfcal.terminal.progress).

Exit codes (the same for every command; see :mod:`lrfcal.errors`): 0 done, 1 ``lrfsim run`` missed its
tolerances, 2 bad input or usage (one line ``error: ...`` on stderr), 3 no trustworthy calibration.

typer >= 0.29 vendors click as ``typer._click``; only typer's public names are used here (``typer.TyperException``
is the base of every usage error, ``typer.BadParameter`` one of them) plus ``typer.core.TyperCommand`` /
``TyperArgument`` / ``TyperOption`` to write usage lines as ``SCENARIO -o DIR`` instead of ``{scenario}``.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable, Sequence
from typing import Annotated, Any, NoReturn

import typer
from typer.core import TyperArgument, TyperCommand, TyperOption

from lrfcal.errors import LrfError

#: Exit code of a usage error or bad input (the same as :class:`lrfcal.errors.InputError`).
EXIT_USAGE = 2


class Command(TyperCommand):
    """A typer command whose usage line names its arguments in capitals (``SCENARIO``, optional ``[X]``) and
    shows its required options (``-o DIR``), and that applies the programs' thread and memory policies when it runs
    (:meth:`invoke`). Every command of ``lrfcal`` and ``lrfsim`` is one (``@app.command(cls=Command)``)."""

    def invoke(self, ctx: Any) -> Any:
        """Run the command once its arguments are parsed: first the process's BLAS / OpenMP thread pools limited
        by the programs' thread policy (:func:`lrfcal.runtime.threads.apply_thread_policy`: the libraries the command
        loads are limited as they load) and numpy's large arrays kept off transparent huge pages
        (:func:`lrfcal.runtime.memory.apply_memory_policy`).
        Here and not before parsing, so that ``--help`` and a usage error answer without importing numpy or scipy.
        """
        from lrfcal.runtime.memory import apply_memory_policy
        from lrfcal.runtime.threads import apply_thread_policy

        apply_memory_policy()
        apply_thread_policy()
        return super().invoke(ctx)

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

    When a command runs (its arguments parsed), :meth:`Command.invoke` applies the thread and memory policies
    first; ``--help`` and usage errors import nothing heavy (tests/test_startup.py).

    ``argv`` None (the console script, whose process ends here): every object left is frozen out of the garbage
    collector first (``gc.freeze``), so that the interpreter's exit does not walk them all again: 0.13-0.15 s of
    ``lrfcal calibrate``'s exit. Nothing the command writes waits for the collector (its files are complete and
    renamed, the children joined); only finalizers of objects caught in reference cycles, which Python does not
    promise to run at exit, are skipped. A call with ``argv`` (a test, a library) leaves the collector alone.
    """
    try:
        _run(app, argv, prog_name)
    finally:
        if argv is None:
            import gc

            gc.freeze()


def _run(app: typer.Typer, argv: Sequence[str] | None, prog_name: str) -> NoReturn:
    try:
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
        from lrfcal.io.files import shown_path

        where = f"{shown_path(e.filename)}: " if getattr(e, "filename", None) else ""
        print(f"error: {where}{e.strerror or one_line(str(e))}", file=sys.stderr)
        sys.exit(EXIT_USAGE)
    sys.exit(rv if isinstance(rv, int) else 0)


def finite_between(lo: float, hi: float, unit: str) -> Callable[[float | None], float | None]:
    """A typer callback refusing NaN, +-inf and values outside [lo, hi] (``--clock-offset nan``)."""

    def check(value: float | None) -> float | None:
        if value is not None and not (math.isfinite(value) and lo <= value <= hi):
            raise typer.BadParameter(f"must be a finite number from {lo:g} to {hi:g} {unit}, got {value!r}")
        return value

    return check


#: The ``--quiet`` option of every command that shows a progress display.
QuietOpt = Annotated[bool, typer.Option("--quiet", "-q", help="No progress display on stderr (it is drawn only on a "
                                        "terminal anyway).")]


__all__ = ["EXIT_USAGE", "Command", "QuietOpt", "finite_between", "make_app", "one_line", "run_app", "version_text"]

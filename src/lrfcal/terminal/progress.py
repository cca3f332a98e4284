"""The progress display of the long jobs (``lrfcal calibrate``, ``lrfsim run``, ``lrfsim study``, ...): a transient
line on stderr, drawn only on a terminal, fed by callbacks that cost nothing when it is off."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from rich.console import Console


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
    :data:`lrfcal.stages.targetless.STAGES`, trials, any other name: what is being written) and the time elapsed.

    Drawn only on a terminal (``console``, default :func:`progress_console`), and not at all with ``quiet``
    (the commands' ``--quiet``): a log file or a pipe gets none of it. The line is erased when the block ends.
    """
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

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
            if not calibration:  # imported here: a job that calibrates nothing (plan, simulate) need not load them
                from lrfcal.pipeline import STAGES
                from lrfcal.stages.targetless import STAGES as TARGETLESS_STAGES

                calibration.append(TARGETLESS_STAGES if name == TARGETLESS_STAGES[0] else STAGES)
            stages = calibration[0]
            if name in stages:  # a calibration stage: every one is drawn at least once (refresh)
                k = stages.index(name)
                bar.update(task, description=f"calibrating: {name}", completed=k, total=len(stages),
                           what=f"stage {k + 1}/{len(stages)}", refresh=True)
            else:  # after the calibration: writing its outputs
                bar.update(task, description=f"writing {name}", completed=1, total=1, what="", refresh=True)

        yield ProgressHooks(scans=scans, stage=stage, trials=trials, steps=steps)


__all__ = ["ProgressHooks", "progress_console", "progress_display"]

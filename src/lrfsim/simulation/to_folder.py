"""Simulate a scenario and write its recording folder: the body of ``lrfsim simulate`` (the simulation itself,
arrays only: lrfsim.simulation.simulate; the folder's format and its atomic writing: lrfsim.simulation.recording)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from lrfsim.scenario.file import Scenario

from .recording import check_output, write_recording
from .result import SimResult
from .simulate import simulate


def simulate_to_folder(scenario: Scenario, out_dir: str | Path, *, overwrite: bool = False,
                       progress: Callable[[int, int], None] | None = None) -> tuple[SimResult, Path]:
    """Simulate and write: the body of ``lrfsim simulate``.

    The output folder is checked before simulating (InputError if it exists, is not empty and not
    ``overwrite``), so nothing is computed or written in vain.
    """
    check_output(out_dir, overwrite)
    result = simulate(scenario, progress)
    return result, write_recording(result, scenario, out_dir, overwrite=overwrite)


__all__ = ["simulate_to_folder"]

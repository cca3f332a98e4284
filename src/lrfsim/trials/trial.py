"""One trial: simulate a scenario, write the recording, read it back as a real one, calibrate, compare with the truth.

The unit of the parameter-recovery tests, the trust benchmark and Monte-Carlo studies. A trial ends in one of two
outcomes: ``calibrated`` (with errors against the truth and the reported sigma) or ``refused`` (the calibration
raised an LrfError: the reason and its exit code are kept). A *confident wrong* result is a calibrated trial
whose error exceeds 4 reported sigma on some DH parameter: the one outcome the calibration must never produce.
"""

from __future__ import annotations

import math
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lrfcal import CalibConfig, CalibrationResult, MarkerEvidence, Recording, Solution, calibrate
from lrfcal.errors import LrfError
from lrfcal.io.bag import BagReader
from lrfcal.io.recording import read_recording
from lrfcal.model.kinematics import DH_NAMES, ESTIMATE_NAMES
from lrfsim.scenario.file import Scenario
from lrfsim.simulation.recording import write_recording
from lrfsim.simulation.simulate import simulate

from .compare import Truth, load_truth

#: |error| / sigma beyond which a calibrated result counts as confidently wrong
CONFIDENT_WRONG_Z = 4.0


@dataclass(frozen=True)
class Trial:
    """The outcome of one trial. errors, sigma (4,) in DH_NAMES order (a, alpha, b, beta; SI units), NaN when
    refused; reason and exit_code when refused; seconds of the calibration alone."""

    name: str
    status: str  # "calibrated" | "refused"
    errors: np.ndarray
    sigma: np.ndarray
    reason: str = ""
    exit_code: int = 0
    seconds: float = math.nan
    clock_offset_error_s: float = math.nan
    result: CalibrationResult | None = field(default=None, repr=False, compare=False)

    @property
    def z(self) -> np.ndarray:
        return self.errors / self.sigma

    @property
    def confident_wrong(self) -> bool:
        return self.status == "calibrated" and bool(np.any(~(np.abs(self.z) <= CONFIDENT_WRONG_Z)))

    def describe(self) -> str:
        if self.status == "refused":
            return f"{self.name}: refused (exit {self.exit_code}): {self.reason}"
        parts = []
        for name, e, s in zip(DH_NAMES, self.errors, self.sigma, strict=True):
            scale, unit = (1000.0, "mm") if name in ("a", "b") else (math.degrees(1.0), "deg")
            parts.append(f"{name} {e * scale:+.3f} +- {s * scale:.3f} {unit} ({e / s:+.1f} sigma)")
        return f"{self.name}: " + ", ".join(parts)


def record(scenario: Scenario, folder: Path) -> Path:
    """Simulate ``scenario`` and write its recording into ``folder`` (which must not exist)."""
    write_recording(simulate(scenario), scenario, folder)
    return folder


def calibrate_recording(
    folder: Path, config: CalibConfig | None = None, *, name: str | None = None,
    mutate: Callable[[Recording], Recording] | None = None, keep_result: bool = False, paper: bool = False,
    bag_reader: BagReader | None = None, force: bool = False,
) -> Trial:
    """Read a recording folder written by lrfsim, calibrate it (``mutate`` may change the Recording first, e.g. the
    nominal values), and compare the DH parameters with its ground_truth.yaml.

    ``paper``: judge the paper's method instead of ours (the marker evidence's ``baseline``: the blob's brightest beam,
    one motor angle per scan, on our detections and association). ``config`` then runs with ``baseline=True`` and
    ``force=True``: the consistency checks are ours, the paper's method has none, so a check that our solution
    fails does not withhold the paper's estimate. ``bag_reader``: the bag's data from memory
    (lrfsim.simulation.recording.in_memory_bag; the folder then needs no bag). ``force``: as ``lrfcal calibrate
    --force``, a failed check recorded in the result instead of refusing (``config``'s own when given)."""
    truth = load_truth(folder / "ground_truth.yaml")
    recording = read_recording(folder, bag_reader=bag_reader)
    if mutate is not None:
        recording = mutate(recording)
    label = name or folder.name
    nan4 = np.full(4, np.nan)
    config = config or CalibConfig(baseline=False, geometry=False, clouds=False, force=force)  # the estimate alone
    if paper:
        config = config.replace(baseline=True, force=True)
    t0 = time.perf_counter()
    try:
        result = calibrate(recording, config)
    except LrfError as err:
        return Trial(label, "refused", nan4, nan4, reason=str(err), exit_code=err.exit_code,
                     seconds=time.perf_counter() - t0)
    return _compared(result, truth, label, time.perf_counter() - t0, paper=paper, keep_result=keep_result)


def calibrate_as_user(folder: Path, *, name: str | None = None, keep_result: bool = False,
                      force: bool = False) -> Trial:
    """Calibrate a marker-less recording folder written by lrfsim exactly as ``lrfcal calibrate FOLDER --targetless
    --no-figures -o OUT`` does (lrfcal.workflow.calibrate_folder with the command's configuration, its outputs
    written into a temporary folder and dropped; ``force``: with ``--force``), and compare the DH parameters with its
    ground_truth.yaml. A DH parameter the calibration held (not determined by the scene) has sigma NaN."""
    from lrfcal import calibrate_folder

    truth = load_truth(folder / "ground_truth.yaml")
    label = name or folder.name
    nan4 = np.full(4, np.nan)
    # the configuration `lrfcal calibrate --targetless` makes (lrfcal.cli.calibrate_cmd's defaults)
    config = CalibConfig(range_sigma_m=None, clock_offset_s=0.0, baseline=True, force=force,
                         estimate_range_bias=True, targetless=True, compare_targetless=False, all_planes=False)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="lrfsim-calibration-") as tmp:
        try:
            result = calibrate_folder(folder, Path(tmp) / "calibration", config=config, figures=False)
        except LrfError as err:
            return Trial(label, "refused", nan4, nan4, reason=str(err), exit_code=err.exit_code,
                         seconds=time.perf_counter() - t0)
    return _compared(result, truth, label, time.perf_counter() - t0, keep_result=keep_result)


def _compared(result: CalibrationResult, truth: Truth, label: str, seconds: float, *, paper: bool = False,
              keep_result: bool = False) -> Trial:
    """A calibrated trial: the result's DH errors against the truth and its sigma (NaN for a parameter it held)."""
    nan4 = np.full(4, np.nan)
    sol: Solution | None = result.solution
    if paper:  # the paper's method runs with markers only
        sol = result.evidence.baseline if isinstance(result.evidence, MarkerEvidence) else None
    if sol is None:  # the paper's method could not run (the reason is in the notes)
        reason = next((n for n in result.notes if "paper's method" in n), "the paper's method did not run")
        return Trial(label, "refused", nan4, nan4, reason=reason, exit_code=3, seconds=seconds)
    est, true = sol.params.dh, truth.dh
    errors = np.array([getattr(est, n) - getattr(true, n) for n in DH_NAMES])
    errors[[1, 3]] = (errors[[1, 3]] + math.pi) % (2 * math.pi) - math.pi
    sigma = np.array([sol.sigma[ESTIMATE_NAMES.index(n)] for n in DH_NAMES])
    return Trial(label, "calibrated", errors, sigma, seconds=seconds,
                 clock_offset_error_s=sol.clock_offset_s - truth.clock_offset_s,
                 result=result if keep_result else None)


def run_trial(scenario: Scenario, config: CalibConfig | None = None, *, workdir: Path | None = None) -> Trial:
    """Simulate, write, read back and calibrate one scenario (in a temporary folder unless ``workdir``)."""
    with tempfile.TemporaryDirectory(dir=workdir) as tmp:
        folder = record(scenario, Path(tmp) / scenario.name)
        return calibrate_recording(folder, config, name=scenario.name)


__all__ = ["CONFIDENT_WRONG_Z", "Trial", "calibrate_as_user", "calibrate_recording", "record", "run_trial"]

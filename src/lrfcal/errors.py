"""The one exception base class of the project (both lrfcal and lrfsim raise its subclasses).

The CLIs turn any :class:`LrfError` into one line on stderr and the error's ``exit_code``; messages therefore
name the file, the field and the offending value. Exit codes (the same for every command):

* 0: done (calibrated);
* 2: bad input (:class:`InputError`): a file, field or option is wrong, and the message says how;
* 3: the data do not support a trustworthy result (:class:`CalibrationError`): the calibration was refused,
  and the message names the check that failed and its numbers;
* 4: ``lrfcal check`` only: the rig drifted (:data:`EXIT_DRIFTED`): the new recording's calibration differs from the
  saved one beyond its noise; not an error (the check's outputs are written), a verdict.
"""

from __future__ import annotations

#: the exit code of `lrfcal check` when the rig drifted (a verdict, not an error: its outputs are written)
EXIT_DRIFTED = 4


class LrfError(Exception):
    """Base class of every error this project raises on purpose."""

    exit_code: int = 2


class InputError(LrfError):
    """Bad user input: a scenario, a recording, a distances file, a nominal file, a CLI option."""

    exit_code = 2


class CalibrationError(LrfError):
    """Well-formed input from which no trustworthy calibration follows (too few markers seen, parameters the data
    leave undetermined, ambiguous alternatives, failed consistency checks, ...)."""

    exit_code = 3


class RunOffError(CalibrationError):
    """A solve that ended where too few of its returns count (beyond their 4 sigma, or no longer meeting their plane
    at a usable incidence): its cost ran off from its start; ``counted`` of ``returns`` count where it ended (the way
    that started it says what that means: lrfcal.stages.scene)."""

    def __init__(self, message: str, counted: int, returns: int) -> None:
        super().__init__(message)
        self.counted, self.returns = counted, returns


class ClockOffsetError(CalibrationError):
    """A refusal over the clock offset itself: no scan lies within the joint states' time span at it, or its start
    (``--clock-offset``) lies beyond what the recording allows or far from where the sweep's two directions line up.
    Its message names the clock offset, so no further hint about the offset is added to it (lrfcal.pipeline)."""


class ClockStartError(ClockOffsetError):
    """The clock offset's start (``--clock-offset``, or a saved calibration's) refused: beyond what the recording
    allows, or far from where the sweep's two directions line up (lrfcal.pipeline); a start of 0 may calibrate."""

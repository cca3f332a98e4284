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

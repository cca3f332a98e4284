"""The one exception base class of the project (both lrfcal and lrfsim raise its subclasses).

The CLIs turn any :class:`LrfError` into one line on stderr and exit code 2; messages therefore name the file,
the field and the offending value.
"""

from __future__ import annotations


class LrfError(Exception):
    """Base class of every error this project raises on purpose."""


class InputError(LrfError):
    """Bad user input: a scenario, a recording, a distances file, a nominal file, a CLI option."""


class CalibrationError(LrfError):
    """The calibration could not be carried out on otherwise well-formed input (too few markers seen, ...)."""

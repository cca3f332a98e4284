"""lrfcal: calibration of a rotating 2D laser range finder from reflective markers (seed paper's method).

The model's names (:class:`DH`, :class:`Params`, :class:`Pose`, :data:`PARAM_NAMES`, from
:mod:`lrfcal.model.kinematics`) are imported when first used (PEP 562), so that importing any part of the package,
such as the command line's help, does not load numpy.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from .errors import CalibrationError, InputError, LrfError

if TYPE_CHECKING:
    from .model.kinematics import DH, PARAM_NAMES, Params, Pose

__all__ = ["DH", "PARAM_NAMES", "CalibrationError", "InputError", "LrfError", "Params", "Pose"]
__version__ = "0.1.0"

_KINEMATICS = ("DH", "PARAM_NAMES", "Params", "Pose")


def __getattr__(name: str) -> Any:
    """The model's names from :mod:`lrfcal.model.kinematics`, imported on first use."""
    if name in _KINEMATICS:
        from .model import kinematics

        return getattr(kinematics, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

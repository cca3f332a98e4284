"""lrfcal: calibration of a rotating 2D laser range finder from reflective markers (seed paper's method)."""

from .errors import CalibrationError, InputError, LrfError
from .model.kinematics import DH, PARAM_NAMES, Params, Pose

__all__ = ["DH", "PARAM_NAMES", "CalibrationError", "InputError", "LrfError", "Params", "Pose"]
__version__ = "0.1.0"

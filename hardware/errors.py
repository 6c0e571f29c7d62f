"""Hardware errors: one line that says what is wrong and what to do (the CLIs print it, exit 2)."""

from dssp_train.errors import DSSPError


class HardwareError(DSSPError):
    """A device is missing, misconfigured, or reported a fault."""


class CameraError(HardwareError):
    """A camera cannot be opened, or delivers no usable frames."""


class CanError(HardwareError):
    """A CAN bus cannot be opened, or a frame could not be sent."""


class ArmError(HardwareError):
    """An arm did not answer, refused a command, or reports an error."""


class CalibrationError(HardwareError):
    """A calibration (extrinsics) file is missing or invalid."""

"""User-facing errors: one line that says what is wrong and what to do.

The CLIs catch :class:`DSSPError` and print its message without a traceback.
"""


class DSSPError(Exception):
    """An error caused by the user's input (a path, a dataset, a config)."""


class OutputError(DSSPError):
    """An output path holds something the command may not replace, or cannot be written (``dssp_core.output_guard``)."""


class DatasetError(DSSPError):
    """A dataset on disk is missing something or holds invalid values."""


class ConfigError(DSSPError):
    """A configuration value is invalid or does not fit a checkpoint."""


class CheckpointError(DSSPError):
    """A checkpoint is missing, corrupt, or does not fit its config."""


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


class ExportError(DSSPError):
    """Bad input to export or verify: a path, an option, a model directory."""


class ParityError(ExportError):
    """The exported graphs disagree with the PyTorch reference beyond the bound (``export.verify``)."""


class NonFiniteObservation(ValueError):
    """An observation holds NaN or infinity; it was refused before the history saw it (the history is unchanged).

    A ValueError, not a :class:`DSSPError`: a runtime condition of one control tick (hold the tick), raised by
    ``dssp_data.streaming_history.check_finite``.
    """

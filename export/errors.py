"""Export errors: one line that says what is wrong and what to do (the CLIs print ``error: ...``).

Exit codes of ``python -m export.to_onnx`` and ``python -m export.verify``: 2 for bad input
(:class:`ExportError`, like every :class:`~dssp_train.errors.DSSPError`), 1 when the exported graphs do
not reproduce the PyTorch model (:class:`ParityError`).
"""

from dssp_train.errors import DSSPError


class ExportError(DSSPError):
    """Bad input to export or verify: a path, an option, a model directory."""


class ParityError(ExportError):
    """The exported graphs disagree with the PyTorch streaming policy beyond the bound."""

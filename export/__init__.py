"""Checkpoint → ONNX / TorchScript graphs for a robot that runs ONNX Runtime alone.

    python -m export.to_onnx RUN_DIR -o MODEL_DIR            # export (and verify) a trained run
    python -m export.verify MODEL_DIR --checkpoint RUN_DIR   # parity with the PyTorch model

Modules: ``graphs`` (the torch modules that are traced), ``to_onnx`` (the exporter), ``verify`` (parity),
``manifest_writer`` (writes ``dssp_model.json``; the format is :mod:`dssp_deploy.manifest`), ``output_dir``
(all-or-nothing model directories), ``quantize``
(int8), ``trajectory`` (what verification streams); errors are :mod:`dssp_core.errors`.
The names below import lazily, so ``import export`` does not import torch.
"""

from dssp_core.errors import ExportError, ParityError
from dssp_deploy.manifest import FORMAT_VERSION, MANIFEST_NAME, read_manifest

__all__ = [
    "ExportError",
    "FORMAT_VERSION",
    "MANIFEST_NAME",
    "ParityError",
    "export_model",
    "read_manifest",
    "verify_model",
]


def export_model(*args, **kwargs):
    """See :func:`export.to_onnx.export_model`."""
    from export.to_onnx import export_model as _export_model  # deferred: loads torch, tqdm

    return _export_model(*args, **kwargs)


def verify_model(*args, **kwargs):
    """See :func:`export.verify.verify_model`."""
    from export.verify import verify_model as _verify_model  # deferred: loads dssp_train, asyncio, …

    return _verify_model(*args, **kwargs)

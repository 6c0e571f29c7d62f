"""Int8 versions of the exported ONNX graphs (ONNX Runtime dynamic quantization).

Weights of every MatMul/Gemm become int8 (per output channel), activations are quantized on the fly
at run time; everything else (the scan, norms, DDIM arithmetic) stays fp32. ORT's optional pre-processing
(``quant_pre_process``) is skipped: on the robotwin denoiser it took 30 s and made the int8 actions 8x
less exact for a 10 % speed-up. The int8 graphs are not
held to the fp32 parity bound: verification reports their action error against the fp32 graphs and
their speed-up instead.
"""

from __future__ import annotations

import logging
import tempfile
from pathlib import Path

QUANTIZED_OPS = ["MatMul", "Gemm"]


def quantize_int8(src: Path, dst: Path, metadata: dict[str, str]) -> None:
    """Write the int8 graph of ``src`` (an fp32 ``.onnx``) to ``dst``, with ``metadata`` as its metadata_props."""
    import onnx
    from onnxruntime.quantization import QuantType, quantize_dynamic

    with tempfile.TemporaryDirectory(dir=Path(dst).parent) as tmp:
        raw = Path(tmp) / "int8.onnx"
        root = logging.getLogger()
        level = root.level
        root.setLevel(logging.ERROR)  # quantize_dynamic logs a pre-processing suggestion on the root logger
        try:
            quantize_dynamic(src, raw, op_types_to_quantize=QUANTIZED_OPS, per_channel=True, weight_type=QuantType.QInt8)
        finally:
            root.setLevel(level)
        model = onnx.load(str(raw))
    del model.metadata_props[:]
    onnx.helper.set_model_props(model, {**metadata, "quantization": "int8 dynamic (onnxruntime.quantization), MatMul/Gemm weights per channel"})
    onnx.save(model, str(dst))

"""Quantized versions of the exported ONNX graphs, both with ONNX Runtime's own quantizers (the int8 fused denoiser's
blocks excepted: :func:`keep_int8_blocks`).

- int8 (:func:`quantize_int8`): dynamic quantization. Weights of every MatMul/Gemm and of every full convolution
  (DP3's UNet: ``ConvInteger``) become int8 (per output channel, 7-bit range: ``reduce_range``), activations are
  quantized to uint8 on the fly at run time. A depthwise convolution (Mamba's causal one: 4 taps per channel) stays
  fp32: its weights are a few kilobytes, and it is one of the fused operators where the kernel loads.
  Why 7 bits: on x86-64 CPUs without VNNI (AVX2 only) ONNX Runtime multiplies uint8 activations by int8 weights
  with VPMADDUBSW, which adds pairs of products in int16 and saturates: 2 x 255 x 127 overflows, 2 x 255 x 63
  does not (a CPU with VNNI adds in int32 and never saturates). With full-range weights, on an AVX2-only CPU
  the observation encoder's z_t was off by 11 % of its scale (7-bit: 1.6 %) and the demo model's int8 graphs
  failed every closed-loop episode its fp32 graphs passed.
- int4 (:func:`quantize_int4`): weight-only. Every MatMul with a constant weight becomes ``MatMulNBits``
  (4-bit weights in blocks of :data:`INT4_BLOCK` along the input dimension, symmetric, one fp32 scale per
  block); ``accuracy_level`` 4 lets ONNX Runtime compute with int8 activations where the CPU allows.

Everything else (the scan, norms, DDIM arithmetic, the fused Mamba operators) stays fp32. ORT's optional pre-processing
(``quant_pre_process``) is skipped: on the robotwin denoiser it took 30 s and made the int8 actions 8x
less exact for a 10 % speed-up. The int8 graphs are not
held to the fp32 parity bound: verification reports their action error against the fp32 graphs and
their speed-up instead.
"""

from __future__ import annotations

import logging
import tempfile
from pathlib import Path

QUANTIZED_OPS = ["MatMul", "Gemm", "Conv"]
INT4_BLOCK = 32
INT4_ACCURACY_LEVEL = 4


def _quiet_root(fn):
    """Run ``fn()`` with the root and onnxruntime loggers at ERROR: the quantizers log hints and every node they skip."""
    import onnxruntime.quantization.matmul_nbits_quantizer  # noqa: F401 (creates its logger)

    loggers = [logging.getLogger()] + [
        logging.getLogger(name) for name in list(logging.root.manager.loggerDict) if name.startswith("onnxruntime")
    ]
    levels = [logger.level for logger in loggers]
    for logger in loggers:
        logger.setLevel(logging.ERROR)
    try:
        return fn()
    finally:
        for logger, level in zip(loggers, levels):
            logger.setLevel(level)


def _save(model, dst: Path, metadata: dict[str, str], quantization: str) -> None:
    import onnx  # deferred: loads onnx

    del model.metadata_props[:]
    onnx.helper.set_model_props(model, {**metadata, "quantization": quantization})
    onnx.save(model, str(dst))


def quantize_int8(src: Path, dst: Path, metadata: dict[str, str]) -> None:
    """Write the int8 graph of ``src`` (an fp32 ``.onnx``) to ``dst``, with ``metadata`` as its metadata_props."""
    import onnx  # deferred: loads onnx
    from onnxruntime.quantization import QuantType, quantize_dynamic  # deferred: loads onnx, onnxruntime

    convs = [n for n in onnx.load(str(src)).graph.node if n.op_type == "Conv"]
    depthwise = [n.name for n in convs if _group(n) > 1]
    with tempfile.TemporaryDirectory(dir=Path(dst).parent) as tmp:
        raw = Path(tmp) / "int8.onnx"
        _quiet_root(
            lambda: quantize_dynamic(
                src,
                raw,
                op_types_to_quantize=QUANTIZED_OPS,
                nodes_to_exclude=depthwise,
                per_channel=True,
                weight_type=QuantType.QInt8,
                reduce_range=True,
            )
        )
        model = onnx.load(str(raw))
    _save(
        model,
        dst,
        metadata,
        f"int8 dynamic (onnxruntime.quantization), MatMul/Gemm{' and Conv' * (len(convs) > len(depthwise))} weights "
        "per channel, 7-bit (reduce_range)",
    )


def _group(node) -> int:
    """A Conv node's ``group`` attribute (1 when absent: a full convolution)."""
    return next((a.i for a in node.attribute if a.name == "group"), 1)


def quantize_int4(src: Path, dst: Path, metadata: dict[str, str]) -> None:
    """Write the int4 weight-only graph of ``src`` (an fp32 ``.onnx``) to ``dst``, with ``metadata`` as its metadata_props."""
    import onnx  # deferred: loads onnx

    # deferred: loads onnx, onnxruntime
    from onnxruntime.quantization.matmul_nbits_quantizer import DefaultWeightOnlyQuantConfig, MatMulNBitsQuantizer

    config = DefaultWeightOnlyQuantConfig(
        block_size=INT4_BLOCK, is_symmetric=True, accuracy_level=INT4_ACCURACY_LEVEL, op_types_to_quantize=("MatMul",)
    )
    quantizer = MatMulNBitsQuantizer(onnx.load(str(src)), algo_config=config)
    _quiet_root(quantizer.process)
    _save(
        quantizer.model.model,
        dst,
        metadata,
        f"int4 weight-only (onnxruntime MatMulNBits), blocks of {INT4_BLOCK}, symmetric, accuracy_level {INT4_ACCURACY_LEVEL}",
    )


def keep_int8_blocks(src: Path, dst: Path, metadata: dict[str, str]) -> None:
    """Write the graph of ``src`` whose denoiser blocks are ``ai.dssp::MambaBlockQ8`` nodes (int8 weights of their own:
    ``export.fused_ops``) to ``dst`` as it is: what is left around them, the actions' projections (H x d x A), stays
    fp32 — as dynamically quantized products each was five nodes where one fp32 MatMul is both faster and exact."""
    import onnx  # deferred: loads onnx

    _save(
        onnx.load(str(src)),
        dst,
        metadata,
        "int8 in every denoiser block (ai.dssp::MambaBlockQ8: weights symmetric per output row, 8-bit; activations "
        "per row), the actions' projections fp32",
    )


QUANTIZERS = {"int8": quantize_int8, "int4": quantize_int4}

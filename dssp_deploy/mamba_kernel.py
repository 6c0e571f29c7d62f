"""Mamba's fused CPU operators (``ai.dssp::SelectiveScan``, ``ai.dssp::CausalConv1d``): their library, found and loaded.

The library is built from ``dssp_deploy/kernel/mamba_ops.cc`` by ``make kernel`` (part of ``make
setup``) into ``dssp_deploy/kernel/libdssp_mamba.so``; ``DSSP_KERNEL=PATH`` points at another build and
``DSSP_KERNEL=off`` disables it. The exported ``*.fused.onnx`` graphs need it; the standard graphs, which
every model directory has, never do. So the kernel is optional: :func:`kernel` says whether it loads,
and the runtime (:class:`dssp_deploy.onnx_policy.OnnxPolicy`) falls back to the standard graphs when it
does not, saying why in one line.

``DSSP_SCAN_PATH=auto|avx512|avx2|portable`` chooses the library's implementation (see the C++ source;
auto, the default, is the widest this CPU runs).
"""

from __future__ import annotations

import ctypes
import functools
import os
from dataclasses import dataclass
from pathlib import Path

DOMAIN = "ai.dssp"
SCAN_OP = "SelectiveScan"
CONV_OP = "CausalConv1d"
OPSET_VERSION = 1
LIBRARY_NAME = "libdssp_mamba.so"
LIBRARY_ENV = "DSSP_KERNEL"
DEFAULT_LIBRARY = Path(__file__).resolve().parent / "kernel" / LIBRARY_NAME
SCAN_PATHS = ("auto", "avx512", "avx2", "portable")  # the values of DSSP_SCAN_PATH


@dataclass(frozen=True)
class Kernel:
    """Whether the fused Mamba library loads here: ``path`` when it does, else ``reason`` (what to do)."""

    path: Path | None
    reason: str = ""
    implementation: str = ""  # "avx512", "avx2" or "portable": what the library runs on this CPU

    @property
    def available(self) -> bool:
        return self.path is not None


def library_path() -> Path | None:
    """The library to load: ``$DSSP_KERNEL`` if set (None for ``off``), else the one ``make kernel`` builds."""
    env = os.environ.get(LIBRARY_ENV, "").strip()
    if env.lower() in ("off", "0", "none"):
        return None
    return Path(env) if env else DEFAULT_LIBRARY


@functools.lru_cache(maxsize=None)
def _probe(path: Path, scan_path: str) -> Kernel:
    import onnxruntime as ort

    if not path.is_file():
        return Kernel(None, f"{path} is missing (build it with `make kernel`)")
    try:
        ort.SessionOptions().register_custom_ops_library(str(path))
    except Exception as exc:  # onnxruntime raises its own exception types
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        return Kernel(None, f"{path} failed to load ({first}); rebuild it with `make kernel`")
    try:
        fn = ctypes.CDLL(str(path)).DsspScanPath
        fn.restype = ctypes.c_char_p
        implementation = fn().decode()
    except (OSError, AttributeError):
        implementation = "unknown"
    if implementation.startswith("invalid"):  # "invalid: " + the library's reason (an unknown value, or a path this CPU lacks)
        why = implementation.partition(":")[2].strip() or f"DSSP_SCAN_PATH={scan_path!r} cannot be used here; unset it"
        return Kernel(None, why)
    return Kernel(path, implementation=implementation)


def kernel() -> Kernel:
    """The fused Mamba library for this process (probed once per library path and DSSP_SCAN_PATH)."""
    path = library_path()
    if path is None:
        return Kernel(None, f"{LIBRARY_ENV}=off")
    return _probe(path.resolve(), os.environ.get("DSSP_SCAN_PATH", "auto"))


def register(options) -> None:
    """Add the library's operators to ``options`` (an ``onnxruntime.SessionOptions``); it must be available."""
    found = kernel()
    if not found.available:
        raise RuntimeError(f"the fused Mamba library is not available: {found.reason}")
    options.register_custom_ops_library(str(found.path))

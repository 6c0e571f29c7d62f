"""The fused CPU operators (``ai.dssp::SelectiveScan``, ``ai.dssp::CausalConv1d``, ``MambaBlockQ8``, ``DdimStep``, …): their
library, found and loaded.

The library is built from ``dssp_deploy/kernel/mamba_ops.cc`` by ``make kernel`` (part of ``make
setup``) into ``dssp_deploy/kernel/libdssp_mamba.so``; ``DSSP_KERNEL=PATH`` points at another build and
``DSSP_KERNEL=off`` disables it. The exported ``*.fused.onnx`` graphs need it; the standard graphs, which
every model directory has, never do. So the kernel is optional: :func:`kernel` says whether it loads,
and the runtime (:class:`dssp_deploy.onnx_policy.OnnxPolicy`) falls back to the standard graphs when it
does not, saying why in one line.

``DSSP_SCAN_PATH=auto|avx512|avx2|neon|portable`` chooses the library's implementation (see the C++ source;
auto, the default, is the widest this CPU runs; neon is the aarch64 build's).

Before the library is loaded its ELF headers are checked (:func:`elf_problem`): loading a truncated library
maps pages past the end of the file, and the first touch of one kills the process (SIGBUS) — no exception
to catch. A library that fails the check is unavailable, as a missing one is.
"""

from __future__ import annotations

import ctypes
import functools
import os
import struct
import sys
from dataclasses import dataclass
from pathlib import Path

DOMAIN = "ai.dssp"
SCAN_OP = "SelectiveScan"
CONV_OP = "CausalConv1d"
BLOCK_OP = "MambaBlockQ8"  # a whole denoiser block on the action tokens, int8 weights (the int8 fused graphs)
POOL_OP = "LayerNormMaxOverPoints"  # the point encoder's last LayerNorm and max over the points, (B, P, F) -> (B, F)
STEP_OP = "DdimStep"  # the denoiser's readout, the DDIM update and the next step's action tokens (the fused graphs)
OPSET_VERSION = 1
# What the exported graphs need of the library (its DsspKernelRevision(); none: before 1). 1: the attributes that take a
# state after a prefix from a pass over more tokens (MambaBlockQ8's plain, SelectiveScan's and CausalConv1d's state_at),
# which an older library would ignore, giving the state after every token instead. 2: DdimStep, which an older library
# lacks (a session would not load the graph).
KERNEL_REVISION = 2
LIBRARY_NAME = "libdssp_mamba.so"
LIBRARY_ENV = "DSSP_KERNEL"
DEFAULT_LIBRARY = Path(__file__).resolve().parent / "kernel" / LIBRARY_NAME
SCAN_PATHS = ("auto", "avx512", "avx2", "neon", "portable")  # the values of DSSP_SCAN_PATH


@dataclass(frozen=True)
class Kernel:
    """Whether the fused Mamba library loads here: ``path`` when it does, else ``reason`` (what to do)."""

    path: Path | None
    reason: str = ""
    implementation: str = ""  # "avx512", "avx2", "neon" or "portable": what the library runs on this CPU

    @property
    def available(self) -> bool:
        return self.path is not None


def library_path() -> Path | None:
    """The library to load: ``$DSSP_KERNEL`` if set (None for ``off``), else the one ``make kernel`` builds."""
    env = os.environ.get(LIBRARY_ENV, "").strip()
    if env.lower() in ("off", "0", "none"):
        return None
    return Path(env) if env else DEFAULT_LIBRARY


ELF_MAGIC = b"\x7fELF"
ET_DYN = 3  # e_type of a shared library
SHT_NOBITS = 8  # a section with no bytes in the file (.bss)
# Per ELF class (1: 32-bit, 2: 64-bit): the header's (e_type, e_machine, e_phoff, e_shoff, e_phentsize, e_phnum,
# e_shentsize, e_shnum) fields after e_ident, and the sizes and fields of a program header (p_offset, p_filesz)
# and a section header (sh_type, sh_offset, sh_size).
ELF_LAYOUT = {
    1: {"header": ("HH8xII4x2xHHHH", 52), "segment": (32, "4xI8xI"), "section": (40, "4xI8xII")},
    2: {"header": ("HH4x8xQQ4x2xHHHH", 64), "segment": (56, "8xQ16xQ"), "section": (64, "4xI16xQQ")},
}


@functools.lru_cache(maxsize=1)
def _host_elf() -> bytes | None:
    """e_ident[4:6] (class, byte order) and e_machine of this Python's own executable; None when it is no ELF file."""
    try:
        with open(os.path.realpath(sys.executable), "rb") as f:
            head = f.read(20)
    except OSError:
        return None
    return head[4:6] + head[18:20] if head[:4] == ELF_MAGIC and len(head) == 20 else None


def elf_problem(path: Path) -> str | None:
    """What makes ``path`` unsafe to load as this process's shared library, or None: not ELF, another class, byte
    order or machine than this Python, not a shared library, or a header table, segment or section that ends past
    the end of the file (a truncated copy: loading it would kill the process with SIGBUS). Not checked where
    this Python is no ELF executable."""
    host = _host_elf()
    if host is None:
        return None
    try:
        data = path.read_bytes()
    except OSError as exc:
        return f"cannot be read ({exc.strerror or exc})"
    size = len(data)
    if size < 20 or data[:4] != ELF_MAGIC:
        return "is not an ELF shared library"
    if data[4:6] + data[18:20] != host:
        return "is built for another machine or word size than this Python"
    layout = ELF_LAYOUT.get(data[4])
    order = "<" if data[5] == 1 else ">"
    fmt, header = layout["header"] if layout else ("", 0)
    if not layout or size < header:
        return f"is truncated ({size} bytes, shorter than its ELF header)"
    e_type, _, phoff, shoff, phentsize, phnum, shentsize, shnum = struct.unpack_from(order + fmt, data, 16)
    if e_type != ET_DYN:
        return f"is not a shared library (ELF type {e_type})"
    for what, offset, entsize, count, (want, fields) in (
        ("program header", phoff, phentsize, phnum, layout["segment"]),
        ("section header", shoff, shentsize, shnum, layout["section"]),
    ):
        if count and (entsize != want or offset + count * entsize > size):
            return f"is truncated (its {what} table ends at byte {offset + count * entsize}, the file has {size})"
        for i in range(count):
            values = struct.unpack_from(order + fields, data, offset + i * entsize)
            start, length = values[-2:]
            if (what == "program header" or values[0] != SHT_NOBITS) and start + length > size:
                kind = "segment" if what == "program header" else "section"
                return f"is truncated (its {kind} {i} ends at byte {start + length}, the file has {size})"
    return None


@functools.lru_cache(maxsize=None)
def _probe(path: Path, scan_path: str) -> Kernel:
    import onnxruntime as ort  # deferred: loads onnxruntime

    if not path.is_file():
        return Kernel(None, f"{path} is missing (build it with `make kernel`)")
    problem = elf_problem(path)
    if problem:
        return Kernel(None, f"{path} failed to load: it {problem}, so it was not loaded; rebuild it with `make kernel`")
    try:
        ort.SessionOptions().register_custom_ops_library(str(path))
    except Exception as exc:  # onnxruntime raises its own exception types
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        return Kernel(None, f"{path} failed to load ({first}); rebuild it with `make kernel`")
    try:
        library = ctypes.CDLL(str(path))
    except OSError as exc:
        return Kernel(None, f"{path} failed to load ({exc}); rebuild it with `make kernel`")
    revision = library.DsspKernelRevision() if hasattr(library, "DsspKernelRevision") else 0
    if revision < KERNEL_REVISION:
        return Kernel(
            None,
            f"{path} is older than this runtime (revision {revision}, {KERNEL_REVISION} needed: it lacks operators "
            "the graphs use, or would ignore attributes they set); rebuild it with `make kernel`",
        )
    try:
        fn = library.DsspScanPath
        fn.restype = ctypes.c_char_p
        implementation = fn().decode()
    except AttributeError:
        implementation = "unknown"
    if implementation.startswith(
        "invalid"
    ):  # "invalid: " + the library's reason (an unknown value, or a path this CPU lacks)
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

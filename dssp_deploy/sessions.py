"""ONNX Runtime sessions configured for a robot's small, shared CPU (numpy + onnxruntime only).

Thread spinning is off unless asked for: ONNX Runtime's own default lets idle threads busy-wait after every
call, and runs were 2-3x slower when another process (or torch in the same process) shared the cores. When
asked for (``spinning=True``; the runtime does for the denoiser when it has 2 threads or more, ``--no-spin``
stops it), the threads spin only while a run is in progress (``session.force_spinning_stop``): a chunk's
hundreds of small parallel operators then do not each wait for a sleeping thread to wake, and nothing spins
between chunks.
"""

from __future__ import annotations

import os
from pathlib import Path

from dssp_data.errors import ConfigError


def default_threads() -> int:
    """The number of CPUs this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


def check_threads(threads: int | None, flag: str = "--threads") -> None:
    """None (all CPUs) or 1..CPUs: more threads than CPUs only slows a run down, and a huge count exhausts
    the machine's threads and memory."""
    if threads is None:
        return
    cpus = default_threads()
    if isinstance(threads, bool) or not isinstance(threads, int) or not 1 <= threads <= cpus:
        raise ConfigError(f"{flag} must be in [1, {cpus}] (the CPUs this process may use), got {threads!r}")


def session_options(threads: int | None = None, spinning: bool = False, fused: bool = False):
    """``SessionOptions`` with ``intra_op_num_threads`` set and thread spinning off unless asked for (then only
    during a run);
    ``fused``: with the fused Mamba operators registered (:mod:`dssp_deploy.mamba_kernel`)."""
    import onnxruntime as ort

    check_threads(threads)

    options = ort.SessionOptions()
    options.intra_op_num_threads = threads or default_threads()
    options.inter_op_num_threads = 1
    flag = "1" if spinning else "0"
    options.add_session_config_entry("session.intra_op.allow_spinning", flag)
    options.add_session_config_entry("session.inter_op.allow_spinning", flag)
    if spinning:  # spin inside a run only: the threads go to sleep when it returns
        options.add_session_config_entry("session.force_spinning_stop", "1")
    if fused:
        from dssp_deploy.mamba_kernel import register

        register(options)
    return options


def open_session(model: Path | bytes, threads: int | None = None, spinning: bool = False, fused: bool = False):
    """A CPU ``InferenceSession`` for one ``.onnx`` file, given as its path or as its bytes (already checked);
    ``fused`` for a graph with the fused Mamba operators."""
    import onnxruntime as ort

    source = bytes(model) if isinstance(model, (bytes, bytearray, memoryview)) else str(model)
    return ort.InferenceSession(source, session_options(threads, spinning, fused), providers=["CPUExecutionProvider"])

"""ONNX Runtime sessions configured for a shared, small CPU (no torch needed).

Thread spinning is off: with spinning on, idle ORT threads busy-wait between calls, and runs were 2-3x
slower when another process (or torch in the same process) shared the cores.
"""

from __future__ import annotations

import os
from pathlib import Path


def default_threads() -> int:
    """The number of CPUs this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


def session_options(threads: int | None = None):
    """``SessionOptions`` with ``intra_op_num_threads`` set and ``session.intra_op.allow_spinning = 0``."""
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = threads or default_threads()
    options.inter_op_num_threads = 1
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    options.add_session_config_entry("session.inter_op.allow_spinning", "0")
    return options


def open_session(path: Path, threads: int | None = None):
    """A CPU ``InferenceSession`` for one ``.onnx`` file."""
    import onnxruntime as ort

    return ort.InferenceSession(str(path), session_options(threads), providers=["CPUExecutionProvider"])

"""ONNX Runtime sessions configured for a robot's small, shared CPU (numpy + onnxruntime only).

Thread spinning is off unless asked for: ONNX Runtime's own default lets idle threads busy-wait after every
call, and runs were 2-3x slower when another process (or torch in the same process) shared the cores. When
asked for (``spinning=True``; the runtime does for the denoiser when it has 2 threads or more, ``--no-spin``
stops it), the threads spin only while a run is in progress (``session.force_spinning_stop``): a chunk's
hundreds of small parallel operators then do not each wait for a sleeping thread to wake, and nothing spins
between chunks.

A session is opened from a graph's bytes, already checked (``dssp_deploy.manifest.read_graph_files``), never
from a path: ONNX Runtime would read what the graph names as external data from the current directory.
Each external-data file comes as checked bytes too (``external``); a graph naming any other is refused.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path

from dssp_core.errors import ConfigError
from dssp_deploy.external_data import MalformedGraph, external_locations
from dssp_deploy.mamba_kernel import register
from dssp_deploy.manifest import ModelDirError


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
    import onnxruntime as ort  # deferred: loads onnxruntime

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
        register(options)
    return options


def add_external_data(options, model: bytes, external: Mapping[str, bytes] | None = None) -> None:
    """Give ``options`` the files the ONNX graph ``model`` keeps tensors in, from ``external`` ({location: bytes},
    checked by ``dssp_deploy.manifest.read_graph_files``). Raises :class:`ModelDirError` for a graph that names
    any other file: ONNX Runtime would read it from the current directory, unchecked."""
    try:
        locations = external_locations(model)
    except MalformedGraph as exc:
        raise ModelDirError(f"not a well-formed ONNX graph ({exc}); export the model again") from None
    external = external or {}
    unchecked = [loc for loc in locations if loc not in external]
    if unchecked:
        raise ModelDirError(
            f"the graph keeps tensors in external data at {unchecked[0]!r}, which was not read and checked "
            "from the model directory (dssp_deploy.manifest.read_graph_files); refused"
        )
    if locations:
        options.add_external_initializers_from_files_in_memory(
            locations, [external[loc] for loc in locations], [len(external[loc]) for loc in locations]
        )


def open_session(
    model: Path | bytes,
    threads: int | None = None,
    spinning: bool = False,
    fused: bool = False,
    external: Mapping[str, bytes] | None = None,
):
    """A CPU ``InferenceSession`` for one ``.onnx`` graph, given as its bytes (already checked) or its path (read
    here); ``external``: the checked bytes of the files its tensors' external data name (see
    :func:`add_external_data`); ``fused`` for a graph with the fused Mamba operators."""
    import onnxruntime as ort  # deferred: loads onnxruntime

    data = bytes(model) if isinstance(model, (bytes, bytearray, memoryview)) else Path(model).read_bytes()
    options = session_options(threads, spinning, fused)
    add_external_data(options, data, external)
    return ort.InferenceSession(data, options, providers=["CPUExecutionProvider"])

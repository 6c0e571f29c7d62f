"""Where a graph's time goes: ONNX Runtime's own per-node profiler, summed by operator type.

    breakdown = op_type_breakdown(path, feeds, threads=2, runs=5)
    # [{"op": "Mul", "ms": 53.5, "nodes": 1389, "share": 0.25}, ...] per run, largest first

This is how ``dssp-profile`` explains a latency: for the robotwin denoiser most of the time is elementwise
work (Mul/Add/Exp/Split/Concat) on the selective scan's state-expanded tensors, (L, E, n) per layer and
DDIM step, not matrix products.
"""

from __future__ import annotations

import collections
import json
import os
from pathlib import Path

import numpy as np

from dssp_deploy.sessions import add_external_data, session_options


def op_type_breakdown(
    path: Path,
    feeds: dict[str, np.ndarray],
    threads: int | None = None,
    runs: int = 5,
    warmup: int = 2,
    fused: bool = False,
    model: bytes | None = None,
    external: dict[str, bytes] | None = None,
) -> list[dict]:
    """Kernel time per run by operator type, over ``runs`` profiled calls after ``warmup`` calls
    (``fused``: a graph with the fused Mamba operators). ``model`` and ``external``: the graph's checked bytes and
    those of its external data (``dssp_deploy.manifest.read_graph_files``; default: ``path``'s bytes, which may
    name no external data)."""
    import onnxruntime as ort  # deferred: loads onnxruntime

    options = session_options(threads, fused=fused)
    options.enable_profiling = True
    options.profile_file_prefix = str(Path(path).with_suffix("")) + "_opprofile"
    data = Path(path).read_bytes() if model is None else model
    add_external_data(options, data, external)
    session = ort.InferenceSession(data, options, providers=["CPUExecutionProvider"])
    for _ in range(warmup):
        session.run(None, feeds)
    # Profiling starts with the session; drop warm-up events by counting runs in the trace.
    for _ in range(runs):
        session.run(None, feeds)
    trace = session.end_profiling()
    try:
        events = json.loads(Path(trace).read_text())
    finally:
        os.remove(trace)
    total_runs = warmup + runs
    time_us: collections.Counter = collections.Counter()
    nodes: collections.Counter = collections.Counter()
    for event in events:
        if event.get("cat") == "Node" and event.get("name", "").endswith("_kernel_time"):
            op = event["args"]["op_name"]
            time_us[op] += event["dur"]
            nodes[op] += 1
    grand = sum(time_us.values()) or 1
    return [
        {"op": op, "ms": us / total_runs / 1e3, "nodes": nodes[op] // total_runs, "share": us / grand}
        for op, us in time_us.most_common()
    ]


ELEMENTWISE = {"Mul", "Add", "Sub", "Exp", "Split", "Concat", "Slice", "Gather", "Softplus", "Sigmoid", "Neg"}


def elementwise_share(breakdown: list[dict]) -> float:
    """Fraction of kernel time spent in elementwise/copy ops (the scan's state-expanded work)."""
    return sum(row["share"] for row in breakdown if row["op"] in ELEMENTWISE)

"""Latency statistics, resident memory and this machine's float32 GEMM peak (numpy only).

Shapes: none; times in milliseconds, memory in MiB, throughput in GFLOP/s.
"""

from __future__ import annotations

import os
import resource
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass

import numpy as np


@dataclass
class LatencyStats:
    """Percentiles of a list of durations, in milliseconds."""

    n: int
    p50: float
    p95: float
    p99: float
    max: float
    mean: float

    @classmethod
    def of(cls, samples_ms) -> "LatencyStats":
        x = np.asarray(samples_ms, dtype=np.float64)
        if x.size == 0:
            raise ValueError("no samples to summarise")
        p50, p95, p99 = np.percentile(x, [50, 95, 99])
        return cls(int(x.size), float(p50), float(p95), float(p99), float(x.max()), float(x.mean()))

    def to_dict(self) -> dict:
        return asdict(self)


def time_calls(fn: Callable[[], object], iterations: int, warmup: int = 3) -> list[float]:
    """Durations (ms) of ``iterations`` calls of ``fn`` after ``warmup`` untimed calls."""
    for _ in range(warmup):
        fn()
    samples = []
    for _ in range(iterations):
        t0 = time.perf_counter()
        fn()
        samples.append((time.perf_counter() - t0) * 1e3)
    return samples


def resident_memory_mib() -> float:
    """Current resident set size of this process (Linux /proc), else the peak from getrusage."""
    try:
        with open(f"/proc/{os.getpid()}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def gemm_peak_gflops(size: int = 1024, repeats: int = 5) -> float:
    """Best float32 GEMM throughput of numpy's BLAS on a size^3 product (2 * size^3 flops per call)."""
    rng = np.random.default_rng(0)
    a = rng.standard_normal((size, size), dtype=np.float32)
    b = rng.standard_normal((size, size), dtype=np.float32)
    a @ b  # warm-up
    best = min(time_calls(lambda: a @ b, repeats, warmup=1))
    return 2 * size**3 / (best / 1e3) / 1e9

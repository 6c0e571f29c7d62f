"""Latency statistics, resident memory, and this machine's float32 GEMM peak and memory bandwidth (numpy only).

Shapes: none; times in milliseconds, memory in MiB, throughput in GFLOP/s, bandwidth in GB/s.
"""

from __future__ import annotations

import os
import resource
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

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


def memory_read_gbs(mib: int = 256, repeats: int = 5) -> float:
    """Best read bandwidth (GB/s) of numpy summing a float32 array far larger than any cache."""
    a = np.ones(mib * 2**20 // 4, dtype=np.float32)
    a.sum()  # warm-up: pages touched
    best = min(time_calls(a.sum, repeats, warmup=1))
    return a.nbytes / (best / 1e3) / 1e9


CACHE_PROBE_MIB = (2, 4, 8, 12, 16, 24, 32, 64, 128)


def read_bandwidth_by_size(sizes_mib: tuple[int, ...] = CACHE_PROBE_MIB, repeats: int = 10) -> list[tuple[int, float]]:
    """[(MiB, best GB/s)] of numpy's vectorised max over float32 arrays of each size, read again and again: the
    sizes the process's share of the caches holds read far faster than the ones that stream from memory."""
    out = []
    for mib in sizes_mib:
        a = np.ones(mib * 2**20 // 4, dtype=np.float32)
        a.max()  # warm-up: pages touched, the array in whatever cache holds it
        best = min(time_calls(a.max, repeats, warmup=1))
        out.append((mib, a.nbytes / (best / 1e3) / 1e9))
    return out


def effective_cache_bytes(profile: list[tuple[int, float]], factor: float = 2.0) -> int | None:
    """The largest probed size read at least ``factor`` times faster than the largest (memory), as bytes: the cache
    this process actually gets, which on a shared machine can be far less than the CPU's (None: none was)."""
    memory = profile[-1][1]
    cached = [mib for mib, gbs in profile[:-1] if gbs >= factor * memory]
    return max(cached) * 2**20 if cached else None


def last_level_cache_bytes() -> int | None:
    """Size of the largest CPU cache (Linux sysfs), None where it cannot be read."""
    sizes = []
    for index in Path("/sys/devices/system/cpu/cpu0/cache").glob("index*"):
        try:
            text = (index / "size").read_text().strip()
        except OSError:
            continue
        unit = {"K": 2**10, "M": 2**20, "G": 2**30}.get(text[-1:].upper(), 1)
        digits = text[:-1] if text[-1:].isalpha() else text
        if digits.isdecimal():
            sizes.append(int(digits) * unit)
    return max(sizes) if sizes else None

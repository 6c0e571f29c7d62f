"""The machine a figure was measured on, as every record states it (benchmarks, studies, the demo)."""

from __future__ import annotations

import os
import platform
from importlib import metadata

FLAGS = ("avx2", "avx512f", "avx512_vnni", "avx_vnni", "amx_tile")
"""The CPU features that change what the kernels and ONNX Runtime's int8 products compute fastest."""
PACKAGES = ("numpy", "onnxruntime", "torch", "mujoco")


def cpu() -> tuple[str, list[str]]:
    """(CPU model, the :data:`FLAGS` it has) from /proc/cpuinfo, or the platform's processor name and []."""
    name, flags = platform.processor() or platform.machine(), []
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    name = line.split(":", 1)[1].strip()
                elif line.startswith("flags"):
                    have = set(line.split(":", 1)[1].split())
                    flags = [flag for flag in FLAGS if flag in have]
                    break
    except OSError:
        pass
    return name, flags


def describe() -> dict:
    """CPU model and features, cores, OS, Python and the installed versions of :data:`PACKAGES` (none imported)."""
    name, flags = cpu()
    info = {
        "cpu": name,
        "cpu_flags": flags,
        "cores": os.cpu_count(),
        "os": platform.platform(),
        "python": platform.python_version(),
    }
    for package in PACKAGES:
        try:
            info[package] = metadata.version(package)
        except metadata.PackageNotFoundError:
            pass
    return info

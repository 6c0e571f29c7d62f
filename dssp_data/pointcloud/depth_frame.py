"""What a depth camera hands out: one frame and its pinhole intrinsics.

A RealSense, a recorded bag, the simulated scenes and a ROS 2 bag's depth topic (``dssp-data convert``) all give
:class:`DepthFrame`, the point-cloud pipeline's input (:func:`dssp_data.pointcloud.frame_to_cloud`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of a depth stream, in pixels (RealSense ``rs.intrinsics`` without distortion)."""

    width: int
    height: int
    fx: float
    fy: float
    ppx: float
    ppy: float

    def to_dict(self) -> dict:
        return {k: getattr(self, k) for k in ("width", "height", "fx", "fy", "ppx", "ppy")}


@dataclass(frozen=True)
class DepthFrame:
    """One depth frame (optionally with colour aligned to it).

    depth: (H, W) uint16 raw units; metres = depth * depth_unit; 0 means no measurement.
    color: (H, W, 3) uint8 RGB aligned to depth, or None.
    timestamp: host time of arrival, ``time.monotonic()`` seconds (what staleness checks use).
    device_timestamp_ms: the camera's own timestamp, for logs.
    """

    depth: np.ndarray
    depth_unit: float
    intrinsics: Intrinsics
    timestamp: float
    frame_number: int
    device_timestamp_ms: float = 0.0
    color: np.ndarray | None = None

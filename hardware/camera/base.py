"""The camera interface: a context manager that keeps the newest depth frame.

    with open_camera("l515") as cam:          # hardware.camera.open_camera
        frame = cam.latest()                  # DepthFrame or None before the first frame

Every implementation (RealSense, recorded file, simulated scene) hands out the same :class:`DepthFrame`,
so the point-cloud pipeline (``hardware.pointcloud``) never knows where a frame came from.
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np

from dssp_core.errors import CameraError


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


class Camera(ABC):
    """Start, hand out the newest frame, stop. Subclasses run their own capture thread (or none)."""

    name: str = "camera"

    @abstractmethod
    def start(self) -> None: ...

    @abstractmethod
    def latest(self) -> DepthFrame | None:
        """The newest frame (never blocks), or None before the first one."""

    @abstractmethod
    def stop(self) -> None: ...

    def wait_for_frame(self, timeout: float = 5.0) -> DepthFrame:
        """Block until a frame is available (raises ``CameraError`` after ``timeout`` seconds)."""


        deadline = time.monotonic() + timeout
        while True:
            frame = self.latest()
            if frame is not None:
                return frame
            if time.monotonic() > deadline:
                raise CameraError(f"{self.name}: no frame within {timeout:g} s; check the cable/USB3 port or the recording")
            time.sleep(0.002)

    def __enter__(self) -> "Camera":
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

"""The camera interface: a context manager that keeps the newest depth frame.

    with open_camera("l515") as cam:          # hardware.camera.open_camera
        frame = cam.latest()                  # DepthFrame or None before the first frame

Every implementation (RealSense, recorded file, simulated scene) hands out the same
:class:`~dssp_data.pointcloud.depth_frame.DepthFrame`, so the point-cloud pipeline (``dssp_data.pointcloud``) never
knows where a frame came from.
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod

from dssp_core.errors import CameraError
from dssp_data.pointcloud.depth_frame import DepthFrame


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
                raise CameraError(
                    f"{self.name}: no frame within {timeout:g} s; check the cable/USB3 port or the recording"
                )
            time.sleep(0.002)

    def __enter__(self) -> "Camera":
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

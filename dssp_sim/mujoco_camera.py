"""MuJoCo's rendered depth as a RealSense camera: rendered frames go through ``rs.software_device``.

:class:`MujocoCamera` is a :class:`hardware.camera.base.Camera` whose frames are rendered from a
:class:`~dssp_sim.env.PiperEnv` and injected into a software RealSense depth sensor, so the same
conversion code as a live L515 turns them into ``DepthFrame`` s, and the same point-cloud pipeline
(``dssp_data.pointcloud``) makes the clouds — for collected datasets and at evaluation alike.

Stepped: ``capture()`` renders the env as it is now (the caller advances the physics).
"""

from __future__ import annotations

import numpy as np

from dssp_core.errors import CameraError
from dssp_data.pointcloud.depth_frame import DepthFrame
from hardware.camera.base import Camera
from hardware.camera.software import SoftwareDepthCamera


class MujocoCamera(Camera):
    name = "mujoco"

    def __init__(self, env, fps: int = 30):
        self.env, self.fps = env, fps
        _, self.depth_unit, self.intrinsics, camera_to_base = env.render_depth()
        self.camera_to_base = np.asarray(camera_to_base, np.float64)  # (4, 4), what a calibration gives
        self._device: SoftwareDepthCamera | None = None
        self._latest: DepthFrame | None = None
        self._number = 0

    def start(self) -> None:
        if self._device is None:
            self._device = SoftwareDepthCamera(self.intrinsics, self.depth_unit, fps=self.fps)
            self._device.start()

    def capture(self) -> DepthFrame:
        """Render the env now and pass the frame through the software sensor; returns it (and keeps it)."""
        if self._device is None:
            raise CameraError("mujoco camera: not started; call start() or use it as a context manager")
        depth, _, _, _ = self.env.render_depth()
        self._latest = self._device.push(np.ascontiguousarray(depth, np.uint16), frame_number=self._number)
        self._number += 1
        return self._latest

    def latest(self) -> DepthFrame | None:
        return self._latest

    def stop(self) -> None:
        if self._device is not None:
            self._device.stop()
            self._device = None

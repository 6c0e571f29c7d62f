"""Depth frames made in numpy, passed through librealsense: ``rs.software_device`` helpers.

:class:`SoftwareDepthCamera` injects (H, W) uint16 depth (and optionally (H, W, 3) uint8 RGB colour
already aligned to it) into a software depth sensor, and takes real ``rs.depth_frame`` s out of an
``rs.syncer``; each is converted by :func:`hardware.camera.realsense.depth_frame_from_rs`, exactly as a
live camera's frames are. :func:`record_depth` writes such frames to a ``.db3`` recording (``rs.recorder``)
that ``rs.pipeline`` — and so :class:`~hardware.camera.realsense.RealSenseCamera` ``(file=...)`` — plays back.

Used by the simulated camera (``hardware.camera.tabletop``) and by tests. ``rs.pipeline`` cannot open a
software device, so frames come out through the syncer, not through a pipeline.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from dssp_core.errors import CameraError
from dssp_core.files import atomic_write
from dssp_data.pointcloud.depth_frame import DepthFrame, Intrinsics
from hardware.camera.base import Camera
from hardware.camera.realsense import depth_frame_from_rs, import_rs


def _rs_intrinsics(rs, intr: Intrinsics):
    out = rs.intrinsics()
    out.width, out.height = int(intr.width), int(intr.height)
    out.fx, out.fy, out.ppx, out.ppy = float(intr.fx), float(intr.fy), float(intr.ppx), float(intr.ppy)
    out.model = rs.distortion.none
    out.coeffs = [0.0] * 5
    return out


class SoftwareDepthCamera(Camera):
    """A software RealSense depth sensor fed from numpy.

    intrinsics: of the depth (and colour) images, pixels. depth_unit: metres per raw unit (e.g. 0.00025).
    fps: the stream's nominal rate; default timestamps are frame_number * 1000 / fps ms.
    color: also register an rgb8 colour stream with the same intrinsics (identity extrinsics to depth).
    record_to: a recording path (``.db3`` on pyrealsense2 2.59); every injected frame is also recorded
    there (the file is complete once ``stop()`` has run).

        with SoftwareDepthCamera(intr, 0.00025) as cam:
            frame = cam.push(depth)              # DepthFrame through the real conversion code
            depth_frame, _ = cam.inject(depth)   # or the rs.depth_frame itself (e.g. for rs.pointcloud)
    """

    name = "software"

    def __init__(
        self,
        intrinsics: Intrinsics,
        depth_unit: float,
        fps: int = 30,
        color: bool = False,
        record_to: str | Path | None = None,
    ) -> None:
        if not (isinstance(depth_unit, (int, float)) and 0 < depth_unit <= 0.01):
            raise CameraError(f"depth_unit must be metres per raw unit in (0, 0.01], got {depth_unit!r}")
        if not (isinstance(fps, int) and fps > 0):
            raise CameraError(f"fps must be a positive integer, got {fps!r}")
        self.intrinsics = intrinsics
        self.depth_unit = float(depth_unit)
        self.fps = fps
        self.color = bool(color)
        self.record_to = None if record_to is None else Path(record_to).expanduser()
        self._rs = None
        self._lock = threading.Lock()
        self._latest: DepthFrame | None = None
        self._next_number = 0
        self._started = False

    def start(self) -> None:
        if self._started:
            return
        rs = self._rs = import_rs()
        intr = _rs_intrinsics(rs, self.intrinsics)
        self._device = rs.software_device()
        self._depth_sensor = self._device.add_sensor("Depth")
        vs = rs.video_stream()
        vs.type, vs.index, vs.uid = rs.stream.depth, 0, 0
        vs.width, vs.height, vs.fps, vs.bpp, vs.fmt = intr.width, intr.height, self.fps, 2, rs.format.z16
        vs.intrinsics = intr
        self._depth_profile = self._depth_sensor.add_video_stream(vs).as_video_stream_profile()
        self._depth_sensor.add_read_only_option(rs.option.depth_units, self.depth_unit)
        sensors = [(self._depth_sensor, self._depth_profile)]
        if self.color:
            self._color_sensor = self._device.add_sensor("Color")
            cs = rs.video_stream()
            cs.type, cs.index, cs.uid = rs.stream.color, 0, 1
            cs.width, cs.height, cs.fps, cs.bpp, cs.fmt = intr.width, intr.height, self.fps, 3, rs.format.rgb8
            cs.intrinsics = intr
            self._color_profile = self._color_sensor.add_video_stream(cs).as_video_stream_profile()
            ext = rs.extrinsics()
            ext.rotation = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
            ext.translation = [0.0, 0.0, 0.0]
            self._depth_profile.register_extrinsics_to(self._color_profile, ext)
            sensors.append((self._color_sensor, self._color_profile))
        self._recorder = None
        if self.record_to is not None:
            self.record_to.parent.mkdir(parents=True, exist_ok=True)
            if self.record_to.exists():
                self.record_to.unlink()
            try:
                self._recorder = rs.recorder(str(self.record_to), self._device)
            except RuntimeError as e:  # e.g. pyrealsense2 2.59: "Output file must have .db3 extension"
                first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
                raise CameraError(f"cannot record to {self.record_to} ({first})") from None
        # Queue several framesets: until the syncer has seen both streams it may emit them separately.
        self._syncer = rs.syncer(8)
        for sensor, profile in sensors:
            sensor.open(profile)
            sensor.start(self._syncer)
        self._sensors = [s for s, _ in sensors]
        self._next_number = 0
        self._started = True

    def _check(self, depth: np.ndarray, color: np.ndarray | None) -> tuple[np.ndarray, np.ndarray | None]:
        h, w = self.intrinsics.height, self.intrinsics.width
        depth = np.asarray(depth)
        if depth.shape != (h, w) or depth.dtype != np.uint16:
            raise CameraError(f"depth must be ({h}, {w}) uint16, got {depth.dtype} {depth.shape}")
        if self.color:
            if color is None:
                raise CameraError("this software camera has a colour stream: pass color=(H, W, 3) uint8 RGB")
            color = np.asarray(color)
            if color.shape != (h, w, 3) or color.dtype != np.uint8:
                raise CameraError(f"color must be ({h}, {w}, 3) uint8, got {color.dtype} {color.shape}")
        elif color is not None:
            raise CameraError("color given but the software camera was made with color=False")
        return np.ascontiguousarray(depth), None if color is None else np.ascontiguousarray(color)

    def inject(
        self,
        depth: np.ndarray,
        color: np.ndarray | None = None,
        *,
        frame_number: int | None = None,
        timestamp_ms: float | None = None,
        timeout: float = 1.0,
    ):
        """Inject one frame; return the ``(rs.depth_frame, rs.video_frame | None)`` the syncer hands back.

        depth: (H, W) uint16 raw units; color: (H, W, 3) uint8 RGB (required iff ``color=True``).
        frame_number: default counts up from 0; timestamp_ms: default frame_number * 1000 / fps.
        The pixels are copied by librealsense, so the arrays may be reused afterwards.
        """
        if not self._started:
            raise CameraError("software camera not started; call start() or use it as a context manager")
        rs = self._rs
        depth, color = self._check(depth, color)
        number = self._next_number if frame_number is None else int(frame_number)
        self._next_number = number + 1
        ts = number * 1000.0 / self.fps if timestamp_ms is None else float(timestamp_ms)
        w = self.intrinsics.width
        f = rs.software_video_frame()
        f.pixels, f.stride, f.bpp = depth, w * 2, 2
        f.timestamp, f.domain, f.frame_number = ts, rs.timestamp_domain.hardware_clock, number
        f.profile, f.depth_units = self._depth_profile, self.depth_unit
        self._depth_sensor.on_video_frame(f)
        if color is not None:
            g = rs.software_video_frame()
            g.pixels, g.stride, g.bpp = color, w * 3, 3
            g.timestamp, g.domain, g.frame_number = ts, rs.timestamp_domain.hardware_clock, number
            g.profile = self._color_profile
            self._color_sensor.on_video_frame(g)
        return self._collect(number, timeout)

    def _collect(self, number: int, timeout: float):
        """Drain the syncer until this frame number's depth (and colour) came out."""
        depth_frame = color_frame = None
        deadline = time.monotonic() + timeout
        while True:
            remaining_ms = max(0, int((deadline - time.monotonic()) * 1000))
            ok, frames = self._syncer.try_wait_for_frames(remaining_ms)
            if not ok:
                missing = "depth" if not depth_frame else "colour"
                raise CameraError(
                    f"software camera: injected frame {number} did not come out of the syncer "
                    f"({missing} missing after {timeout:g} s)"
                )
            d = frames.get_depth_frame()
            if d and d.get_frame_number() == number:
                depth_frame = d
            if self.color:
                c = frames.get_color_frame()
                if c and c.get_frame_number() == number:
                    color_frame = c
            if depth_frame and (color_frame or not self.color):
                return depth_frame, color_frame

    def push(
        self,
        depth: np.ndarray,
        color: np.ndarray | None = None,
        *,
        frame_number: int | None = None,
        timestamp_ms: float | None = None,
    ) -> DepthFrame:
        """Inject one frame and return it as a :class:`DepthFrame` (also kept as ``latest()``)."""
        depth_frame, color_frame = self.inject(depth, color, frame_number=frame_number, timestamp_ms=timestamp_ms)
        frame = depth_frame_from_rs(depth_frame, color_frame)
        with self._lock:
            self._latest = frame
        return frame

    def latest(self) -> DepthFrame | None:
        with self._lock:
            return self._latest

    def stop(self) -> None:
        if not self._started:
            return
        self._started = False
        for sensor in self._sensors:
            try:
                sensor.stop()
                sensor.close()
            except RuntimeError:
                pass
        # Dropping the recorder finalises the .db3 file.
        self._recorder = None
        self._sensors = []
        self._syncer = None
        self._depth_sensor = self._color_sensor = None
        self._depth_profile = self._color_profile = None
        self._device = None


def record_depth(
    path: str | Path,
    frames: Iterable[np.ndarray],
    intrinsics: Intrinsics,
    depth_unit: float,
    fps: int = 30,
    colors: Iterable[np.ndarray] | None = None,
    pace: bool = True,
) -> Path:
    """Write depth frames (each (H, W) uint16 raw units; optional colours (H, W, 3) uint8 RGB) to a recording.

    path: the file to write; pyrealsense2 2.59 records rosbag2 only, so it must end in ``.db3`` there
    (older SDKs write rosbag1 ``.bag``). The recorder's own complaint becomes a one-line CameraError.

    Frame numbers count from 0, device timestamps are frame_number * 1000 / fps ms. Playback in real time
    follows the wall-clock time at which frames were written, so ``pace=True`` writes them 1/fps s apart;
    with ``pace=False`` the file is written at once and must be played with ``real_time=False``.
    An existing file at ``path`` is replaced. Returns the path.
    """
    path = Path(path).expanduser()
    color_iter = None if colors is None else iter(colors)

    def write(tmp: str) -> None:
        cam = SoftwareDepthCamera(intrinsics, depth_unit, fps=fps, color=color_iter is not None, record_to=tmp)
        n = 0
        try:
            try:
                cam.start()
            except CameraError as e:  # name the user's path, not the temporary one
                raise CameraError(str(e).replace(tmp, str(path))) from None
            t0 = time.monotonic()
            for depth in frames:
                color = None
                if color_iter is not None:
                    color = next(color_iter, None)
                    if color is None:
                        raise CameraError(f"record_depth: fewer colour images than depth frames ({n})")
                if pace:
                    delay = t0 + n / fps - time.monotonic()
                    if delay > 0:
                        time.sleep(delay)
                cam.inject(depth, color)
                n += 1
        finally:
            cam.stop()
        if n == 0:
            raise CameraError(f"record_depth: no frames given for {path}")

    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, write, suffix=f".tmp{path.suffix}")
    return path

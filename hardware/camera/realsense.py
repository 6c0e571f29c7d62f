"""Intel RealSense cameras and recordings through pyrealsense2's ``rs.pipeline``.

    cam = RealSenseCamera("d435", serial="123456789012", color=True)   # a live camera
    cam = RealSenseCamera(file="episode.db3", real_time=False)          # a .bag / .db3 recording
    with cam:
        frame = cam.wait_for_frame()                                   # hardware.camera.DepthFrame

Also :func:`depth_frame_from_rs`, the one conversion from an ``rs.depth_frame`` (+ colour) to a
:class:`DepthFrame` that every implementation uses (live, playback, software device, simulation), and
:func:`check_sdk_support`, which refuses the L515 on librealsense >= 2.54 (where L500 support was
removed) before anything touches USB.

pyrealsense2 is imported lazily, so ``hardware.camera`` imports without it.
"""

from __future__ import annotations

import threading
import time
import warnings
from pathlib import Path

import numpy as np

from dssp_core.errors import CameraError
from dssp_data.pointcloud.depth_frame import DepthFrame, Intrinsics
from hardware.camera.base import Camera
from hardware.camera.profiles import CameraProfile, load_profile, parse_version

RECORDING_SUFFIXES = (".bag", ".db3")

_warned_distortion: set[str] = set()


def import_rs():
    """The pyrealsense2 module, or a CameraError that says how to install it."""
    try:
        import pyrealsense2 as rs  # optional: pyrealsense2 (the hardware extra), imported on first use
    except ImportError as e:
        hint = (
            "install the system library: apt-get install -y libusb-1.0-0"
            if "libusb" in str(e)
            else "install it: pip install pyrealsense2 (or pip install 'dssp[hardware]')"
        )
        raise CameraError(f"pyrealsense2 cannot be imported ({e}); {hint}") from None
    return rs


def sdk_version() -> str:
    """The installed librealsense version as reported by pyrealsense2, e.g. '2.59.1'."""
    rs = import_rs()
    return str(getattr(rs, "__version__", "0"))


def l515_sdk_message(version: str) -> str:
    """The one-line explanation for an L515 requested on a librealsense that no longer supports it."""
    return (
        f"the L515 needs librealsense <= 2.53, but pyrealsense2 {version} is installed (L500 support was "
        f"removed in 2.54); use Python 3.10 with `pip install pyrealsense2==2.53.1.*`, or build librealsense "
        f"<= 2.53 from source; L515 recordings still play on this SDK with file:PATH"
    )


def check_sdk_support(profile: CameraProfile, version: str | None = None) -> None:
    """Raise CameraError when ``profile``'s model is not supported by librealsense ``version``.

    version: e.g. '2.59.1'; None reads the installed pyrealsense2's version (importing it touches no USB).
    """
    if profile.removed_in_sdk is None:
        return
    version = sdk_version() if version is None else str(version)
    if profile.supported_by_sdk(version):
        return
    if profile.product_line == "L500":
        raise CameraError(l515_sdk_message(version))
    raise CameraError(
        f"the {profile.device_name} is not supported by librealsense {version} (removed in "
        f"{profile.removed_in_sdk}); install an older pyrealsense2 (< {profile.removed_in_sdk})"
    )


def intrinsics_from_rs(intr) -> Intrinsics:
    """``rs.intrinsics`` -> :class:`Intrinsics` (pixels). Distortion is not kept: RealSense depth streams
    (L515, D4xx) report zero coefficients; a warning is issued once if a stream does not."""
    coeffs = [float(c) for c in getattr(intr, "coeffs", [])]
    if any(abs(c) > 1e-9 for c in coeffs):
        model = str(getattr(intr, "model", "?"))
        if model not in _warned_distortion:
            _warned_distortion.add(model)
            warnings.warn(
                f"depth stream reports distortion {model} {coeffs}; point clouds ignore it (pinhole deprojection)",
                RuntimeWarning,
                stacklevel=3,
            )
    return Intrinsics(
        width=int(intr.width),
        height=int(intr.height),
        fx=float(intr.fx),
        fy=float(intr.fy),
        ppx=float(intr.ppx),
        ppy=float(intr.ppy),
    )


def _clean_unit(unit: float) -> float:
    """The SDK stores depth units as float32 (0.00025 -> 0.0002500000118743628); keep 7 significant digits."""
    return float(f"{float(unit):.7g}")


def depth_frame_from_rs(depth_frame, color_frame=None, *, arrival: float | None = None) -> DepthFrame:
    """An ``rs.depth_frame`` (and optionally an ``rs.video_frame`` of colour aligned to it) -> :class:`DepthFrame`.

    depth: (H, W) uint16 copied out of the SDK's frame pool; depth_unit from the frame (metres per unit);
    intrinsics from the frame's stream profile; color: (H, W, 3) uint8 RGB (rgb8 or bgr8 input), which must
    have the depth's size (align it first with ``rs.align(rs.stream.depth)``).
    arrival: host ``time.monotonic()`` seconds when the frame arrived; None = now.
    device_timestamp_ms / frame_number: the SDK's ``get_timestamp()`` / ``get_frame_number()``.
    """
    arrival = time.monotonic() if arrival is None else float(arrival)
    if not depth_frame:
        raise CameraError("no depth frame in the frameset; check that the depth stream is enabled")
    intr = intrinsics_from_rs(depth_frame.profile.as_video_stream_profile().get_intrinsics())
    depth = np.asanyarray(depth_frame.get_data())
    if depth.dtype != np.uint16 or depth.shape != (intr.height, intr.width):
        raise CameraError(
            f"depth frame is {depth.dtype} {depth.shape}, expected uint16 "
            f"({intr.height}, {intr.width}); request the z16 depth format"
        )
    depth = np.array(depth, copy=True)
    color = None
    if color_frame:
        rs = import_rs()
        fmt = color_frame.profile.format()
        data = np.asanyarray(color_frame.get_data())
        if fmt not in (rs.format.rgb8, rs.format.bgr8) or data.ndim != 3 or data.shape[2] != 3:
            raise CameraError(f"colour format {fmt} is not supported; request rgb8 (or bgr8)")
        if data.shape[:2] != depth.shape:
            raise CameraError(
                f"colour is {data.shape[1]}x{data.shape[0]} but depth is {depth.shape[1]}x"
                f"{depth.shape[0]}; align colour to depth (rs.align(rs.stream.depth)) first"
            )
        color = np.array(data[..., ::-1] if fmt == rs.format.bgr8 else data, dtype=np.uint8, copy=True)
    return DepthFrame(
        depth=depth,
        depth_unit=_clean_unit(depth_frame.get_units()),
        intrinsics=intr,
        timestamp=arrival,
        frame_number=int(depth_frame.get_frame_number()),
        device_timestamp_ms=float(depth_frame.get_timestamp()),
        color=color,
    )


def list_devices() -> list[dict]:
    """Connected RealSense devices: [{'name', 'serial', 'product_line', 'firmware'}] (strings; '' if unknown)."""
    rs = import_rs()
    out = []
    for dev in rs.context().query_devices():
        info = {}
        for key, field in (
            ("name", rs.camera_info.name),
            ("serial", rs.camera_info.serial_number),
            ("product_line", rs.camera_info.product_line),
            ("firmware", rs.camera_info.firmware_version),
        ):
            try:
                info[key] = dev.get_info(field) if dev.supports(field) else ""
            except RuntimeError:
                info[key] = ""
        out.append(info)
    return out


def describe_devices(devices: list[dict]) -> str:
    """'Intel RealSense D435 (serial 123, D400), ...' or 'none'."""
    if not devices:
        return "none"
    return ", ".join(f"{d['name'] or '?'} (serial {d['serial'] or '?'}, {d['product_line'] or '?'})" for d in devices)


def choose_device(profile: CameraProfile, devices: list[dict], serial: str | None, sdk: str | None = None) -> dict:
    """The device to open for ``profile`` (and ``serial`` if given) among ``devices``, or a one-line CameraError.

    sdk: the installed librealsense version; on >= 2.54 the message adds that an L515 is not listed at all.
    """
    if not devices:
        l515 = ""
        if sdk is not None and parse_version(sdk) >= (2, 54):
            l515 = f"; an L515 is never listed by pyrealsense2 {sdk} (use librealsense <= 2.53 for it)"
        raise CameraError(
            f"no RealSense device connected (looking for a {profile.device_name}); check the USB3 "
            f"cable and port (lsusb should show an Intel 8086: device), the udev rules "
            f"(99-realsense-libusb.rules), and that no other program (realsense-viewer) holds the "
            f"camera{l515}"
        )
    if serial is not None:
        for d in devices:
            if d["serial"] == str(serial):
                if profile.device_name.lower() not in d["name"].lower():
                    raise CameraError(
                        f"device {serial} is a {d['name']}, not a {profile.device_name}; use the "
                        f"profile that matches it or another --serial (connected: "
                        f"{describe_devices(devices)})"
                    )
                return d
        raise CameraError(
            f"no RealSense device with serial {serial}; connected: {describe_devices(devices)}; check --serial"
        )
    matching = [d for d in devices if profile.device_name.lower() in d["name"].lower()]
    if not matching:
        raise CameraError(
            f"no {profile.device_name} connected; connected: {describe_devices(devices)}; use the "
            f"profile that matches the camera or plug in the {profile.device_name}"
        )
    if len(matching) > 1:
        raise CameraError(
            f"{len(matching)} {profile.device_name} cameras connected "
            f"({describe_devices(matching)}); choose one with --serial"
        )
    return matching[0]


class RealSenseCamera(Camera):
    """A live RealSense camera or a recording, read by ``rs.pipeline`` in a capture thread.

    RealSenseCamera(profile="l515" | "d435" | "d405" | CameraProfile, serial=None, color=False)
    RealSenseCamera(file="x.db3" | "x.bag", repeat_playback=False, real_time=True, color=False)

    The constructor checks everything that needs no USB (profile, SDK support, the file); ``start()``
    opens the device. The capture thread keeps only the newest :class:`DepthFrame` (host arrival time
    ``time.monotonic()``, device timestamp, frame number, intrinsics from the stream); ``latest()``
    never blocks. ``color=True`` adds an rgb8 stream aligned to depth (``rs.align``; as the SDK does,
    pixels without depth get black colour, and colour is resampled even when the geometry is identical).
    poll_timeout: seconds per wait for a frameset in the thread (how quickly stop() and the end of a
    recording are noticed).
    For recordings: ``repeat_playback`` loops the file; ``real_time=False`` plays as fast as the capture
    thread reads, without skipping frames (``latest()`` still returns only the newest);
    ``playback_finished`` turns True at the end. Real-time playback follows the wall-clock times at which
    the frames were recorded.
    """

    def __init__(
        self,
        profile: str | CameraProfile | None = None,
        *,
        serial: str | None = None,
        file: str | Path | None = None,
        color: bool = False,
        repeat_playback: bool = False,
        real_time: bool = True,
        poll_timeout: float = 0.2,
        sdk: str | None = None,
    ) -> None:
        if file is not None and (profile is not None or serial is not None):
            raise CameraError("give either a camera profile (with an optional serial) or file=PATH, not both")
        if file is None and profile is None:
            raise CameraError("give a camera profile (l515, d435, d405) or file=PATH of a .bag/.db3 recording")
        self.color = bool(color)
        self.serial = None if serial is None else str(serial)
        self.repeat_playback = bool(repeat_playback)
        self.real_time = bool(real_time)
        self.poll_timeout = float(poll_timeout)
        self.profile: CameraProfile | None = None
        self.file: Path | None = None
        if file is not None:
            self.file = Path(file).expanduser()
            self._check_file()
            self.name = f"file:{self.file}"
        else:
            self.profile = profile if isinstance(profile, CameraProfile) else load_profile(profile)
            check_sdk_support(self.profile, sdk)  # the L515 on librealsense >= 2.54: refuse before USB
            self.name = self.profile.name if self.serial is None else f"{self.profile.name}:{self.serial}"
        self._pipe = None
        self._rs = None
        self._align = None
        self._playback = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._latest: DepthFrame | None = None
        self._error: str | None = None
        self._frames = 0
        self._finished = False
        self.device: dict = {}

    # -- setup -------------------------------------------------------------------------------------------
    def _check_file(self) -> None:
        f = self.file
        if f.suffix.lower() not in RECORDING_SUFFIXES:
            raise CameraError(f"recording {f} must be a .bag or .db3 file (rosbag / rosbag2 from librealsense)")
        if not f.exists():
            raise CameraError(f"recording {f} does not exist; check the path")
        if not f.is_file():
            raise CameraError(f"recording {f} is not a file; give the .bag/.db3 file itself")

    def _configure_file(self, rs):
        self._check_file()
        cfg = rs.config()
        cfg.enable_device_from_file(str(self.file), repeat_playback=self.repeat_playback)
        cfg.enable_stream(rs.stream.depth)
        if self.color:
            cfg.enable_stream(rs.stream.color)
        self.device = {"name": "recording", "serial": "", "product_line": "", "firmware": "", "file": str(self.file)}
        return cfg

    def _configure_device(self, rs):
        p = self.profile
        self.device = choose_device(p, list_devices(), self.serial, sdk=sdk_version())
        cfg = rs.config()
        cfg.enable_device(self.device["serial"])
        cfg.enable_stream(rs.stream.depth, p.width, p.height, getattr(rs.format, p.format), p.fps)
        if self.color:
            if p.color is None:
                raise CameraError(f"profile {p.name} has no colour stream; open it without color")
            c = p.color
            cfg.enable_stream(rs.stream.color, c.width, c.height, getattr(rs.format, c.format), c.fps)
        return cfg

    def start(self) -> None:
        if self._thread is not None:
            return
        rs = import_rs()
        cfg = self._configure_file(rs) if self.file is not None else self._configure_device(rs)
        pipe = rs.pipeline()
        try:
            # Configure the device before streaming: pipe.start() reuses the device cfg.resolve() picked.
            # For recordings this matters: switching to non-real-time after start() is too late, a
            # recording written quickly is then dumped at once and most of its frames are dropped.
            resolved = cfg.resolve(rs.pipeline_wrapper(pipe))
            if self.file is not None:
                resolved.get_device().as_playback().set_real_time(self.real_time)
            else:
                self._set_depth_unit(rs, resolved.get_device())
            started = pipe.start(cfg)
        except RuntimeError as e:
            raise CameraError(self._start_failure(str(e))) from None
        if self.file is not None:
            self._playback = started.get_device().as_playback()
        self._pipe, self._rs = pipe, rs
        self._align = rs.align(rs.stream.depth) if self.color else None
        self._stop.clear()
        self._error, self._latest, self._frames, self._finished = None, None, 0, False
        self._thread = threading.Thread(target=self._run, name=f"camera-{self.name}", daemon=True)
        self._thread.start()

    def _start_failure(self, msg: str) -> str:
        line = msg.strip().splitlines()[0] if msg.strip() else "unknown error"
        if self.file is not None:
            if "resolve" in line.lower() and self.color:
                return (
                    f"recording {self.file} has no colour stream matching the request ({line}); open it without color"
                )
            return f"cannot play recording {self.file} ({line}); check that it is a librealsense .bag/.db3 recording"
        return (
            f"{self.name}: cannot start {self.profile.width}x{self.profile.height} depth @ {self.profile.fps} fps "
            f"({line}); check the USB3 connection and that no other program uses the camera"
        )

    def _set_depth_unit(self, rs, dev) -> None:
        """Ask the depth sensor for the profile's unit when it is settable (D4xx); L515's is fixed."""
        sensor = dev.first_depth_sensor()
        opt = rs.option.depth_units
        if sensor.supports(opt) and not sensor.is_option_read_only(opt):
            try:
                sensor.set_option(opt, self.profile.depth_unit)
            except RuntimeError:
                pass  # the unit in use is read from every frame anyway

    # -- capture thread ----------------------------------------------------------------------------------
    def _run(self) -> None:
        timeout_ms = max(1, int(self.poll_timeout * 1000))
        try:
            while not self._stop.is_set():
                ok, frames = self._pipe.try_wait_for_frames(timeout_ms)
                if not ok:
                    if self._playback is not None and not self.repeat_playback:
                        if self._playback.current_status() == self._rs.playback_status.stopped and self._frames:
                            self._finished = True
                    continue
                arrival = time.monotonic()
                if self._align is not None:
                    frames = self._align.process(frames)
                depth = frames.get_depth_frame()
                color = frames.get_color_frame() if self.color else None
                if not depth or (self.color and not color):
                    continue  # a frameset without depth or colour: wait for a complete one
                frame = depth_frame_from_rs(depth, color, arrival=arrival)
                with self._lock:
                    self._latest = frame
                    self._frames += 1
        except CameraError as e:
            self._error = f"{self.name}: {e}"
        except RuntimeError as e:
            first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            self._error = f"{self.name}: capture stopped ({first}); check the cable and restart"

    # -- Camera API ----------------------------------------------------------------------------------------
    def latest(self) -> DepthFrame | None:
        """The newest frame, or None before the first. Raises CameraError if the capture thread failed."""
        if self._error is not None:
            raise CameraError(self._error)
        with self._lock:
            return self._latest

    @property
    def frames_received(self) -> int:
        """How many frames the capture thread has converted since ``start()``."""
        return self._frames

    @property
    def playback_finished(self) -> bool:
        """True once a recording opened with ``repeat_playback=False`` has been played to its end."""
        return self._finished

    def stop(self) -> None:
        thread, self._thread = self._thread, None
        if thread is not None:
            self._stop.set()
            thread.join(timeout=self.poll_timeout + 2.0)
        pipe, self._pipe = self._pipe, None
        if pipe is not None:
            try:
                pipe.stop()
            except RuntimeError:
                pass  # already stopped (end of a recording)
        self._playback = None
        self._align = None

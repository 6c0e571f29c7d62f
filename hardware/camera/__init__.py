"""Depth cameras: RealSense devices and recordings, a simulated tabletop, and :func:`open_camera`.

    with open_camera("l515") as cam:         # or "d435", "d405", "file:episode.db3", "tabletop"
        frame = cam.wait_for_frame()         # DepthFrame: depth (H, W) uint16, depth_unit m, intrinsics

Modules: ``base`` (the interface), ``profiles`` (stream profiles as data), ``realsense`` (rs.pipeline),
``software`` (rs.software_device: numpy frames through the SDK, .db3 recordings), ``tabletop`` (the
simulated tabletop camera, spec ``tabletop``). pyrealsense2 is imported only when a camera is opened.
"""

from __future__ import annotations

from pathlib import Path

from dssp_core.errors import CameraError
from dssp_data.pointcloud.depth_frame import DepthFrame, Intrinsics
from hardware.camera.base import Camera
from hardware.camera.profiles import CameraProfile, load_profile, profile_names
from hardware.camera.realsense import RealSenseCamera

TABLETOP = "tabletop"  # the spec of the simulated tabletop camera (hardware.camera.tabletop)

__all__ = [
    "TABLETOP",
    "Camera",
    "CameraProfile",
    "DepthFrame",
    "Intrinsics",
    "check_camera_spec",
    "load_profile",
    "open_camera",
    "spec_forms",
]


def spec_forms() -> str:
    """The accepted camera specs, for messages and --help: 'd405|d435|l515|file:PATH|tabletop'."""
    return "|".join(profile_names() + ["file:PATH", TABLETOP])


def check_camera_spec(spec: str, serial: str | None = None) -> None:
    """Refuse a camera spec that :func:`open_camera` cannot open, without opening anything (CameraError)."""
    if not isinstance(spec, str) or not spec.strip():
        raise CameraError(f"camera spec must be one of {spec_forms()}, got {spec!r}")
    text = spec.strip()
    if text.lower().startswith("file:"):
        path = text[len("file:") :]
        if not path:
            raise CameraError("camera spec file: needs a path, e.g. file:episode.db3")
        if serial is not None:
            raise CameraError("a serial number selects a live camera; it cannot be used with file:PATH")
        if not Path(path).expanduser().is_file():
            raise CameraError(
                f"camera recording {path} does not exist (or is not a file); give a .bag or .db3 recording"
            )
        return
    name = text.lower()
    if name == "sim":  # the spelling before there were two simulators
        raise CameraError(
            "camera 'sim' is ambiguous: the simulated tabletop camera is 'tabletop'; the MuJoCo Piper's "
            "camera is 'mujoco' (dssp-sim record only)"
        )
    if name == "mujoco":
        raise CameraError(
            "camera 'mujoco' is the MuJoCo Piper's and exists only under dssp-sim (dssp-sim record); "
            f"here use one of {spec_forms()}"
        )
    if name == TABLETOP:
        if serial is not None:
            raise CameraError(f"a serial number selects a live camera; it cannot be used with {TABLETOP}")
        return
    if name not in profile_names():
        raise CameraError(f"unknown camera {spec!r}; use one of {spec_forms()}")


def open_camera(spec: str, serial: str | None = None, color: bool = False, **kw) -> Camera:
    """A camera for ``spec`` (not started; use it as a context manager or call ``start()``).

    spec: a profile name ('l515', 'd435', 'd405'; case-insensitive) for a live RealSense, optionally with
    ``serial``; 'file:PATH' for a .bag/.db3 recording (keywords ``repeat_playback``, ``real_time``);
    'tabletop' for the simulated tabletop (keywords of :class:`hardware.camera.tabletop.SimCamera`, e.g. ``seed``).
    color: also deliver RGB aligned to depth. Unknown specs raise CameraError listing the valid forms.
    """
    check_camera_spec(spec, serial)
    text = spec.strip()
    if text.lower().startswith("file:"):
        path = text[len("file:") :]
        return RealSenseCamera(file=path, color=color, **kw)
    name = text.lower()
    if name == TABLETOP:
        from hardware.camera.tabletop import SimCamera  # deferred: loads hardware.camera.software, uuid

        return SimCamera(color=color, **kw)
    return RealSenseCamera(name, serial=serial, color=color, **kw)

"""Camera stream profiles as data: ``profiles.json`` next to this module, loaded into :class:`CameraProfile`.

    profile = load_profile("l515")   # 640x480 z16 @ 30 fps, depth unit 0.00025 m, product line L500

A profile says which stream to ask the SDK for and what the depth unit should be; the unit a frame
really carries is read from the frame itself (``DepthFrame.depth_unit``). No pyrealsense2 here.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

from hardware.errors import CameraError

PROFILES_PATH = Path(__file__).with_name("profiles.json")

_DEPTH_FORMATS = ("z16",)
_COLOR_FORMATS = ("rgb8", "bgr8")
_VERSION_RE = re.compile(r"^\d+(\.\d+)*$")


def parse_version(version: str) -> tuple[int, ...]:
    """'2.59.1' or '2.53.1.6145' -> (2, 59, 1) / (2, 53, 1, 6145); leading numeric fields only."""
    parts = []
    for field in str(version).strip().split("."):
        m = re.match(r"\d+", field)
        if m is None:
            break
        parts.append(int(m.group()))
        if m.end() != len(field):
            break
    if not parts:
        raise CameraError(f"cannot read a version number from {version!r}; expected e.g. '2.53.1'")
    return tuple(parts)


@dataclass(frozen=True)
class ColorProfile:
    """The colour stream requested with ``color=True`` (aligned to depth afterwards). Pixels, fps."""

    width: int
    height: int
    fps: int
    format: str = "rgb8"

    def __post_init__(self) -> None:
        for key in ("width", "height", "fps"):
            value = getattr(self, key)
            if not isinstance(value, int) or isinstance(value, bool) or value <= 0:
                raise CameraError(f"colour profile: {key} must be a positive integer, got {value!r}")
        if self.format not in _COLOR_FORMATS:
            raise CameraError(f"colour profile: format {self.format!r} is not one of {', '.join(_COLOR_FORMATS)}")


@dataclass(frozen=True)
class CameraProfile:
    """One depth camera model: the depth stream to request and what to expect from it.

    width, height: depth image size in pixels; fps: frames per second; format: 'z16' (uint16 raw depth).
    depth_unit: metres per raw depth unit the camera should deliver.
    product_line / device_name: how the device identifies itself (``rs.camera_info.product_line`` /
    a substring of ``rs.camera_info.name``), used to pick the right device and to list others.
    removed_in_sdk: first librealsense version without support for this model ('2.54' for the L515), or None.
    """

    name: str
    width: int
    height: int
    fps: int
    depth_unit: float
    product_line: str
    device_name: str
    format: str = "z16"
    description: str = ""
    color: ColorProfile | None = None
    removed_in_sdk: str | None = None

    def __post_init__(self) -> None:
        where = f"camera profile {self.name!r}"
        for key in ("width", "height", "fps"):
            value = getattr(self, key)
            if not isinstance(value, int) or isinstance(value, bool) or value <= 0:
                raise CameraError(f"{where}: {key} must be a positive integer, got {value!r}")
        unit = self.depth_unit
        number = isinstance(unit, (int, float)) and not isinstance(unit, bool)
        if not number or not math.isfinite(unit) or not 0 < unit <= 0.01:
            raise CameraError(f"{where}: depth_unit must be metres per raw unit in (0, 0.01], got {unit!r}")
        if self.format not in _DEPTH_FORMATS:
            raise CameraError(f"{where}: depth format {self.format!r} is not supported; "
                              f"use {', '.join(_DEPTH_FORMATS)}")
        if not self.product_line or not self.device_name:
            raise CameraError(f"{where}: product_line and device_name must be non-empty")
        if self.removed_in_sdk is not None and not _VERSION_RE.match(str(self.removed_in_sdk)):
            raise CameraError(f"{where}: removed_in_sdk must look like '2.54', got {self.removed_in_sdk!r}")

    @classmethod
    def from_dict(cls, name: str, data: dict) -> "CameraProfile":
        if not isinstance(data, dict):
            raise CameraError(f"camera profile {name!r}: expected a JSON object, got {type(data).__name__}")
        known = {"description", "product_line", "device_name", "width", "height", "fps", "format", "depth_unit",
                 "color", "removed_in_sdk"}
        unknown = sorted(set(data) - known)
        if unknown:
            raise CameraError(f"camera profile {name!r}: unknown keys {unknown}; known: {sorted(known)}")
        missing = sorted({"product_line", "device_name", "width", "height", "fps", "depth_unit"} - set(data))
        if missing:
            raise CameraError(f"camera profile {name!r}: missing keys {missing}")
        color = data.get("color")
        if color is not None:
            if not isinstance(color, dict):
                raise CameraError(f"camera profile {name!r}: 'color' must be an object or null")
            try:
                color = ColorProfile(**color)
            except TypeError as e:
                raise CameraError(f"camera profile {name!r}: bad 'color' entry ({e})") from None
        fields = {k: v for k, v in data.items() if k != "color"}
        return cls(name=name, color=color, **fields)

    def to_dict(self) -> dict:
        out = {k: getattr(self, k) for k in ("description", "product_line", "device_name", "width", "height",
                                             "fps", "format", "depth_unit", "removed_in_sdk")}
        out["color"] = None if self.color is None else dict(vars(self.color))
        return out

    def supported_by_sdk(self, sdk_version: str) -> bool:
        """False when the installed librealsense (e.g. '2.59.1') no longer supports this model."""
        if self.removed_in_sdk is None:
            return True
        return parse_version(sdk_version) < parse_version(self.removed_in_sdk)


@lru_cache(maxsize=None)
def _load_all(path: str) -> dict[str, CameraProfile]:
    try:
        data = json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise CameraError(f"camera profiles file {path} is missing; reinstall the package") from None
    except json.JSONDecodeError as e:
        raise CameraError(f"camera profiles file {path} is not valid JSON (line {e.lineno}: {e.msg})") from None
    if not isinstance(data, dict) or not data:
        raise CameraError(f"camera profiles file {path} must hold a non-empty JSON object of profiles")
    return {name: CameraProfile.from_dict(name, entry) for name, entry in data.items()}


def profile_names() -> list[str]:
    """The known profile names, sorted."""
    return sorted(_load_all(str(PROFILES_PATH)))


def load_profile(name: str) -> CameraProfile:
    """The profile called ``name`` (case-insensitive); CameraError listing the known names otherwise."""
    profiles = _load_all(str(PROFILES_PATH))
    key = str(name).strip().lower()
    if key not in profiles:
        raise CameraError(f"unknown camera profile {name!r}; known profiles: {', '.join(sorted(profiles))}")
    return profiles[key]

"""Camera stream profiles as data: ``profiles.json`` next to this module, loaded into :class:`CameraProfile`.

    profile = load_profile("l515")   # 640x480 z16 @ 30 fps, depth unit 0.00025 m, product line L500

A profile says which stream to ask the SDK for and what the depth unit should be; the unit a frame
really carries is read from the frame itself (``DepthFrame.depth_unit``). No pyrealsense2 here.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import ClassVar

from dssp_core.errors import CameraError, ConfigError
from dssp_core.schema import Settings, read_json_object, setting

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
class ColorProfile(Settings):
    """The colour stream requested with ``color=True`` (aligned to depth afterwards). Pixels, fps."""

    SECTION: ClassVar[str] = "camera profile color"

    width: int = setting(ge=1, le=8192, unit="pixels")
    height: int = setting(ge=1, le=8192, unit="pixels")
    fps: int = setting(ge=1, le=1000)
    format: str = setting("rgb8", choices=_COLOR_FORMATS)


@dataclass(frozen=True)
class CameraProfile(Settings):
    """One depth camera model: the depth stream to request and what to expect from it.

    width, height: depth image size in pixels; fps: frames per second; format: 'z16' (uint16 raw depth).
    depth_unit: metres per raw depth unit the camera should deliver.
    product_line / device_name: how the device identifies itself (``rs.camera_info.product_line`` /
    a substring of ``rs.camera_info.name``), used to pick the right device and to list others.
    removed_in_sdk: first librealsense version without support for this model ('2.54' for the L515), or None.
    """

    SECTION: ClassVar[str] = "camera profile"

    name: str = setting()
    width: int = setting(ge=1, le=8192, unit="pixels")
    height: int = setting(ge=1, le=8192, unit="pixels")
    fps: int = setting(ge=1, le=1000)
    depth_unit: float = setting(gt=0, le=0.01, unit="m per raw unit")
    product_line: str = setting()
    device_name: str = setting()
    format: str = setting("z16", choices=_DEPTH_FORMATS)
    description: str = setting("")
    color: ColorProfile | None = setting(None)
    removed_in_sdk: str | None = setting(None)

    def validate(self) -> None:
        if not self.product_line or not self.device_name:
            raise ConfigError(f"camera profile {self.name!r}: product_line and device_name must be non-empty")
        if self.removed_in_sdk is not None and not _VERSION_RE.match(self.removed_in_sdk):
            raise ConfigError(
                f"camera profile {self.name!r}: removed_in_sdk must look like '2.54', got {self.removed_in_sdk!r}"
            )

    @classmethod
    def from_entry(cls, name: str, data: dict) -> "CameraProfile":
        """One entry of ``profiles.json`` (the key is the name); CameraError naming the profile."""
        if not isinstance(data, dict):
            raise CameraError(f"camera profile {name!r}: expected a JSON object, got {type(data).__name__}")
        try:
            return cls.from_dict({**data, "name": name})
        except ConfigError as exc:
            raise CameraError(f"camera profile {name!r}: {exc}") from None

    def to_entry(self) -> dict:
        """The ``profiles.json`` entry (without the name, its key)."""
        out = self.to_dict()
        out.pop("name")
        return out

    def supported_by_sdk(self, sdk_version: str) -> bool:
        """False when the installed librealsense (e.g. '2.59.1') no longer supports this model."""
        if self.removed_in_sdk is None:
            return True
        return parse_version(sdk_version) < parse_version(self.removed_in_sdk)


@lru_cache(maxsize=None)
def _load_all(path: str) -> dict[str, CameraProfile]:
    data = read_json_object(path, "camera profiles", error=CameraError, hint="reinstall the package")
    if not data:
        raise CameraError(f"camera profiles file {path} must hold a non-empty JSON object of profiles")
    return {name: CameraProfile.from_entry(name, entry) for name, entry in data.items()}


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

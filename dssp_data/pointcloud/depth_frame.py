"""What a depth camera hands out: one frame and its pinhole intrinsics.

A RealSense, a recorded bag, the simulated scenes and a ROS 2 bag's depth topic (``dssp-data convert``) all give
:class:`DepthFrame`, the point-cloud pipeline's input (:func:`dssp_data.pointcloud.frame_to_cloud`).
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from dssp_core.errors import ConfigError

MAX_IMAGE_SIDE = 16384
"""Pixels an image side may have (a 16K sensor; a larger value is a damaged header)."""
MAX_FOCAL_PX = 1e6
"""The longest focal length in pixels (a 16384-pixel image seeing under 1 degree); beyond it a unit mistake."""
DISTORTION_TOLERANCE = 1e-9
"""Distortion coefficients up to this are zero: the pipeline deprojects an undistorted (rectified) image."""


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of a depth stream, in pixels (RealSense ``rs.intrinsics`` without distortion).

    Checked on construction, the one check of a camera's intrinsics wherever they come from (a camera, a bag's
    CameraInfo, a LeRobot feature's ``info``): width and height whole numbers in [1, MAX_IMAGE_SIDE], fx and fy
    finite in (0, MAX_FOCAL_PX], the principal point (ppx, ppy) finite and inside the image ([0, width] x
    [0, height]). A ConfigError line names the field and its value.
    """

    width: int
    height: int
    fx: float
    fy: float
    ppx: float
    ppy: float

    def __post_init__(self) -> None:
        for name in ("width", "height"):
            value = getattr(self, name)
            if not (
                isinstance(value, numbers.Integral) and not isinstance(value, bool) and 1 <= value <= MAX_IMAGE_SIDE
            ):
                raise ConfigError(
                    f"camera intrinsics: {name} is {value!r}; it must be a whole number of pixels in "
                    f"[1, {MAX_IMAGE_SIDE}]"
                )
        ranges = {
            "fx": (0.0, MAX_FOCAL_PX, "in (0, {hi:g}]"),
            "fy": (0.0, MAX_FOCAL_PX, "in (0, {hi:g}]"),
            "ppx": (0.0, float(self.width), "inside the image, [0, {hi:g}]"),
            "ppy": (0.0, float(self.height), "inside the image, [0, {hi:g}]"),
        }
        for name, (low, high, where) in ranges.items():
            value = getattr(self, name)
            number = isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value)
            inside = number and (low < value if name in ("fx", "fy") else low <= value) and value <= high
            if not inside:
                raise ConfigError(
                    f"camera intrinsics: {name} is {value!r}; it must be a finite number of pixels "
                    f"{where.format(hi=high)}"
                )

    @classmethod
    def rectified(cls, width, height, fx, fy, ppx, ppy, distortion: Sequence[float] = ()) -> Intrinsics:
        """Intrinsics of a camera whose ``distortion`` coefficients (e.g. a CameraInfo's D) are all zero: a NaN, an
        infinite or a non-zero coefficient is one ConfigError line (the pipeline has no distortion model)."""
        values = np.asarray(distortion, dtype=np.float64).reshape(-1)
        bad = np.flatnonzero(~np.isfinite(values) | (np.abs(values) > DISTORTION_TOLERANCE))
        if bad.size:
            raise ConfigError(
                f"camera intrinsics: lens distortion D[{int(bad[0])}] is {float(values[bad[0]])!r}; the "
                "clouds are made from a rectified image, whose distortion is zero"
            )
        return cls(width, height, fx, fy, ppx, ppy)

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

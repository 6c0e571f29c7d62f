"""Point-cloud preprocessing settings: :class:`PointCloudConfig`, stored as plain JSON (no pickles).

The same config is used to build a dataset and on the robot, so a policy sees identical clouds in both.
All lengths are metres; the crop box is in the robot-base frame (after the camera->base extrinsic).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

from dssp_data.files import atomic_write_text
from dssp_data.errors import ConfigError
from dssp_data.schema import Settings, setting

SAMPLING_METHODS = ("fps",)
MAX_RANGE_M = 20.0  # no depth camera of the toolkit measures farther; a larger value is a unit mistake (mm)
MAX_CROP_M = 100.0  # a crop corner this far out keeps everything; beyond it the box was given in millimetres


@dataclass(frozen=True)
class PointCloudConfig(Settings):
    """How a depth frame becomes a fixed-size cloud.

    n_points: points per cloud (P), default 1024.
    depth_near, depth_far: keep camera depths in [near, far] metres (0 = no measurement is always dropped).
    crop_min, crop_max: workspace box (x, y, z) metres in the robot-base frame; points outside are dropped.
      The default is a tabletop workspace in front of the arm base (base at the origin, x forward, z up,
      table surface at z = 0) and keeps the table surface.
    voxel_size: metres, 0 = off. One measured point is kept per occupied voxel before sampling.
      1 cm is about a third of the spacing of 1024 points spread over a 0.8 m x 0.8 m table, so it does
      not change what farthest point sampling picks, and it makes sampling several times faster.
    use_color: append RGB in [0, 1] as channels 3..5 (the frames must carry colour).
    sampling: 'fps' (farthest point sampling).
    """

    SECTION: ClassVar[str] = "pointcloud"

    n_points: int = setting(1024, ge=1, le=1_000_000)
    depth_near: float = setting(0.1, ge=0, le=MAX_RANGE_M, unit="m")
    depth_far: float = setting(2.0, gt=0, le=MAX_RANGE_M, unit="m")
    crop_min: tuple[float, float, float] = setting((0.0, -0.4, -0.02), ge=-MAX_CROP_M, le=MAX_CROP_M, unit="m")
    crop_max: tuple[float, float, float] = setting((0.8, 0.4, 0.5), ge=-MAX_CROP_M, le=MAX_CROP_M, unit="m")
    voxel_size: float = setting(0.01, ge=0, le=1.0, unit="m (0 = off)")
    use_color: bool = setting(False)
    sampling: str = setting("fps", choices=SAMPLING_METHODS)

    def validate(self) -> None:
        if not self.depth_near < self.depth_far:
            raise ConfigError(f"pointcloud.depth_near ({self.depth_near}) must be below depth_far "
                              f"({self.depth_far}), metres")
        if not all(a < b for a, b in zip(self.crop_min, self.crop_max)):
            raise ConfigError(f"pointcloud.crop_min {list(self.crop_min)} must be below crop_max "
                              f"{list(self.crop_max)} on every axis")

    @property
    def point_dim(self) -> int:
        """Channels per point: 3 (xyz) or 6 (xyz + rgb)."""
        return 6 if self.use_color else 3

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2)

    @classmethod
    def from_json(cls, text: str) -> "PointCloudConfig":
        try:
            data = json.loads(text)
        except json.JSONDecodeError as e:
            raise ConfigError(f"point cloud config is not valid JSON (line {e.lineno}: {e.msg})") from None
        return cls.from_dict(data)

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        atomic_write_text(path, self.to_json() + "\n")
        return path

"""Point-cloud preprocessing settings: :class:`PointCloudConfig`, stored as plain JSON (no pickles).

The same config is used to build a dataset and on the robot, so a policy sees identical clouds in both.
All lengths are metres; the crop box is in the robot-base frame (after the camera->base extrinsic).
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, fields
from pathlib import Path

from dssp_train.errors import ConfigError

SAMPLING_METHODS = ("fps",)


def _vec3(name: str, value) -> tuple[float, float, float]:
    try:
        out = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        raise ConfigError(f"point cloud config: {name} must be 3 numbers (x, y, z metres), got {value!r}") from None
    if len(out) != 3 or not all(math.isfinite(v) for v in out):
        raise ConfigError(f"point cloud config: {name} must be 3 finite numbers (x, y, z metres), got {value!r}")
    return out


@dataclass(frozen=True)
class PointCloudConfig:
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

    n_points: int = 1024
    depth_near: float = 0.1
    depth_far: float = 2.0
    crop_min: tuple[float, float, float] = (0.0, -0.4, -0.02)
    crop_max: tuple[float, float, float] = (0.8, 0.4, 0.5)
    voxel_size: float = 0.01
    use_color: bool = False
    sampling: str = "fps"

    def __post_init__(self) -> None:
        n = self.n_points
        if isinstance(n, bool) or not isinstance(n, int) or not 1 <= n <= 1_000_000:
            raise ConfigError(f"point cloud config: n_points must be an integer in [1, 1000000], got {n!r}")
        for key in ("depth_near", "depth_far", "voxel_size"):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise ConfigError(f"point cloud config: {key} must be a finite number >= 0 (metres), got {v!r}")
            object.__setattr__(self, key, float(v))
        if not self.depth_near < self.depth_far:
            raise ConfigError(f"point cloud config: depth_near ({self.depth_near}) must be below depth_far "
                              f"({self.depth_far}), metres")
        if self.voxel_size > 1.0:
            raise ConfigError(f"point cloud config: voxel_size {self.voxel_size} m is larger than 1 m; "
                              f"give metres (0 = off)")
        lo, hi = _vec3("crop_min", self.crop_min), _vec3("crop_max", self.crop_max)
        if not all(a < b for a, b in zip(lo, hi)):
            raise ConfigError(f"point cloud config: crop_min {lo} must be below crop_max {hi} on every axis")
        object.__setattr__(self, "crop_min", lo)
        object.__setattr__(self, "crop_max", hi)
        if not isinstance(self.use_color, bool):
            raise ConfigError(f"point cloud config: use_color must be true or false, got {self.use_color!r}")
        if self.sampling not in SAMPLING_METHODS:
            raise ConfigError(f"point cloud config: sampling {self.sampling!r} is not one of "
                              f"{', '.join(SAMPLING_METHODS)}")

    @property
    def point_dim(self) -> int:
        """Channels per point: 3 (xyz) or 6 (xyz + rgb)."""
        return 6 if self.use_color else 3

    def to_dict(self) -> dict:
        """JSON-ready dict (tuples become lists)."""
        out = asdict(self)
        out["crop_min"], out["crop_max"] = list(self.crop_min), list(self.crop_max)
        return out

    @classmethod
    def from_dict(cls, data: dict) -> "PointCloudConfig":
        """Inverse of :meth:`to_dict`; unknown keys are an error (a typo must not be ignored)."""
        if not isinstance(data, dict):
            raise ConfigError(f"point cloud config must be a JSON object, got {type(data).__name__}")
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ConfigError(f"point cloud config: unknown keys {unknown}; known: {sorted(known)}")
        return cls(**data)

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
        path.write_text(self.to_json() + "\n")
        return path

    @classmethod
    def load(cls, path: str | Path) -> "PointCloudConfig":
        path = Path(path)
        if not path.is_file():
            raise ConfigError(f"point cloud config {path} does not exist; check the path")
        return cls.from_json(path.read_text())

"""The one depth-frame -> point-cloud pipeline, used both to build datasets and on the robot.

    cloud, info = frame_to_cloud(frame, PointCloudConfig(), camera_to_base)
    # cloud (P, 3) float32 metres, robot-base frame — or (P, 6) with RGB in [0, 1] when use_color

Stages (each timed in ``CloudInfo.timings_ms``):

1. clip — keep pixels whose depth is in [depth_near, depth_far] (compared on the raw uint16 values;
   depth 0 = no measurement never survives).
2. deproject — pixel (u, v) with depth z -> camera point z * ((u - ppx) / fx, (v - ppy) / fy, 1)
   (pinhole, as ``rs2_deproject_pixel_to_point`` without distortion), and the camera->base transform,
   in one step: the per-pixel rays are rotated into the base frame once per (intrinsics, extrinsics)
   and cached, so a point is base = z * ray_base + t.
3. crop — keep points inside the workspace box (base frame).
4. voxel — keep one measured point per occupied voxel (not the centroid: cheaper, and every output
   point is a real measurement with its own colour).
5. sample — farthest point sampling to ``n_points`` with fpsample's bucket FPS (QuickFPS, kd-line
   variant) from a fixed start, so the same frame always gives the same cloud.
6. pad — with fewer than ``n_points`` points, the rows are filled by repeating the real points
   cyclically (never zeros: a zero row is a point at the base origin, a real place in the workspace).
   ``CloudInfo.n_padded`` says how many rows are repeats.

With no point left after cropping, :class:`EmptyCloudError` (a CameraError) is raised with the
``CloudInfo`` attached: a run-time caller must not feed the policy an invented cloud.

The pipeline is plain numpy (plus fpsample) because that is measured faster here: on the 2-core
robot computer the open3d chain (deprojection, crop, voxel grid, FPS) took 86-129 ms per 640x480
frame, this one about 5 ms (``benchmarks/pointcloud_time.py``); it also keeps the robot's install small.
"""

from __future__ import annotations

import math
import threading
import time
from collections import OrderedDict
from dataclasses import asdict, dataclass, field

import numpy as np

from dssp_core.errors import CameraError
from dssp_data.observation import PointCloudConfig
from dssp_data.pointcloud.depth_frame import DepthFrame, Intrinsics
from dssp_data.pointcloud.extrinsics import validate_extrinsics

STAGES = ("clip", "deproject", "crop", "voxel", "sample", "pad", "color")
_MAX_DENSE_VOXELS = 1 << 23  # above this many grid cells (32 MiB of scratch), voxel dedup sorts keys


@dataclass(frozen=True)
class CloudInfo:
    """What happened to one frame. Counts are points (pixels) left after each stage.

    n_pixels: H * W. n_valid: pixels with a depth inside the clip range. n_in_crop: points inside the
    workspace box. n_after_voxel: after voxel downsampling (= n_in_crop when voxel_size is 0).
    n_points: rows of the output (config.n_points). n_padded: output rows that repeat a point because
    fewer than n_points were left (0 = none). timings_ms: milliseconds per stage (clip, deproject, crop,
    voxel, sample, pad, color) and 'total'.
    """

    n_pixels: int
    n_valid: int
    n_in_crop: int
    n_after_voxel: int
    n_points: int
    n_padded: int
    timings_ms: dict[str, float] = field(default_factory=dict)

    @property
    def padded(self) -> bool:
        return self.n_padded > 0

    def to_dict(self) -> dict:
        return asdict(self)


class EmptyCloudError(CameraError):
    """No point survived the depth clip and the workspace crop; ``.info`` holds the :class:`CloudInfo`."""

    def __init__(self, message: str, info: CloudInfo) -> None:
        super().__init__(message)
        self.info = info


# -- cached geometry ---------------------------------------------------------------------------------------
_ray_cache: OrderedDict[tuple, tuple[np.ndarray, np.ndarray]] = OrderedDict()
_ray_lock = threading.Lock()
_RAY_CACHE_SIZE = 4  # 640x480: 3.7 MB each
_local = threading.local()


def camera_rays(intrinsics: Intrinsics) -> np.ndarray:
    """(3, H*W) float64 camera-frame rays ((u - ppx) / fx, (v - ppy) / fy, 1) in row-major pixel order."""
    w, h = intrinsics.width, intrinsics.height
    u = (np.arange(w, dtype=np.float64) - intrinsics.ppx) / intrinsics.fx
    v = (np.arange(h, dtype=np.float64) - intrinsics.ppy) / intrinsics.fy
    return np.stack(
        [
            np.broadcast_to(u[None, :], (h, w)).reshape(-1),
            np.broadcast_to(v[:, None], (h, w)).reshape(-1),
            np.ones(h * w),
        ]
    )


def _base_rays(intrinsics: Intrinsics, camera_to_base: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """((3, H*W) float32 rays rotated into the base frame, (3,) float32 translation), cached."""
    key = (intrinsics, camera_to_base.tobytes())
    with _ray_lock:
        hit = _ray_cache.get(key)
        if hit is not None:
            _ray_cache.move_to_end(key)
            return hit
    m = validate_extrinsics(camera_to_base)
    rays = np.ascontiguousarray((m[:3, :3] @ camera_rays(intrinsics)).astype(np.float32))
    value = (rays, m[:3, 3].astype(np.float32))
    with _ray_lock:
        _ray_cache[key] = value
        while len(_ray_cache) > _RAY_CACHE_SIZE:
            _ray_cache.popitem(last=False)
    return value


def _owner_buffer(n_cells: int) -> np.ndarray:
    """A reusable (>= n_cells,) int32 scratch array for voxel dedup (per thread; contents are garbage)."""
    buf = getattr(_local, "owner", None)
    if buf is None or buf.size < n_cells:
        buf = np.empty(max(n_cells, 1 << 16), np.int32)
        _local.owner = buf
    return buf


# -- stages ------------------------------------------------------------------------------------------------
def deproject(depth: np.ndarray, depth_unit: float, intrinsics: Intrinsics) -> np.ndarray:
    """Camera-frame points for every pixel: depth (H, W) uint16 raw -> (H, W, 3) float32 metres.

    Pixel (u, v) (column, row) with depth z metres -> (z (u - ppx) / fx, z (v - ppy) / fy, z);
    depth 0 gives (0, 0, 0), as ``rs.pointcloud`` does.
    """
    depth = np.asarray(depth)
    if depth.shape != (intrinsics.height, intrinsics.width):
        raise CameraError(f"depth is {depth.shape}, intrinsics say ({intrinsics.height}, {intrinsics.width})")
    rays = camera_rays(intrinsics).astype(np.float32)
    z = depth.reshape(-1).astype(np.float32) * np.float32(depth_unit)
    return (rays * z).T.reshape(intrinsics.height, intrinsics.width, 3)


def voxel_cells(points: np.ndarray, voxel_size: float) -> np.ndarray:
    """(N, 3) int64 voxel coordinates of points (N, 3) metres: round(p / voxel_size).

    Voxels are centred on multiples of ``voxel_size`` in the points' frame, so a surface at a round
    coordinate (a table top at z = 0 in the base frame) lies inside one layer of voxels, not on a border.
    """
    return np.floor(np.asarray(points, np.float64) / voxel_size + 0.5).astype(np.int64)


def voxel_downsample(points: np.ndarray, voxel_size: float) -> np.ndarray:
    """Indices (M,) int64, ascending, of one point per occupied voxel (:func:`voxel_cells`) of edge
    ``voxel_size`` metres. points: (N, 3) metres. voxel_size 0 keeps every point. Deterministic."""
    pts = np.asarray(points, np.float32)
    if len(pts) == 0 or voxel_size <= 0:
        return np.arange(len(pts))
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    return _voxel_select(np.ascontiguousarray(pts.T), voxel_size, lo, hi)


def _voxel_select(pts: np.ndarray, voxel_size: float, lo, hi) -> np.ndarray:
    """Indices (M,) int64, ascending, one per occupied voxel; pts (3, N) float32 inside the box [lo, hi]."""
    inv = 1.0 / voxel_size
    first = [math.floor(float(a) * inv + 0.5) for a in lo]  # cell index of the box's low corner
    dims = [math.floor(float(b) * inv + 0.5) - f + 1 for f, b in zip(first, hi)]
    n = pts.shape[1]
    cells = []
    for axis in range(3):
        # floor(p / s + 0.5) - first, computed as a truncation of a value that is >= 0 inside the box
        c = pts[axis] * np.float32(inv)
        c += np.float32(0.5 - first[axis])
        c = c.astype(np.int64)
        np.clip(c, 0, dims[axis] - 1, out=c)  # float32 rounding at the box faces
        cells.append(c)
    n_cells = dims[0] * dims[1] * dims[2]
    keys = cells[0] * dims[1]
    keys += cells[1]
    keys *= dims[2]
    keys += cells[2]
    if n_cells <= _MAX_DENSE_VOXELS:
        # Scatter each point's index into its cell; the point whose index stays there owns the cell.
        owner = _owner_buffer(n_cells)
        order = np.arange(n, dtype=np.int32)
        owner[keys] = order
        return np.flatnonzero(owner[keys] == order)
    _, first_idx = np.unique(keys, return_index=True)
    return np.sort(first_idx)


def _fps_height(n: int) -> int:
    """fpsample kd-tree height: buckets of 2**h points; 5 suits up to ~20k points, 7 above (measured)."""
    h = 5 if n < 20000 else 7
    return max(1, min(h, int(math.log2(max(n, 2)))))


def farthest_point_indices(points: np.ndarray, n_samples: int) -> np.ndarray:
    """Indices (n_samples,) int64 of farthest point sampling over points (N, 3), N > n_samples.

    fpsample's bucket FPS (kd-line) from start index 0 (the first point, in pixel order); deterministic.
    """
    import fpsample  # deferred: loads fpsample

    pts = np.ascontiguousarray(points, dtype=np.float32)
    idx = fpsample.bucket_fps_kdline_sampling(pts, n_samples, h=_fps_height(len(pts)), start_idx=0)
    return np.asarray(idx, dtype=np.int64)


# -- the pipeline ------------------------------------------------------------------------------------------
def frame_to_cloud(
    frame: DepthFrame, config: PointCloudConfig, camera_to_base: np.ndarray | None = None
) -> tuple[np.ndarray, CloudInfo]:
    """One :class:`DepthFrame` -> (cloud, info).

    camera_to_base: (4, 4) camera->robot-base transform (``load_extrinsics``); None = identity.
    cloud: (P, 3) float32 metres in the robot-base frame, P = config.n_points, or (P, 6) with RGB in
    [0, 1] as channels 3..5 when config.use_color (the frame must carry colour).
    Raises EmptyCloudError (with ``.info``) when nothing is left after the clip and crop.
    """
    return depth_to_cloud(frame.depth, frame.depth_unit, frame.intrinsics, config, camera_to_base, color=frame.color)


def depth_to_cloud(
    depth: np.ndarray,
    depth_unit: float,
    intrinsics: Intrinsics,
    config: PointCloudConfig,
    camera_to_base: np.ndarray | None = None,
    color: np.ndarray | None = None,
) -> tuple[np.ndarray, CloudInfo]:
    """:func:`frame_to_cloud` on raw arrays: depth (H, W) uint16 raw units (metres = depth * depth_unit),
    color (H, W, 3) uint8 RGB aligned to depth or None. Same outputs."""
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    depth = np.asarray(depth)
    h, w = intrinsics.height, intrinsics.width
    if depth.shape != (h, w) or depth.dtype != np.uint16:
        raise CameraError(f"depth must be ({h}, {w}) uint16 to match the intrinsics, got {depth.dtype} {depth.shape}")
    if config.use_color:
        if color is None:
            raise CameraError("the point cloud config uses colour but the frame has none; open the camera with color")
        color = np.asarray(color)
        if color.shape != (h, w, 3) or color.dtype != np.uint8:
            raise CameraError(f"colour must be ({h}, {w}, 3) uint8 aligned to depth, got {color.dtype} {color.shape}")
    if not (depth_unit > 0 and math.isfinite(depth_unit)):
        raise CameraError(f"depth unit must be a positive number of metres, got {depth_unit!r}")
    m = np.eye(4) if camera_to_base is None else np.asarray(camera_to_base, dtype=np.float64)
    if m.shape != (4, 4):
        raise CameraError(f"camera_to_base must be (4, 4), got {m.shape}")

    # 1. clip, on raw values
    t = time.perf_counter()
    raw = depth.reshape(-1)
    near_raw = max(1, math.ceil(config.depth_near / depth_unit - 1e-6))
    far_raw = min(65535, math.floor(config.depth_far / depth_unit + 1e-6))
    mask = raw >= near_raw
    mask &= raw <= far_raw
    n_valid = int(np.count_nonzero(mask))
    timings["clip"] = _ms(t)

    # 2. deproject + transform, whole image (contiguous arrays beat gathers): base = z * ray_base + t
    t = time.perf_counter()
    rays, trans = _base_rays(intrinsics, m)
    z = raw.astype(np.float32)
    z *= np.float32(depth_unit)
    xyz = rays * z  # (3, H*W)
    xyz += trans[:, None]
    timings["deproject"] = _ms(t)

    # 3. crop
    t = time.perf_counter()
    for axis in range(3):
        mask &= xyz[axis] >= np.float32(config.crop_min[axis])
        mask &= xyz[axis] <= np.float32(config.crop_max[axis])
    pix = np.flatnonzero(mask)
    pts = np.take(xyz, pix, axis=1)  # (3, n); np.take is several times faster than xyz[:, pix]
    n_in_crop = len(pix)
    timings["crop"] = _ms(t)

    if n_in_crop == 0:
        info = CloudInfo(h * w, n_valid, 0, 0, config.n_points, config.n_points, _total(timings, t_start))
        if n_valid == 0:
            msg = (
                f"no valid depth in [{config.depth_near:g}, {config.depth_far:g}] m in the frame; check that "
                f"the camera sees the workspace and the depth clip"
            )
        else:
            msg = (
                f"none of the {n_valid} valid depth points is inside the crop box {list(config.crop_min)}.."
                f"{list(config.crop_max)} m; check camera_to_base (calibration) and the crop box"
            )
        raise EmptyCloudError(msg, info)

    # 4. voxel
    t = time.perf_counter()
    if config.voxel_size > 0:
        sel = _voxel_select(pts, config.voxel_size, config.crop_min, config.crop_max)
        pts, pix = np.take(pts, sel, axis=1), pix[sel]
    n_after_voxel = len(pix)
    pts = np.ascontiguousarray(pts.T)  # (n, 3)
    timings["voxel"] = _ms(t)

    # 5. sample
    t = time.perf_counter()
    if n_after_voxel > config.n_points:
        sel = farthest_point_indices(pts, config.n_points)
        pts, pix = np.take(pts, sel, axis=0), pix[sel]
    timings["sample"] = _ms(t)

    # 6. pad by repeating real points
    t = time.perf_counter()
    n_padded = max(0, config.n_points - len(pix))
    if n_padded:
        rep = np.resize(np.arange(len(pix)), config.n_points)
        pts, pix = np.take(pts, rep, axis=0), pix[rep]
    timings["pad"] = _ms(t)

    t = time.perf_counter()
    if config.use_color:
        rgb = np.take(color.reshape(-1, 3), pix, axis=0).astype(np.float32) * np.float32(1.0 / 255.0)
        cloud = np.concatenate([pts, rgb], axis=1)
    else:
        cloud = np.ascontiguousarray(pts)
    timings["color"] = _ms(t)

    info = CloudInfo(h * w, n_valid, n_in_crop, n_after_voxel, config.n_points, n_padded, _total(timings, t_start))
    return cloud, info


def _ms(t0: float) -> float:
    return (time.perf_counter() - t0) * 1000.0


def _total(timings: dict[str, float], t_start: float) -> dict[str, float]:
    timings = dict(timings)
    timings["total"] = _ms(t_start)
    return timings

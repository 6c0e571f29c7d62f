"""A simulated depth camera over a synthetic tabletop, rendered analytically in numpy by ray casting.

The scene, in the robot-base frame (metres, z up): a table top at z = 0 (a finite rectangle), a floor
below it, a few boxes standing on the table, and optionally one moving box whose pose comes from a
callback (e.g. following the robot's gripper). The camera looks down at the table from the front with
L515-like intrinsics (640x480, 70 deg horizontal field of view) and depth unit 0.00025 m.

    cam = SimCamera(seed=0)                 # capture thread at the profile's fps
    cam = SimCamera(seed=0); cam.start(thread=False); frame = cam.capture()   # deterministic steps

Every frame goes through :class:`~hardware.camera.software.SoftwareDepthCamera`, so the same SDK
conversion code as a live camera produces the :class:`DepthFrame`. Rendering a 640x480 frame takes
well under 1 ms (about 1 ms more through the SDK): per-pixel rays, the static scene and a pool of
noise are precomputed; per frame only the moving box's image rectangle is ray-cast.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from dssp_core.errors import CameraError
from dssp_data.pointcloud.depth_frame import DepthFrame, Intrinsics
from hardware.camera.base import Camera
from hardware.camera.profiles import CameraProfile, load_profile
from hardware.camera.software import SoftwareDepthCamera

# Object ids in the rendered id image (index into the colour palette); boxes follow from FIRST_BOX_ID.
NOTHING, FLOOR, TABLE, FIRST_BOX_ID = 0, 1, 2, 3


@dataclass(frozen=True)
class Box:
    """An upright box: centre (x, y, z) and full edge lengths (sx, sy, sz) in metres (robot-base frame),
    rotated by ``yaw`` radians about the base z axis; ``color`` RGB uint8."""

    center: tuple[float, float, float]
    size: tuple[float, float, float]
    yaw: float = 0.0
    color: tuple[int, int, int] = (200, 60, 50)

    def __post_init__(self) -> None:
        if len(self.center) != 3 or len(self.size) != 3 or min(self.size) <= 0:
            raise CameraError(f"Box needs a 3-vector centre and 3 positive sizes, got {self.center}, {self.size}")

    def corners(self) -> np.ndarray:
        """(8, 3) float64 corner positions in the base frame, metres."""
        half = np.asarray(self.size, float) / 2
        signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        return (signs * half) @ rot.T + np.asarray(self.center, float)


def _default_boxes() -> tuple[Box, ...]:
    return (
        Box(center=(0.40, 0.10, 0.04), size=(0.06, 0.06, 0.08), yaw=0.3, color=(200, 50, 40)),
        Box(center=(0.50, -0.15, 0.02), size=(0.10, 0.05, 0.04), yaw=-0.5, color=(40, 70, 200)),
        Box(center=(0.28, -0.02, 0.02), size=(0.04, 0.04, 0.04), color=(50, 170, 60)),
    )


@dataclass(frozen=True)
class TableScene:
    """Table top z = 0 over [table_min, table_max] (x, y metres), floor at ``floor_z``, static ``boxes``."""

    table_min: tuple[float, float] = (-0.2, -0.6)
    table_max: tuple[float, float] = (1.0, 0.6)
    floor_z: float = -0.75
    table_color: tuple[int, int, int] = (150, 120, 90)
    floor_color: tuple[int, int, int] = (90, 90, 90)
    boxes: tuple[Box, ...] = field(default_factory=_default_boxes)


def look_at(eye: Sequence[float], target: Sequence[float], up: Sequence[float] = (0.0, 0.0, 1.0)) -> np.ndarray:
    """(4, 4) float64 camera->base transform of a camera at ``eye`` looking at ``target`` (base frame, metres),
    with the RealSense optical convention: x right, y down, z forward."""
    eye, target, up = (np.asarray(v, float) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        raise CameraError("look_at: the viewing direction is parallel to 'up'; choose another target or up")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    out = np.eye(4)
    out[:3, :3] = np.stack([x, y, z], axis=1)
    out[:3, 3] = eye
    return out


DEFAULT_CAMERA_TO_BASE = look_at(eye=(0.95, 0.0, 0.55), target=(0.35, 0.0, 0.0))


def intrinsics_for(width: int, height: int, hfov_deg: float = 70.0) -> Intrinsics:
    """Square-pixel pinhole intrinsics with the given horizontal field of view, principal point at the centre."""
    f = (width / 2) / math.tan(math.radians(hfov_deg) / 2)
    return Intrinsics(width=width, height=height, fx=f, fy=f, ppx=(width - 1) / 2, ppy=(height - 1) / 2)


class SceneRenderer:
    """Ray casts a :class:`TableScene` for one camera. Depth is the camera-z distance (what depth cameras
    report), in metres; inf where a ray hits nothing.

    The rays are stored per pixel in the base frame, scaled so that the point at depth z is origin + z * ray.
    """

    def __init__(self, intrinsics: Intrinsics, camera_to_base: np.ndarray, scene: TableScene | None = None) -> None:
        self.intrinsics = intr = intrinsics
        self.camera_to_base = np.asarray(camera_to_base, float)
        self.scene = TableScene() if scene is None else scene
        self._rot = self.camera_to_base[:3, :3]
        self.origin = self.camera_to_base[:3, 3].copy()
        u = (np.arange(intr.width, dtype=np.float64) - intr.ppx) / intr.fx
        v = (np.arange(intr.height, dtype=np.float64) - intr.ppy) / intr.fy
        cam = np.stack(np.broadcast_arrays(u[None, :], v[:, None], np.ones((1, 1))), axis=0)  # (3, H, W)
        self.rays = np.einsum("ij,jhw->ihw", self._rot, cam).astype(np.float32)  # (3, H, W) base frame
        self.palette = np.zeros((FIRST_BOX_ID + len(self.scene.boxes) + 1, 3), np.uint8)
        self.palette[FLOOR] = self.scene.floor_color
        self.palette[TABLE] = self.scene.table_color
        for i, box in enumerate(self.scene.boxes):
            self.palette[FIRST_BOX_ID + i] = box.color
        self.moving_id = FIRST_BOX_ID + len(self.scene.boxes)
        self.static_depth, self.static_ids = self._render_static()

    def _render_static(self) -> tuple[np.ndarray, np.ndarray]:
        sc = self.scene
        o = self.origin
        dx, dy, dz = self.rays
        depth = np.full(dx.shape, np.inf, np.float32)
        ids = np.zeros(dx.shape, np.uint8)
        with np.errstate(divide="ignore", invalid="ignore"):
            for plane_z, obj in ((sc.floor_z, FLOOR), (0.0, TABLE)):
                t = (plane_z - o[2]) / dz
                hit = np.isfinite(t) & (t > 0)
                if obj == TABLE:
                    x, y = o[0] + t * dx, o[1] + t * dy
                    hit &= (x >= sc.table_min[0]) & (x <= sc.table_max[0])
                    hit &= (y >= sc.table_min[1]) & (y <= sc.table_max[1])
                closer = hit & (t < depth)
                depth[closer] = t[closer]
                ids[closer] = obj
        for i, box in enumerate(sc.boxes):
            self._cast_box(box, FIRST_BOX_ID + i, depth, ids)
        return depth, ids

    def _box_rect(self, box: Box) -> tuple[slice, slice] | None:
        """Image rows/columns that can see ``box`` (its projected corners' bounding rectangle), or None."""
        intr = self.intrinsics
        pc = (box.corners() - self.origin) @ self._rot  # (8, 3) camera frame
        if np.all(pc[:, 2] <= 0):
            return None
        if np.any(pc[:, 2] <= 1e-3):
            return slice(0, intr.height), slice(0, intr.width)
        u = intr.fx * pc[:, 0] / pc[:, 2] + intr.ppx
        v = intr.fy * pc[:, 1] / pc[:, 2] + intr.ppy
        u0, u1 = max(int(np.floor(u.min())) - 1, 0), min(int(np.ceil(u.max())) + 2, intr.width)
        v0, v1 = max(int(np.floor(v.min())) - 1, 0), min(int(np.ceil(v.max())) + 2, intr.height)
        if u0 >= u1 or v0 >= v1:
            return None
        return slice(v0, v1), slice(u0, u1)

    def _cast_box(self, box: Box, obj: int, depth: np.ndarray, ids: np.ndarray) -> tuple[slice, slice] | None:
        """Slab test of every ray in the box's image rectangle; writes nearer hits into depth/ids in place.
        Returns the rectangle (rows, columns) it tested, or None when the box is out of view."""
        rect = self._box_rect(box)
        if rect is None:
            return None
        c, s = math.cos(box.yaw), math.sin(box.yaw)
        to_box = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])  # base -> box axes
        o = to_box @ (self.origin - np.asarray(box.center, float))
        rays = self.rays[:, rect[0], rect[1]]
        d = np.einsum("ij,jhw->ihw", to_box.astype(np.float32), rays)
        half = np.asarray(box.size, float) / 2
        near = np.full(d.shape[1:], -np.inf, np.float32)
        far = np.full(d.shape[1:], np.inf, np.float32)
        with np.errstate(divide="ignore", invalid="ignore"):
            for axis in range(3):
                inv = 1.0 / d[axis]
                t1 = (-half[axis] - o[axis]) * inv
                t2 = (half[axis] - o[axis]) * inv
                near = np.maximum(near, np.minimum(t1, t2))
                far = np.minimum(far, np.maximum(t1, t2))
        hit = (near <= far) & (near > 0)
        sub_depth, sub_ids = depth[rect], ids[rect]
        closer = hit & (near < sub_depth)
        sub_depth[closer] = near[closer]
        sub_ids[closer] = obj
        return rect

    def render(self, moving: Box | None = None) -> tuple[np.ndarray, np.ndarray, tuple[slice, slice] | None]:
        """The scene with the optional moving box: depth (H, W) float32 metres (inf = no hit), ids (H, W)
        uint8 object ids (``moving_id`` for the moving box), and the image rectangle the moving box was
        cast in (None if none). The static arrays are returned as they are when there is no moving box:
        do not modify them."""
        if moving is None:
            return self.static_depth, self.static_ids, None
        depth, ids = self.static_depth.copy(), self.static_ids.copy()
        rect = self._cast_box(moving, self.moving_id, depth, ids)
        return depth, ids, rect


class SimCamera(Camera):
    """A simulated depth camera (a :class:`Camera`) over a :class:`TableScene`.

    profile: stream size, fps and depth unit ('l515' by default: 640x480 @ 30, 0.00025 m).
    seed: noise and invalid pixels are drawn from ``np.random.default_rng(seed)``: the same seed gives the
    same frames. noise_std: Gaussian depth noise, metres. invalid_fraction: share of pixels set to 0 per frame.
    moving_box: ``callback(t) -> Box | None`` called per frame with the sim time t = frame_number / fps
    seconds (None hides the box). camera_to_base: (4, 4) pose of the camera in the base frame
    (default :data:`DEFAULT_CAMERA_TO_BASE`, looking at the table from the front). color: also deliver
    RGB colour (flat object colours, aligned to depth). max_range: metres; farther surfaces read 0.

    ``start()`` runs a capture thread at ``fps``; ``start(thread=False)`` + ``capture()`` steps by hand.
    """

    def __init__(
        self,
        profile: str | CameraProfile = "l515",
        *,
        seed: int = 0,
        fps: int | None = None,
        color: bool = False,
        noise_std: float = 0.001,
        invalid_fraction: float = 0.002,
        scene: TableScene | None = None,
        moving_box: Callable[[float], Box | None] | None = None,
        camera_to_base: np.ndarray | None = None,
        intrinsics: Intrinsics | None = None,
        hfov_deg: float = 70.0,
        max_range: float = 9.0,
    ) -> None:
        self.profile = profile if isinstance(profile, CameraProfile) else load_profile(profile)
        self.fps = int(fps or self.profile.fps)
        if self.fps <= 0:
            raise CameraError(f"sim camera: fps must be positive, got {fps}")
        if not 0 <= noise_std < 0.1:
            raise CameraError(f"sim camera: noise_std is metres in [0, 0.1), got {noise_std}")
        if not 0 <= invalid_fraction < 1:
            raise CameraError(f"sim camera: invalid_fraction must be in [0, 1), got {invalid_fraction}")
        self.name = f"sim:{self.profile.name}"
        self.seed = int(seed)
        self.color = bool(color)
        self.noise_std = float(noise_std)
        self.invalid_fraction = float(invalid_fraction)
        self.moving_box = moving_box
        self.max_range = float(max_range)
        self.depth_unit = float(self.profile.depth_unit)
        self.intrinsics = intrinsics or intrinsics_for(self.profile.width, self.profile.height, hfov_deg)
        pose = DEFAULT_CAMERA_TO_BASE if camera_to_base is None else np.asarray(camera_to_base, float)
        if pose.shape != (4, 4):
            raise CameraError(f"sim camera: camera_to_base must be (4, 4), got {pose.shape}")
        self.renderer = SceneRenderer(self.intrinsics, pose, scene)
        self._n_pixels = self.intrinsics.width * self.intrinsics.height
        self._software = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._error: str | None = None
        self._static_color: np.ndarray | None = None
        self._reset_rng()

    @property
    def camera_to_base(self) -> np.ndarray:
        """(4, 4) float64 camera->base transform the scene is rendered with (what a calibration would give)."""
        return self.renderer.camera_to_base.copy()

    def _reset_rng(self) -> None:
        self._rng = np.random.default_rng(self.seed)
        # A pool of Gaussian noise twice the image size; each frame reads it from a random offset.
        self._noise = self._rng.standard_normal(2 * self._n_pixels, dtype=np.float32) * np.float32(
            self.noise_std / self.depth_unit
        )
        self._frame_number = 0

    # -- rendering -----------------------------------------------------------------------------------------
    def render(self, t: float = 0.0) -> tuple[np.ndarray, np.ndarray | None]:
        """The next frame's images at sim time ``t`` seconds, drawing noise from the camera's generator:
        (depth (H, W) uint16 raw units, 0 = invalid; colour (H, W, 3) uint8 RGB or None)."""
        moving = None
        if self.moving_box is not None:
            try:
                moving = self.moving_box(t)
            except Exception as e:  # a failing callback must not kill the capture silently
                raise CameraError(f"{self.name}: moving_box callback failed ({type(e).__name__}: {e})") from None
        depth_m, ids, rect = self.renderer.render(moving)
        h, w = depth_m.shape
        scaled = depth_m * np.float32(1.0 / self.depth_unit)
        if self.noise_std > 0:
            offset = int(self._rng.integers(0, self._n_pixels))
            scaled += self._noise[offset : offset + self._n_pixels].reshape(h, w)
        limit = min(self.max_range / self.depth_unit, 65535.0)
        bad = ~(scaled <= limit)  # also catches inf / nan
        np.rint(scaled, out=scaled)
        scaled[bad] = 0
        np.maximum(scaled, 0, out=scaled)
        depth = scaled.astype(np.uint16)
        k = int(round(self.invalid_fraction * self._n_pixels))
        if k:
            depth.reshape(-1)[self._rng.integers(0, self._n_pixels, k)] = 0
        color = None
        if self.color:
            if self._static_color is None:
                self._static_color = self.renderer.palette[self.renderer.static_ids]
            color = self._static_color.copy()
            if rect is not None:
                sub = color[rect]
                sub[ids[rect] == self.renderer.moving_id] = moving.color
        return depth, color

    # -- Camera API ----------------------------------------------------------------------------------------
    def start(self, thread: bool = True) -> None:
        """Start the software sensor and, with ``thread=True``, a capture thread at ``fps``."""
        if self._software is not None:
            return

        self._software = SoftwareDepthCamera(self.intrinsics, self.depth_unit, fps=self.fps, color=self.color)
        self._software.start()
        self._error = None
        if thread:
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, name=f"camera-{self.name}", daemon=True)
            self._thread.start()

    def capture(self) -> DepthFrame:
        """Render, inject and convert the next frame (stepped mode); returns it (also ``latest()``)."""
        if self._thread is not None:
            raise CameraError(f"{self.name}: capture() is for stepped mode; start(thread=False) first")
        return self._capture()

    def _capture(self) -> DepthFrame:
        if self._software is None:
            raise CameraError(f"{self.name}: not started; call start() or use it as a context manager")
        number = self._frame_number
        depth, color = self.render(number / self.fps)
        frame = self._software.push(depth, color, frame_number=number)
        self._frame_number = number + 1
        return frame

    def _run(self) -> None:
        period = 1.0 / self.fps
        next_time = time.monotonic()
        try:
            while not self._stop.is_set():
                self._capture()
                next_time += period
                delay = next_time - time.monotonic()
                if delay < -period:  # running late: do not try to catch up with a burst
                    next_time = time.monotonic()
                elif delay > 0:
                    self._stop.wait(delay)
        except CameraError as e:
            self._error = str(e)

    def latest(self) -> DepthFrame | None:
        if self._error is not None:
            raise CameraError(self._error)
        return None if self._software is None else self._software.latest()

    def stop(self) -> None:
        thread, self._thread = self._thread, None
        if thread is not None:
            self._stop.set()
            thread.join(timeout=2.0)
        software, self._software = self._software, None
        if software is not None:
            software.stop()

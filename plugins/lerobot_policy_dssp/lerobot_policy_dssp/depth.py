"""Training on a LeRobot dataset's depth: each frame's cloud by the robot's pipeline.

A dataset without ``observation.pointcloud`` but with a depth feature (``--policy.depth_key``, uint16 counts or
float32 metres, (H, W), with ``info.camera_intrinsics = {fx, fy, ppx, ppy, width, height, depth_unit}``: the
convention of :mod:`dssp_data.lerobot.layout`) is trained on the clouds that
:func:`dssp_data.pointcloud.frame_to_cloud` makes of its frames, in the robot's base frame (``--policy.extrinsics``,
the file dssp-calibrate writes), with the point-cloud settings of ``--policy.pointcloud`` (else the preset's, else
the robot's defaults with the model's ``n_points``). :func:`resolve_depth_camera` checks the dataset and the files
and returns what the processor step (:class:`lerobot_policy_dssp.processor_dssp.DepthToCloudStep`) records;
:func:`depth_clouds` is what the step runs. float32 metres are first quantised to ``depth_unit`` (1 mm when not
given), as ``dssp-data convert`` does.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dssp_core.errors import DSSPError
from dssp_data.lerobot.read import depth_feature, quantised
from dssp_data.observation import FRAME_ROBOT_BASE, PointCloudConfig
from dssp_data.pointcloud import EmptyCloudError, frame_to_cloud, load_extrinsics
from dssp_data.pointcloud.depth_frame import DepthFrame, Intrinsics


def resolve_depth_camera(config, dataset_meta) -> dict:
    """What the depth-to-cloud step needs, from the dataset's depth feature, ``--policy.extrinsics`` and the
    point-cloud settings: ``{key, dtype, intrinsics, depth_unit, camera_to_base, pointcloud, frame}``. A dataset
    or a file that does not fit is refused with a one-line ValueError."""
    key = config.depth_key
    feature = dataset_meta.features[key]
    info = feature.get("info")
    if not (isinstance(info, dict) and isinstance(info.get("camera_intrinsics"), dict)):
        raise ValueError(
            f"the dataset's depth feature {key} has no info.camera_intrinsics {{fx, fy, ppx, ppy, width, "
            "height, depth_unit}: add the camera's intrinsics to its entry in meta/info.json (as "
            "dssp_data/README.md describes) to train on its depth"
        )
    try:
        depth = depth_feature(dataset_meta.features, key, Path(dataset_meta.root))
    except DSSPError as exc:
        raise ValueError(str(exc)) from None
    if config.extrinsics is None:
        raise ValueError(
            f"training on the depth feature {key} needs the camera's pose: give --policy.extrinsics="
            "calib.json (the file dssp-calibrate writes); the clouds are made in the robot's base frame"
        )
    try:
        camera_to_base = load_extrinsics(config.extrinsics)
        if config.pointcloud is not None:
            cloud = PointCloudConfig.load(config.pointcloud, "point-cloud settings")
        else:
            run = config.run()
            cloud = run.observation.pointcloud or PointCloudConfig(n_points=run.model.n_points)
    except DSSPError as exc:
        raise ValueError(str(exc)) from None
    if cloud.use_color:
        raise ValueError(
            f"the point-cloud settings ask for colour (use_color) but {key} is depth alone: set use_color false"
        )
    return {
        "key": key,
        "dtype": depth.dtype,
        "intrinsics": depth.intrinsics.to_dict(),
        "depth_unit": depth.depth_unit,
        "camera_to_base": camera_to_base.tolist(),
        "pointcloud": cloud.to_dict(),
        "frame": FRAME_ROBOT_BASE,
    }


def cloud_range(depth_camera: dict) -> np.ndarray:
    """(2, 3) the crop box of the point-cloud settings: every cloud lies inside it, so the model's cloud
    normaliser is fitted on it (the dataset's statistics hold no clouds)."""
    cloud = PointCloudConfig.from_dict(depth_camera["pointcloud"])
    return np.array([cloud.crop_min, cloud.crop_max], dtype=np.float64)


class DepthClouds:
    """The robot's pipeline on a depth feature's frames (what the processor step runs)."""

    def __init__(self, depth_camera: dict) -> None:
        self.key = depth_camera["key"]
        self.dtype = depth_camera["dtype"]
        self.depth_unit = float(depth_camera["depth_unit"])
        self.intrinsics = Intrinsics(**depth_camera["intrinsics"])
        self.config = PointCloudConfig.from_dict(depth_camera["pointcloud"])
        self.camera_to_base = np.asarray(depth_camera["camera_to_base"], dtype=np.float64)

    def counts(self, depth: np.ndarray) -> np.ndarray:
        """(..., H, W) depth as LeRobot hands it (int64 counts or float32 metres) -> uint16 counts."""
        h, w = self.intrinsics.height, self.intrinsics.width
        if depth.ndim >= 3 and depth.shape[-3:] == (h, w, 1):
            depth = depth[..., 0]
        if depth.shape[-2:] != (h, w):
            raise ValueError(f"{self.key} frames are {depth.shape[-2:]}; its camera_intrinsics say ({h}, {w})")
        if self.dtype == "uint16":
            return depth.astype(np.uint16)
        return quantised(depth, self.depth_unit)

    def cloud(self, counts: np.ndarray, where: str) -> np.ndarray:
        """One (H, W) uint16 frame -> its (P, 3) float32 cloud; ``where`` names the frame in a refusal."""
        frame = DepthFrame(
            depth=counts, depth_unit=self.depth_unit, intrinsics=self.intrinsics, timestamp=0.0, frame_number=0
        )
        try:
            return frame_to_cloud(frame, self.config, self.camera_to_base)[0]
        except EmptyCloudError as exc:
            raise ValueError(f"{where} has no point in the crop box of the point-cloud settings ({exc})") from None

    def __call__(self, depth: np.ndarray, pad: np.ndarray | None, current: int, index=None, episode=None) -> np.ndarray:
        """Depth (H, W), (B, H, W) or (B, T, H, W) -> clouds (..., P, 3) float32. ``pad`` (B, T): frames outside
        the episode (LeRobot repeats its first or last frame there): they get the cloud of the frame they repeat.
        ``current``: the sample's own frame in T; ``index``, ``episode`` (B,): its dataset index and episode, to
        name a frame with no point in the crop."""
        counts = self.counts(np.asarray(depth))
        lead = counts.shape[:-2]
        if len(lead) > 2:
            raise ValueError(f"{self.key} has shape {counts.shape}; expected (H, W), (B, H, W) or (B, T, H, W)")
        rows = counts.reshape(*((1, 1), (*lead, 1), lead)[len(lead)], *counts.shape[-2:])
        b, t = rows.shape[:2]
        outside = np.zeros((b, t), bool) if pad is None else np.asarray(pad, bool).reshape(b, t)
        out = np.empty((b, t, self.config.n_points, 3), np.float32)
        for i in range(b):
            inside = np.flatnonzero(~outside[i])
            first, last = (int(inside[0]), int(inside[-1])) if inside.size else (0, t - 1)
            for j in range(first, last + 1):
                if index is None:
                    where = f"the depth frame {self.key}" + (f" {j}" if t > 1 else "")
                else:
                    where = f"the depth frame {self.key} at dataset index {int(index[i]) + j - current}" + (
                        f" (episode {int(episode[i])})" if episode is not None else ""
                    )
                out[i, j] = self.cloud(rows[i, j], where)
            out[i, :first] = out[i, first]
            out[i, last + 1 :] = out[i, last]
        return out.reshape(*lead, self.config.n_points, 3)

"""Depth frames to fixed-size point clouds: one pipeline for dataset building and for the robot.

    from dssp_data.pointcloud import PointCloudConfig, frame_to_cloud, load_extrinsics
    cloud, info = frame_to_cloud(frame, PointCloudConfig(), load_extrinsics("calib.json"))
    # cloud (1024, 3) float32 metres, robot-base frame

numpy only; imports without pyrealsense2.
"""

from dssp_data.observation import PointCloudConfig
from dssp_data.pointcloud.extrinsics import identity, load_extrinsics, save_extrinsics, validate_extrinsics
from dssp_data.pointcloud.pipeline import (
    CloudInfo,
    EmptyCloudError,
    deproject,
    depth_to_cloud,
    farthest_point_indices,
    frame_to_cloud,
    voxel_downsample,
)

__all__ = [
    "CloudInfo",
    "EmptyCloudError",
    "PointCloudConfig",
    "deproject",
    "depth_to_cloud",
    "farthest_point_indices",
    "frame_to_cloud",
    "identity",
    "load_extrinsics",
    "save_extrinsics",
    "validate_extrinsics",
    "voxel_downsample",
]

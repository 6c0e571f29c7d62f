"""What the simulation's datasets and evaluations share: the point-cloud settings and dataset attributes.

The workspace crop is the tabletop in front of the arm up to 10 cm (robot-base frame, metres): every
object of the tasks, and the gripper when it works there; the arm above it is left out, as DP3 crops its
clouds to the workspace — the joints are in the proprioception already. With the arm in the cloud (a
crop up to 40 cm: 200 of 256 points on the arm) the policy learnt to continue its own motion instead of
locating the button: its first chunk ignored where the button was, and it pressed beside buttons near
the edge of their range (tap: 85 % and 65 % for two training seeds, against 90 % with this crop; see the
README). The point count comes from the model (or the preset) that will read the clouds.
"""

from __future__ import annotations

from dssp_data.observation import ObservationContract, PointCloudConfig, piper_layout

SIM_N_POINTS = 256
# Table area in front of the arm, a little above the table top (z = 0) to drop the table itself, and up
# to 10 cm: the tallest object (the swap cylinder) is 6 cm, the put2 bins' walls 7.5 cm.
SIM_CROP_MIN = (0.05, -0.35, 0.005)
SIM_CROP_MAX = (0.60, 0.35, 0.10)


SIM_RENDER_SIZE = (120, 160)  # (H, W) pixels of the depth render
SIM_VOXEL = 0.01  # m
# Where a task needs a finer cloud: swap's objects are small (a 4 cm cube, a 3.6 cm cylinder on 6 cm slots).
# At 160 x 120 pixels and 1 cm voxels its whole workspace gave about 70 points (the other 186 of 256 padding),
# and DSSP carried the cube to the slot the cylinder stood on in 6 of 20 episodes; at 320 x 240 and 5 mm,
# 270-360 points (the 256 are sampled from them).
TASK_OBSERVATION = {"swap": {"render_size": (240, 320), "voxel_size": 0.005}}


def render_size_for(task: str | None = None) -> tuple[int, int]:
    """(H, W) of the depth render for ``task`` (the simulation's default for the others)."""
    return TASK_OBSERVATION.get(task, {}).get("render_size", SIM_RENDER_SIZE)


def cloud_config_for(n_points: int | None = None, task: str | None = None) -> PointCloudConfig:
    """The simulation's point-cloud settings for ``task`` with ``n_points`` points (default :data:`SIM_N_POINTS`)."""
    return PointCloudConfig(
        n_points=n_points or SIM_N_POINTS,
        depth_near=0.1,
        depth_far=2.0,
        crop_min=SIM_CROP_MIN,
        crop_max=SIM_CROP_MAX,
        voxel_size=TASK_OBSERVATION.get(task, {}).get("voxel_size", SIM_VOXEL),
    )


def sim_attrs(task: str, env, camera, cloud_config: PointCloudConfig) -> dict:
    """Dataset attributes: enough to rebuild the clouds and to know what ``action`` means."""
    return {
        "control_rate_hz": float(env.control_rate_hz),
        "task": task,
        "generator": "dssp_sim.collect",
        "action_convention": "target: the joint/gripper target commanded at this tick (policy units)",
        "state_convention": "measured [J1..J6 rad, gripper opening 0..1]",
        **ObservationContract(pointcloud=cloud_config, state=piper_layout(1), action=piper_layout(1)).attrs(),
        "camera_intrinsics": camera.intrinsics.to_dict(),
        "camera_depth_unit": float(camera.depth_unit),
        "camera_to_base": camera.camera_to_base.tolist(),
    }

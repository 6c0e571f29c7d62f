"""``dssp-data convert`` of ROS 2 bags written by the ``rosbags`` library's own writer, as piper_ros users record
them: ``/joint_states`` (joint1..joint7, the gripper in metres), a RealSense-style 16UC1 depth topic and its
CameraInfo. The streams run at their own rates and phases; the converted steps are checked against the point-cloud
pipeline run directly on the frame each tick should take, and every refusal is one line with nothing written."""

from __future__ import annotations

import os

import numpy as np
import pytest
from conftest import CAMERA, CLOUD, calibration_flags, one_error_line
from ros_bags import T0, depth_image, joints, write_bag

from dssp_data.data_cli import main as data_main
from dssp_data.pointcloud import frame_to_cloud
from dssp_data.pointcloud.depth_frame import DepthFrame
from dssp_data.replay_buffer import ReplayBuffer


@pytest.fixture()
def calibration(tmp_path):
    """The bags' calibration flags (:func:`conftest.calibration_flags`) and their depth unit."""
    return [*calibration_flags(tmp_path), "--depth-unit", "0.00025"]


def convert(capsys, source, out, *extra):
    code = data_main(["convert", str(source), "--out", str(out), *extra])
    return code, *capsys.readouterr()


def test_a_bag_becomes_an_episode_aligned_to_the_control_rate(tmp_path, capsys, calibration):
    bag = write_bag(tmp_path / "demo_0")
    out = tmp_path / "demo.zarr"
    code, stdout, stderr = convert(capsys, bag, out, *calibration, "--control-rate", "10")
    assert code == 0, stderr
    assert "1 episodes (one per bag)" in stdout and "action = the state at the next tick" in stdout
    buffer = ReplayBuffer.load(out, extras=True)
    ep = buffer.episode(0)
    # ticks at 10 Hz from the latest first message (the depth's, 4 ms in) to the earliest last one: 15, the last
    # dropped by the next-state convention
    start = T0 + 0.004
    ticks = start + 0.1 * np.arange(15)
    assert ep.n_steps == 14
    np.testing.assert_allclose(ep.extras["timestamp"], ticks[:14] - start, atol=1e-6)
    for k in range(14):
        t = ticks[k]
        joint_time = np.floor((t - T0) * 100 + 1e-6) / 100 + T0  # the newest joint message at or before the tick
        expected = joints(joint_time)
        expected[6] /= 0.07
        np.testing.assert_allclose(ep.state[k], expected, atol=1e-5)
        depth_time = T0 + 0.004 + np.floor((t - T0 - 0.004) * 30 + 1e-3) / 30  # (float seconds near 1.7e9 s)
        frame = DepthFrame(depth_image(depth_time), 0.00025, CAMERA.intrinsics, depth_time, 0)
        cloud, _ = frame_to_cloud(frame, CLOUD, CAMERA.camera_to_base)
        np.testing.assert_array_equal(ep.point_cloud[k], cloud)  # the robot's pipeline, bit for bit
        np.testing.assert_allclose(ep.extras["camera_timestamp"][k], depth_time - start, atol=1e-6)
    np.testing.assert_allclose(ep.action[:-1], ep.state[1:], atol=1e-6)  # next-state convention
    attrs = buffer.attrs
    assert attrs["control_rate_hz"] == 10.0 and attrs["action_convention"].startswith("next_state")
    assert attrs["camera_intrinsics"]["width"] == 160 and attrs["rosbag2_topics"]["state"] == "/joint_states"
    assert attrs["pointcloud"]["n_points"] == 128 and np.allclose(attrs["camera_to_base"], CAMERA.camera_to_base)


def test_the_leader_topic_gives_the_action_and_a_folder_of_bags_gives_episodes(tmp_path, capsys, calibration):
    bags = tmp_path / "bags"
    bags.mkdir()
    write_bag(bags / "ep_a", seconds=1.0, leader=True)
    write_bag(bags / "ep_b", seconds=1.2, leader=True)
    out = tmp_path / "lead.zarr"
    code, stdout, stderr = convert(capsys, bags, out, *calibration, "--action-topic", "/leader/joint_states")
    assert code == 0, stderr
    buffer = ReplayBuffer.load(out, extras=True)
    assert buffer.n_episodes == 2 and buffer.attrs["converted_from"] == ["ep_a", "ep_b"]
    assert buffer.attrs["action_convention"].startswith("leader_command")
    ep = buffer.episode(1)
    assert ep.n_steps == 12  # no step lost: the leader's command is the action of its own tick
    for k in range(ep.n_steps):
        t = T0 + 0.004 + 0.1 * k
        lead = joints(np.floor((t - T0) * 100 + 1e-6) / 100 + T0 + 0.1)
        lead[6] /= 0.07
        np.testing.assert_allclose(ep.action[k], lead, atol=1e-5)


def test_what_cannot_be_converted_faithfully_is_one_line(tmp_path, capsys, calibration):
    cases = {
        "no camera_info": (dict(info=False), "no topic /camera/camera/depth/camera_info"),
        "unsynchronised": (dict(depth_gap=(0.5, 0.9)), "not synchronised: /camera/camera/depth/image_rect_raw"),
        "float depth": (dict(encoding="32FC1"), "depth must be 16UC1"),
        "distortion": (dict(distortion=(0.1, 0.0, 0.0, 0.0, 0.0)), "lens distortion"),
    }
    for name, (kwargs, message) in cases.items():
        bag = write_bag(tmp_path / name.replace(" ", "_"), seconds=1.2, **kwargs)
        out = tmp_path / f"{bag.name}.zarr"
        code, _, stderr = convert(capsys, bag, out, *calibration)
        assert code == 2, (name, stderr)
        line = one_error_line(stderr)
        assert message in line, (name, line)
        assert not out.exists(), name
    # the tolerance is printed, and raising it lets the same bag through (the gap is 0.4 s)
    code, _, stderr = convert(capsys, tmp_path / "unsynchronised", tmp_path / "u.zarr", *calibration)
    assert "tolerance 0.05 s" in one_error_line(stderr)
    code, _, stderr = convert(
        capsys, tmp_path / "unsynchronised", tmp_path / "u.zarr", *calibration, "--tolerance", "0.5"
    )
    assert code == 0, stderr
    # a wrong joint name, a missing calibration
    code, _, stderr = convert(
        capsys, tmp_path / "unsynchronised", tmp_path / "j.zarr", *calibration, "--joints", "a,b,c,d,e,f,g"
    )
    assert code == 2 and "has no joint a, b, c" in one_error_line(stderr)
    code, _, stderr = convert(capsys, tmp_path / "unsynchronised", tmp_path / "c.zarr")
    assert code == 2 and "--extrinsics is needed" in one_error_line(stderr)


def test_a_bag_whose_storage_is_a_link_out_of_its_folder_is_refused(tmp_path, capsys, calibration):
    bag = write_bag(tmp_path / "inner", seconds=0.5)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    [storage] = [p for p in bag.iterdir() if p.name != "metadata.yaml"]
    moved = elsewhere / storage.name
    storage.rename(moved)
    os.symlink(moved, storage)
    code, _, stderr = convert(capsys, bag, tmp_path / "x.zarr", *calibration)
    assert code == 2 and "is a link or lies outside the bag folder" in one_error_line(stderr)
    assert not (tmp_path / "x.zarr").exists()

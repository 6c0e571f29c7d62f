"""The point-cloud pipeline: deprojection against pyrealsense2's rs.pointcloud, extrinsics, crop, voxel grid,
farthest point sampling, padding, colour, and the validation of calibration files and configs."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest
from conftest import DEPTH_UNIT, one_line_message
from hypothesis import given, settings
from hypothesis import strategies as st

from dssp_core.errors import CalibrationError, CameraError, ConfigError
from dssp_data.pointcloud import (
    EmptyCloudError,
    PointCloudConfig,
    deproject,
    farthest_point_indices,
    frame_to_cloud,
    load_extrinsics,
    save_extrinsics,
    validate_extrinsics,
    voxel_downsample,
)
from dssp_data.pointcloud.depth_frame import DepthFrame, Intrinsics
from dssp_data.pointcloud.pipeline import voxel_cells

SMALL = Intrinsics(width=96, height=64, fx=83.3, fy=79.1, ppx=45.2, ppy=30.7)
EVERYWHERE = dict(
    crop_min=(-50.0, -50.0, -50.0), crop_max=(50.0, 50.0, 50.0), voxel_size=0.0, depth_near=0.0, depth_far=20.0
)


def _depth(shape=(64, 96), seed=0, invalid=0.1, hi=9000) -> np.ndarray:
    rng = np.random.default_rng(seed)
    d = rng.integers(1, hi, shape, dtype=np.uint16)
    d[rng.random(shape) < invalid] = 0
    return d


def _frame(depth, intr=SMALL, unit=DEPTH_UNIT, color=None) -> DepthFrame:
    return DepthFrame(depth=depth, depth_unit=unit, intrinsics=intr, timestamp=0.0, frame_number=0, color=color)


def _rot_z(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def _transform(rot, t) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = rot, t
    return m


def _one_line(exc_info) -> str:
    """The raised error's :func:`conftest.one_line_message`, which says more than a word."""
    msg = one_line_message(exc_info)
    assert len(msg) > 15
    return msg


# -- deprojection vs the SDK ---------------------------------------------------------------------------------
def test_deprojection_matches_rs_pointcloud():
    import pyrealsense2 as rs

    from hardware.camera.software import SoftwareDepthCamera

    depth = _depth()
    with SoftwareDepthCamera(SMALL, DEPTH_UNIT) as cam:
        depth_frame, _ = cam.inject(depth)
        vertices = np.asanyarray(rs.pointcloud().calculate(depth_frame).get_vertices())
        vertices = vertices.view(np.float32).reshape(-1, 3).copy()
        frame = cam.push(depth)  # the same pixels through the DepthFrame conversion
    mine = deproject(frame.depth, frame.depth_unit, frame.intrinsics).reshape(-1, 3)
    np.testing.assert_allclose(mine, vertices, rtol=0, atol=2e-6)
    # the pipeline's cloud (identity extrinsics, no crop/voxel, P = number of valid pixels) is exactly the
    # SDK's vertices of the valid pixels, in pixel order
    valid = depth.reshape(-1) > 0
    cfg = PointCloudConfig(n_points=int(valid.sum()), **EVERYWHERE)
    cloud, info = frame_to_cloud(frame, cfg, np.eye(4))
    assert info.n_valid == info.n_in_crop == info.n_after_voxel == valid.sum() and info.n_padded == 0
    np.testing.assert_allclose(cloud, vertices[valid], rtol=0, atol=2e-6)


# -- extrinsics in the pipeline ------------------------------------------------------------------------------
@settings(max_examples=15, deadline=None)
@given(angles=st.tuples(*[st.floats(-180, 180)] * 3), t=st.tuples(*[st.floats(-2, 2)] * 3))
def test_extrinsic_applied(angles, t):
    a, b, c = (math.radians(x) for x in angles)
    rx = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    ry = np.array([[math.cos(b), 0, math.sin(b)], [0, 1, 0], [-math.sin(b), 0, math.cos(b)]])
    rot = rx @ ry @ _rot_z(math.degrees(c))
    m = _transform(rot, t)
    depth = _depth(seed=1)
    cfg = PointCloudConfig(n_points=int((depth > 0).sum()), **EVERYWHERE)
    cam_cloud, _ = frame_to_cloud(_frame(depth), cfg, None)
    base_cloud, _ = frame_to_cloud(_frame(depth), cfg, m)
    np.testing.assert_allclose(base_cloud, cam_cloud.astype(np.float64) @ rot.T + np.asarray(t), atol=2e-5)


def test_known_transform_and_identity_default():
    depth = np.full((64, 96), 4000, np.uint16)  # a wall 1 m in front of the camera
    cfg = PointCloudConfig(n_points=64 * 96, **EVERYWHERE)
    cloud, _ = frame_to_cloud(_frame(depth), cfg)  # identity: camera frame
    assert np.allclose(cloud[:, 2], 1.0)
    # camera 0.5 m above the base looking straight down: camera z -> base -z, camera x -> base x
    down = _transform(np.diag([1.0, -1.0, -1.0]), (0.0, 0.0, 0.5))
    cloud, _ = frame_to_cloud(_frame(depth), cfg, down)
    assert np.allclose(cloud[:, 2], -0.5, atol=1e-6)
    centre = np.argmin(np.abs(cloud[:, 0]) + np.abs(cloud[:, 1]))
    assert abs(cloud[centre, 0]) < 0.01 and abs(cloud[centre, 1]) < 0.01


# -- crop, voxel, sampling, padding -------------------------------------------------------------------------
def test_crop_box():
    intr = Intrinsics(width=80, height=60, fx=100.0, fy=100.0, ppx=39.5, ppy=29.5)
    depth = np.full((60, 80), 4000, np.uint16)  # z = 1 m; x = (u - 39.5) / 100: no point on x = +-0.1
    cfg = PointCloudConfig(n_points=2000, crop_min=(-0.1, -1.0, 0.5), crop_max=(0.1, 1.0, 1.5), voxel_size=0.0)
    cloud, info = frame_to_cloud(_frame(depth, intr), cfg)
    assert info.n_valid == 80 * 60
    assert info.n_in_crop == 20 * 60  # columns 30..49
    assert info.n_padded == 2000 - 1200
    assert np.all(np.abs(cloud[:, 0]) < 0.1)
    assert len(np.unique(np.round(cloud[:, 0], 4))) == 20


def test_depth_clip():
    depth = np.zeros((64, 96), np.uint16)
    depth[:, :32] = 800  # 0.2 m
    depth[:, 32:64] = 4000  # 1.0 m
    depth[:, 64:] = 12000  # 3.0 m
    cfg = PointCloudConfig(
        n_points=100,
        depth_near=0.5,
        depth_far=2.0,
        **{k: v for k, v in EVERYWHERE.items() if not k.startswith("depth")},
    )
    cloud, info = frame_to_cloud(_frame(depth), cfg)
    assert info.n_valid == 64 * 32
    assert np.allclose(cloud[:, 2], 1.0)


def test_voxel_size_respected():
    rng = np.random.default_rng(0)
    s = 0.02
    cells = rng.integers(-20, 20, (300, 3))
    # 1..4 points per cell, each within +-0.4 voxel of its cell centre (no point near a border)
    pts = np.concatenate([(c + rng.uniform(-0.4, 0.4, (rng.integers(1, 5), 3))) * s for c in cells])
    pts = pts[rng.permutation(len(pts))].astype(np.float32)
    keep = voxel_downsample(pts, s)
    kept_cells = voxel_cells(pts[keep], s)
    assert len(keep) == len(np.unique(cells, axis=0))
    assert len(np.unique(kept_cells, axis=0)) == len(keep)  # one point per voxel
    assert set(map(tuple, kept_cells)) == set(map(tuple, voxel_cells(pts, s)))  # every voxel kept
    np.testing.assert_array_equal(voxel_downsample(pts, s), keep)  # deterministic
    assert len(voxel_downsample(pts, 0.0)) == len(pts)


def test_voxel_in_pipeline_on_sim_frame():
    from hardware.camera.tabletop import SimCamera

    cam = SimCamera(seed=0)
    cam.start(thread=False)
    frame = cam.capture()
    cam.stop()
    cfg = PointCloudConfig(n_points=200_000, voxel_size=0.02)
    cloud, info = frame_to_cloud(frame, cfg, cam.camera_to_base)
    real = cloud[: info.n_after_voxel]
    assert info.n_after_voxel < info.n_in_crop / 10
    assert info.n_padded == cfg.n_points - info.n_after_voxel
    # at most one point per 2 cm cell (allow float32 rounding at cell borders: a handful at most)
    cells = voxel_cells(real, 0.02)
    assert len(real) - len(np.unique(cells, axis=0)) <= 3
    # the table (z ~ 0) lies in one layer of voxels
    table = np.abs(real[:, 2]) < 0.005
    assert table.sum() > 1000 and np.all(cells[table, 2] == 0)


@pytest.mark.parametrize("n_points", [1, 7, 512, 1024, 4000])
def test_exactly_n_points(n_points):
    depth = _depth(seed=2)
    cfg = PointCloudConfig(n_points=n_points, **dict(EVERYWHERE, voxel_size=0.005))
    cloud, info = frame_to_cloud(_frame(depth), cfg)
    assert cloud.shape == (n_points, 3) and cloud.dtype == np.float32
    assert info.n_points == n_points
    assert info.n_padded == max(0, n_points - info.n_after_voxel)
    assert set(info.timings_ms) >= {"clip", "deproject", "crop", "voxel", "sample", "pad", "total"}
    assert info.timings_ms["total"] >= info.timings_ms["sample"] >= 0


def test_fps_subset_spread_and_deterministic():
    rng = np.random.default_rng(0)
    pts = rng.random((6000, 3)).astype(np.float32) * np.float32([0.8, 0.8, 0.1])
    idx = farthest_point_indices(pts, 256)
    assert idx.shape == (256,) and len(np.unique(idx)) == 256
    assert idx.min() >= 0 and idx.max() < len(pts)
    np.testing.assert_array_equal(idx, farthest_point_indices(pts, 256))

    def min_dist(p):
        d = np.linalg.norm(p[:, None] - p[None], axis=-1)
        np.fill_diagonal(d, np.inf)
        return d.min()

    rand = rng.choice(len(pts), 256, replace=False)
    assert min_dist(pts[idx]) > 3 * min_dist(pts[rand])
    # through the pipeline: every output point is one of the input points
    depth = _depth(seed=3)
    cfg = PointCloudConfig(n_points=300, **EVERYWHERE)
    cloud, info = frame_to_cloud(_frame(depth), cfg)
    everything, _ = frame_to_cloud(_frame(depth), PointCloudConfig(n_points=info.n_valid, **EVERYWHERE))
    rows = {tuple(r) for r in everything}
    assert info.n_after_voxel > 300 and info.n_padded == 0
    assert all(tuple(r) in rows for r in cloud) and len({tuple(r) for r in cloud}) == 300
    again, _ = frame_to_cloud(_frame(depth), cfg)
    np.testing.assert_array_equal(cloud, again)


def test_padding_repeats_real_points():
    depth = np.zeros((64, 96), np.uint16)
    depth[10, 10:15] = [3000, 3100, 3200, 3300, 3400]  # five valid pixels
    cfg = PointCloudConfig(n_points=32, **EVERYWHERE)
    cloud, info = frame_to_cloud(_frame(depth), cfg)
    assert cloud.shape == (32, 3)
    assert (info.n_valid, info.n_in_crop, info.n_after_voxel, info.n_padded) == (5, 5, 5, 27) and info.padded
    real = {tuple(r) for r in cloud[:5]}
    assert len(real) == 5 and all(tuple(r) in real for r in cloud)
    counts = [sum(tuple(r) == p for r in map(tuple, cloud)) for p in real]
    assert max(counts) - min(counts) <= 1  # repeated evenly (cyclic)


def test_invalid_depth_never_gives_origin_points():
    depth = _depth(seed=4, invalid=0.6)
    cfg = PointCloudConfig(n_points=1500, **EVERYWHERE)  # depth_near = 0: only 0 = "no data" is dropped
    m = _transform(_rot_z(30), (0.2, -0.1, 0.4))
    for transform, origin in ((None, np.zeros(3)), (m, m[:3, 3])):
        cloud, info = frame_to_cloud(_frame(depth), cfg, transform)
        assert info.n_valid == (depth > 0).sum()
        assert np.all(np.linalg.norm(cloud - origin, axis=1) > 1e-4)


def test_empty_clouds_raise_with_info():
    cfg = PointCloudConfig(n_points=64, **EVERYWHERE)
    with pytest.raises(EmptyCloudError) as exc:
        frame_to_cloud(_frame(np.zeros((64, 96), np.uint16)), cfg)
    assert "no valid depth" in _one_line(exc)
    assert exc.value.info.n_valid == 0 and exc.value.info.n_padded == 64
    assert isinstance(exc.value, CameraError)
    far_away = PointCloudConfig(n_points=64, crop_min=(5.0, 5.0, 5.0), crop_max=(6.0, 6.0, 6.0))
    with pytest.raises(EmptyCloudError) as exc:
        frame_to_cloud(_frame(_depth()), far_away)
    assert "crop box" in _one_line(exc) and exc.value.info.n_valid > 0 and exc.value.info.n_in_crop == 0


def test_colour_channels():
    depth = _depth(seed=5)
    h, w = depth.shape
    v, u = np.mgrid[0:h, 0:w]
    color = np.stack([u * 2, v * 3, np.full_like(u, 200)], axis=-1).astype(np.uint8)  # encodes the pixel
    cfg = PointCloudConfig(n_points=400, use_color=True, **EVERYWHERE)
    cloud, _ = frame_to_cloud(_frame(depth, color=color), cfg)
    assert cloud.shape == (400, 6) and cloud.dtype == np.float32
    rgb = cloud[:, 3:]
    assert rgb.min() >= 0 and rgb.max() <= 1
    # project each point back to its pixel: its colour must be that pixel's colour
    uu = np.rint(cloud[:, 0] / cloud[:, 2] * SMALL.fx + SMALL.ppx).astype(int)
    vv = np.rint(cloud[:, 1] / cloud[:, 2] * SMALL.fy + SMALL.ppy).astype(int)
    np.testing.assert_allclose(rgb, color[vv, uu] / 255.0, atol=1e-6)
    xyz_only, _ = frame_to_cloud(_frame(depth, color=color), PointCloudConfig(n_points=400, **EVERYWHERE))
    np.testing.assert_array_equal(xyz_only, cloud[:, :3])
    with pytest.raises(CameraError) as exc:
        frame_to_cloud(_frame(depth), cfg)
    assert "colour" in _one_line(exc)


def test_sim_frame_default_config():
    from hardware.camera.tabletop import Box, SimCamera

    cam = SimCamera(seed=0, color=True, moving_box=lambda t: Box(center=(0.3, 0.25, 0.1), size=(0.05, 0.05, 0.2)))
    cam.start(thread=False)
    frame = cam.capture()
    cam.stop()
    cloud, info = frame_to_cloud(frame, PointCloudConfig(), cam.camera_to_base)
    assert cloud.shape == (1024, 3) and info.n_padded == 0
    lo, hi = np.array(PointCloudConfig().crop_min), np.array(PointCloudConfig().crop_max)
    assert np.all(cloud >= lo - 1e-6) and np.all(cloud <= hi + 1e-6)
    assert np.mean(np.abs(cloud[:, 2]) < 0.005) > 0.8  # mostly table
    tall = cloud[cloud[:, 2] > 0.12]  # only the moving box (0.2 m tall) reaches above 12 cm
    assert len(tall) > 3 and np.allclose(tall[:, :2].mean(axis=0), (0.3, 0.25), atol=0.03)
    cloud6, _ = frame_to_cloud(frame, PointCloudConfig(use_color=True), cam.camera_to_base)
    assert cloud6.shape == (1024, 6)


# -- calibration files ---------------------------------------------------------------------------------------
def test_extrinsics_roundtrip(tmp_path):
    m = _transform(_rot_z(35) @ np.diag([1.0, -1.0, -1.0]), (0.9, 0.05, 0.6))
    path = save_extrinsics(tmp_path / "calib" / "cam.json", m, frame="piper_base", notes="test")
    data = json.loads(path.read_text())
    assert data["frame"] == "piper_base" and data["notes"] == "test"
    np.testing.assert_allclose(load_extrinsics(path), m, atol=1e-12)
    assert [p.name for p in path.parent.iterdir()] == ["cam.json"]  # no temporary file left
    np.testing.assert_array_equal(load_extrinsics(None), np.eye(4))


@pytest.mark.parametrize(
    "content, words",
    [
        ("{not json", "not valid JSON"),
        ('{"frame": "base"}', "camera_to_base"),
        ('{"camera_to_base": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}', "a list of 4 lists of 4 finite numbers"),
        (
            '{"camera_to_base": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, NaN], [0, 0, 0, 1]]}',
            "camera_to_base[2][3] must be a finite number",
        ),
        ('{"camera_to_base": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]]}', "last row"),
        ('{"camera_to_base": [[2, 0, 0, 0], [0, 2, 0, 0], [0, 0, 2, 0], [0, 0, 0, 1]]}', "orthonormal"),
        ('{"camera_to_base": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, -1, 0], [0, 0, 0, 1]]}', "determinant"),
        ('{"camera_to_base": [[1, 0, 0, 900], [0, 1, 0, 50], [0, 0, 1, 600], [0, 0, 0, 1]]}', "metres"),
        ('{"camera_to_base": [[1, 0, 0, "a"], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}', "finite number"),
    ],
)
def test_calibration_file_errors(tmp_path, content, words):
    path = tmp_path / "calib.json"
    path.write_text(content)
    with pytest.raises(CalibrationError) as exc:
        load_extrinsics(path)
    msg = _one_line(exc)
    assert words in msg and str(path) in msg


def test_calibration_missing_and_save_rejects(tmp_path):
    with pytest.raises(CalibrationError) as exc:
        load_extrinsics(tmp_path / "nope.json")
    assert "does not exist" in _one_line(exc)
    with pytest.raises(CalibrationError):
        save_extrinsics(tmp_path / "bad.json", np.diag([1.0, 1.0, 2.0, 1.0]))
    assert not list(tmp_path.iterdir())
    # printed with 4 decimals: still accepted
    m = np.round(_transform(_rot_z(33), (0.1, 0.2, 0.3)), 4)
    assert validate_extrinsics(m).shape == (4, 4)
    with pytest.raises(CalibrationError) as exc:  # the pipeline validates what it is given too
        frame_to_cloud(_frame(_depth()), PointCloudConfig(), np.diag([1.0, 1.0, -1.0, 1.0]))
    assert "determinant" in _one_line(exc)


# -- config ------------------------------------------------------------------------------------------------
def test_config_roundtrip(tmp_path):
    cfg = PointCloudConfig(
        n_points=512,
        depth_near=0.2,
        depth_far=1.5,
        crop_min=[-0.3, -0.3, 0.0],
        crop_max=(0.3, 0.3, 0.4),
        voxel_size=0.005,
        use_color=True,
    )
    assert cfg.crop_min == (-0.3, -0.3, 0.0) and cfg.point_dim == 6
    assert PointCloudConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    assert PointCloudConfig.load(cfg.save(tmp_path / "pc.json")) == cfg
    d = PointCloudConfig()
    assert (d.n_points, d.sampling, d.use_color, d.point_dim) == (1024, "fps", False, 3)


@pytest.mark.parametrize(
    "kw, words",
    [
        (dict(n_points=0), "n_points"),
        (dict(n_points=10.5), "n_points"),
        (dict(depth_near=1.0, depth_far=0.5), "depth_near"),
        (dict(depth_far=float("nan")), "depth_far"),
        (dict(voxel_size=-0.01), "voxel_size"),
        (dict(voxel_size=5.0), "voxel_size must be a number in [0, 1] m"),
        (dict(crop_min=(0.0, 0.0, 1.0), crop_max=(1.0, 1.0, 0.5)), "crop_min"),
        (dict(crop_min=(0.0, 0.0)), "crop_min"),
        (dict(use_color="yes"), "use_color"),
        (dict(sampling="random"), "sampling"),
    ],
)
def test_config_validation(kw, words):
    with pytest.raises(ConfigError) as exc:
        PointCloudConfig(**kw)
    assert words in _one_line(exc)


def test_config_from_dict_rejects_unknown_keys():
    with pytest.raises(ConfigError) as exc:
        PointCloudConfig.from_dict({"n_point": 512})
    assert "n_point" in _one_line(exc)
    with pytest.raises(ConfigError):
        PointCloudConfig.from_json("[1, 2]")


def test_pointcloud_imports_without_pyrealsense2():
    code = (
        "import sys; sys.modules['pyrealsense2'] = None; sys.modules['open3d'] = None\n"
        "import dssp_data.pointcloud, hardware.camera\n"
        "from hardware.camera.tabletop import SimCamera\n"
        "print('ok')"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "ok"

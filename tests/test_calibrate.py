"""Hand-eye calibration (``dssp-calibrate``, ``dssp-sim calibrate``) against the MuJoCo twin, with OpenCV's ChArUco
detection and hand-eye methods doing the work: the twin's camera pose is recovered to 2 mm / 0.5 degrees in both set-ups,
and what may not be trusted is refused with one line."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dssp_core.errors import CalibrationError, ConfigError
from dssp_data.arm_kinematics import flange_pose
from dssp_data.pointcloud.extrinsics import (
    load_camera_to_gripper,
    load_extrinsics,
    save_camera_to_gripper,
    save_extrinsics,
)
from dssp_sim.calibration_twin import CalibrationTwin, TwinRig
from dssp_sim.sim_cli import main as sim_main
from hardware.calibration.charuco import CharucoBoardSpec, detect_board
from hardware.calibration.hand_eye import distance, invert, solve_hand_eye
from hardware.calibration.pose_plan import auto_poses, load_poses
from hardware.calibration.tour import CalibrationTour
from hardware.rig import Rig
from hardware.run_loop import LoopSettings, Runner
from hardware.safety import SafetyConfig

BOUND_MM, BOUND_DEG = 2.0, 0.5
POSES = 10


def tour_on_the_twin(mode: str, n: int = POSES):
    """The calibration tour on the twin through the control loop: (views, the true transform)."""
    board = CharucoBoardSpec()
    rig = TwinRig(mode, board)
    try:
        with rig.camera:
            tour = CalibrationTour(
                lambda start: auto_poses(start, n),
                rig.camera,
                rig.clock,
                gripper="close" if mode == "eye-to-hand" else "hold",
                events=lambda line: None,
            )
            loop_rig = Rig(None, rig.robot, np.eye(4), SafetyConfig(), clock=rig.clock)
            with loop_rig:
                runner = Runner(tour, loop_rig, None, LoopSettings(control_rate_hz=10))
                summary = runner.run()
                runner.close()
        assert summary["fault"] is None and summary["ended_by"] == "done"
        assert summary["events"].get("clip", 0) > 0, "the far poses were ramped to by the safety layer"
        return tour.views, rig.truth(), board
    finally:
        rig.close()


@pytest.mark.parametrize("mode", ["eye-to-hand", "eye-in-hand"])
def test_the_twin_recovers_the_camera_pose(mode, tmp_path):
    views, truth, board = tour_on_the_twin(mode)
    assert len(views) == POSES
    detections = [detect_board(v.frame.color, v.frame.intrinsics, board) for v in views]
    assert all(d.ok for d in detections), [d.reason for d in detections]
    result = solve_hand_eye(
        [flange_pose(v.joints) for v in views], [d.board_to_camera for d in detections], mode, centre=board.centre
    )
    result.check()
    mm, deg = distance(result.transform, truth)
    assert mm <= BOUND_MM and deg <= BOUND_DEG, (mm, deg)
    assert len(result.disagreement) >= 2
    assert len(result.residuals) == POSES
    # what is written is what was solved
    path = tmp_path / "calib.json"
    if mode == "eye-to-hand":
        save_extrinsics(path, result.transform)
        assert np.array_equal(load_extrinsics(path), result.transform)
    else:
        save_camera_to_gripper(path, result.transform)
        assert np.array_equal(load_camera_to_gripper(path), result.transform)
        with pytest.raises(CalibrationError):  # dssp-run takes fixed cameras only
            load_extrinsics(path)


def test_dssp_sim_calibrate_writes_the_extrinsics_and_keeps_an_existing_file(tmp_path, capsys):
    out = tmp_path / "calib.json"
    argv = ["calibrate", "--mode", "eye-to-hand", "--auto", str(POSES), "--out", str(out)]
    assert sim_main(argv) == 0
    printed = capsys.readouterr().out
    assert "camera_to_base" in printed and "disagreement" in printed and " pose  corners" in printed
    written = load_extrinsics(out)
    mm, deg = distance(written, CalibrationTwin("eye-to-hand").truth())
    assert mm <= BOUND_MM and deg <= BOUND_DEG, (mm, deg)
    before = out.read_bytes()
    assert sim_main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "exists; pass --force" in err, err
    assert out.read_bytes() == before
    record = tmp_path / "record.json"
    assert sim_main(argv + ["--force", "--json", str(record)]) == 0
    # --json keeps the calibration's record: every view's row, the written transform, the distance from the truth
    kept = json.loads(record.read_text())
    assert kept["mode"] == "eye-to-hand" and kept["result"] == "camera_to_base" and len(kept["views"]) == POSES
    assert np.allclose(kept["transform"], load_extrinsics(out), atol=1e-9)
    assert kept["truth_error"] == pytest.approx(
        list(distance(load_extrinsics(out), CalibrationTwin("eye-to-hand").truth()))
    )
    used = [v for v in kept["views"] if "residual_mm" in v]
    assert used and np.sqrt(np.mean([v["residual_mm"] ** 2 for v in used])) == pytest.approx(kept["rms_mm"])


def test_too_few_poses_are_refused_with_one_line(tmp_path, capsys):
    """Too few poses are refused when parsed, before the twin opens; too few views with the board detected, by
    the solve."""
    out = tmp_path / "calib.json"
    with pytest.raises(SystemExit) as exited:
        sim_main(["calibrate", "--mode", "eye-to-hand", "--auto", "5", "--out", str(out)])
    assert exited.value.code == 2
    captured = capsys.readouterr()
    err = captured.err.strip()
    assert err.count("\n") == 0 and "--auto: N must be 8 to 200 poses" in err, err
    assert not out.exists() and "board" not in captured.out  # the twin was never opened
    views = auto_poses(CalibrationTwin("eye-to-hand").start_pose(), 8)[:5]
    grippers = [flange_pose(q) for q in views]
    with pytest.raises(CalibrationError, match="5 views with the board detected, 8 needed"):
        solve_hand_eye(grippers, grippers, "eye-to-hand")


def test_rotations_about_one_axis_are_refused_with_one_line(tmp_path, capsys):
    start = CalibrationTwin("eye-to-hand").start_pose()
    poses = np.repeat(start[None], 9, axis=0)
    poses[:, 5] += np.linspace(-0.4, 0.4, 9)  # J6 only: every rotation about the approach axis
    path = tmp_path / "poses.json"
    path.write_text(json.dumps({"poses": poses.tolist()}))
    out = tmp_path / "calib.json"
    assert sim_main(["calibrate", "--mode", "eye-to-hand", "--poses", str(path), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "about one axis only" in err, err
    assert not out.exists()


def test_an_image_without_the_board_gives_its_reason():
    twin = CalibrationTwin("eye-in-hand")
    try:
        found = detect_board(twin.render_rgb(), twin.intrinsics(), twin.board)
        assert found.ok
        twin.model.body_pos[twin.board_body] += [0.0, 3.0, 0.0]  # the board off the table, out of view
        import mujoco

        mujoco.mj_forward(twin.model, twin.data)
        empty = detect_board(twin.render_rgb(), twin.intrinsics(), twin.board)
    finally:
        twin.close()
    assert not empty.ok and empty.board_to_camera is None
    assert empty.reason == "0 board corners found (0 markers), 8 needed"
    assert not detect_board(None, twin.intrinsics(), twin.board).ok


def test_a_view_off_the_chain_is_refused_naming_it():
    """OpenCV's solve on exact synthetic views, one of them 20 mm off: the residuals name it."""
    import cv2

    rng = np.random.default_rng(1)

    def pose(rvec, t):
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = cv2.Rodrigues(np.asarray(rvec, float))[0], t
        return m

    camera_to_base, board_to_gripper = (
        pose([0.3, -2.0, 0.4], [0.9, 0.05, 0.5]),
        pose([0.1, 0.2, -0.3], [0.0, 0.02, 0.1]),
    )
    grippers = [pose(rng.normal(0, 0.3, 3) + [0, 3.0, 0], rng.normal([0.4, 0, 0.3], 0.05)) for _ in range(10)]
    boards = [invert(camera_to_base) @ g @ board_to_gripper for g in grippers]
    exact = solve_hand_eye(grippers, boards, "eye-to-hand")
    assert exact.problem() is None and distance(exact.transform, camera_to_base)[0] < 1e-6
    boards[4] = boards[4].copy()
    boards[4][:3, 3] += [0.02, 0.0, 0.0]
    with pytest.raises(CalibrationError, match=r"view 5's board is"):
        solve_hand_eye(grippers, boards, "eye-to-hand").check()


def test_poses_outside_the_limits_are_refused_before_anything_moves(tmp_path):
    path = tmp_path / "poses.json"
    path.write_text(json.dumps([[0.0, 1.0, -1.0, 0.0, 0.5, 0.0], [0.0, 3.5, -1.0, 0.0, 0.5, 0.0]]))
    with pytest.raises(ConfigError, match=r"pose 2 has J2 = 3\.5 rad, outside"):
        load_poses(path)
    path.write_text(json.dumps([[0.0, 1.0, -1.0]]))
    with pytest.raises(ConfigError, match="6 joint angles"):
        load_poses(path)

"""``dssp-calibrate``: hand-eye calibration of a RealSense and a Piper with a ChArUco board.

    dssp-calibrate --camera l515|d435|d405 --can can0 --mode eye-to-hand|eye-in-hand (--poses poses.json | --auto N)
                   --out calib.json [--json record.json] [--board board.json] [--force] [--control-rate HZ] [--safety FILE]
                   [--serial SERIAL] [--interface socketcan]

The arm visits each pose through the control loop and its safety layer (:mod:`hardware.calibration.tour`), a colour
frame is taken once it has settled, the board is detected in each (:mod:`hardware.calibration.charuco`) and the
camera solved for with OpenCV's hand-eye methods (:mod:`hardware.calibration.hand_eye`). It prints the result, the
methods' disagreement and a table of the views (corners, reprojection, residual), then writes ``--out``:
eye-to-hand the ``camera_to_base`` file ``dssp-run --extrinsics`` reads (:func:`dssp_data.pointcloud.save_extrinsics`),
eye-in-hand a ``camera_to_gripper`` file of its own. A result that may not be trusted is refused with one line
saying what is wrong and what to do, and nothing is written. Every flag is checked before a device opens or a file
is written: the rig's (:func:`_check`), the poses as a plan that can pass the solve (``--auto N`` bounded when
parsed), the board and safety files, the output paths (:func:`_check_outputs`). An output that still cannot be
written after the tour loses nothing: its content is kept in the system's temporary folder and printed, with one
``error:`` line (:func:`_write`). ``dssp-sim calibrate`` (same flags, :mod:`dssp_sim.calibration_twin`) runs this on
the MuJoCo twin, handed in as a :class:`SimulatedCalibrationRig` (this package never imports the simulation).
Exit codes: 0 written, 1 the arm or camera failed during the tour, 2 bad input, a refused calibration or an output
that could not be written, 128 + N stopped by signal N (the arm holds where it is), 141 stdout or stderr went away.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Protocol

from dssp_core.cli_runner import ArgumentParser, run_cli
from dssp_core.errors import ConfigError, DSSPError, OutputError
from dssp_core.schema import DEFAULT_CONTROL_RATE_HZ, check_rate
from hardware.cli.stops import Stops
from hardware.piper.bus import interface_name

MUJOCO = "mujoco"  # the camera and arm of the twin dssp-sim calibrate hands in
MODES = ("eye-to-hand", "eye-in-hand")
INTERFACE = "socketcan"  # --interface when not given


class SimulatedCalibrationRig(Protocol):
    """What ``dssp-sim calibrate`` hands in (:class:`dssp_sim.calibration_twin.TwinRigs`)."""

    def open(self, mode: str, board):
        """A rig for ``mode`` showing ``board``: ``camera`` (a Camera with colour), ``robot`` (a Robot), ``clock``,
        ``description`` (a phrase), ``truth()`` (the transform the calibration should find), ``close()``."""


def _pose_count(text: str) -> int:
    """``--auto N``, bounded when parsed by the plan's own bounds
    (:func:`hardware.calibration.pose_plan.check_pose_count`)."""
    from hardware.calibration.pose_plan import check_pose_count  # deferred: loads numpy

    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a whole number, got {text!r}") from None
    try:
        return check_pose_count(value, "N")
    except ConfigError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def build_parser(sim: SimulatedCalibrationRig | None = None, prog: str = "dssp-calibrate") -> argparse.ArgumentParser:
    from hardware.calibration.pose_plan import MAX_POSES, MIN_POSES  # deferred: loads numpy

    p = ArgumentParser(prog=prog, description="Hand-eye calibration of the camera with a ChArUco board.")
    default = MUJOCO if sim is not None else None
    p.add_argument(
        "--camera",
        default=default,
        required=sim is None,
        help="l515 | d435 | d405" + (" | mujoco (default: the twin's)" if sim else ""),
    )
    not_twin = " (not on the twin)" if sim else ""
    p.add_argument("--serial", help="RealSense serial number, when several are connected" + not_twin)
    p.add_argument(
        "--can",
        default=default,
        required=sim is None,
        help="the arm's CAN bus, e.g. can0" + (" | mujoco (default: the twin's arm)" if sim else ""),
    )
    p.add_argument("--interface", type=interface_name, help=f"python-can interface (default: {INTERFACE})" + not_twin)
    p.add_argument(
        "--mode",
        choices=MODES,
        required=True,
        help="eye-to-hand: fixed camera, board on the gripper (writes camera_to_base); eye-in-hand: camera "
        "on the wrist, board on the table (writes camera_to_gripper)",
    )
    where = p.add_mutually_exclusive_group(required=True)
    where.add_argument("--poses", type=Path, help='JSON of joint vectors (rad): {"poses": [[J1..J6], ...]}')
    where.add_argument(
        "--auto",
        type=_pose_count,
        metavar="N",
        help=f"N poses ({MIN_POSES} to {MAX_POSES}) generated around the arm's position at start (put "
        f"the board in view first)",
    )
    p.add_argument(
        "--board",
        type=Path,
        help="board JSON (squares_x, squares_y, square_m, marker_m, dictionary; "
        "default: 7 x 5 squares of 36 mm, DICT_4X4_50, A4)",
    )
    p.add_argument("--out", type=Path, required=True, help="the calibration JSON to write")
    p.add_argument(
        "--json",
        type=Path,
        help="also write the calibration's record here: the result, each view's row, the "
        "methods' disagreement (and on the twin the distance from the true pose)",
    )
    p.add_argument("--force", action="store_true", help="replace an existing --out (and --json)")
    p.add_argument(
        "--control-rate",
        type=float,
        default=DEFAULT_CONTROL_RATE_HZ,
        help=f"control rate of the moves, Hz (default {DEFAULT_CONTROL_RATE_HZ:g})",
    )
    p.add_argument("--safety", type=Path, help="safety settings JSON (hardware.safety.SafetyConfig fields)")
    return p


def _check(args, sim) -> None:
    """The rig's flags (camera, serial, bus, interface, rate), before anything opens."""
    from hardware.camera import check_camera_spec  # deferred: loads numpy
    from hardware.camera.profiles import profile_names  # deferred: loads numpy

    check_rate(args.control_rate)
    camera, can = args.camera.strip().lower(), args.can.strip().lower()
    if sim is not None:
        if camera != MUJOCO or can != MUJOCO:
            raise ConfigError(
                "dssp-sim calibrate runs the twin: --camera mujoco --can mujoco (the defaults); calibrate "
                "a real robot with dssp-calibrate"
            )
        for flag, value in (("--serial", args.serial), ("--interface", args.interface)):
            if value is not None:
                raise ConfigError(
                    f"{flag} {value}: the twin has no RealSense and no CAN interface to choose; leave "
                    f"{flag} out (it is dssp-calibrate's, for a real robot)"
                )
        return
    if camera not in profile_names():
        raise ConfigError(
            f"--camera {args.camera}: calibration needs a live RealSense with colour: one of "
            f"{', '.join(profile_names())}"
        )
    check_camera_spec(camera, args.serial)
    if can.startswith("sim") or can == MUJOCO:
        raise ConfigError(
            f"--can {args.can}: dssp-calibrate drives a real arm; calibrate the twin with dssp-sim calibrate"
        )


def _outputs(args) -> list[tuple[Path, str]]:
    """(path, flag) of each file the command writes: --out, then --json."""
    return [(args.out, "--out")] + ([(args.json, "--json")] if args.json is not None else [])


def _check_outputs(args) -> None:
    """--out and --json before anything opens: the output guard's rules (a new file, or one replaced with --force;
    never a folder or a link; in a folder this process may write; names the folder takes, the write's temporary
    name included), not one of the inputs, not each other."""
    from dssp_core.output_guard import check_not_inside, check_output_file  # deferred: loads numpy

    inputs = [path for path in (args.poses, args.board, args.safety) if path is not None]
    for path, flag in _outputs(args):
        try:
            check_output_file(path, force=args.force, flag=flag)
            check_not_inside(path, inputs, flag=flag)
        except OSError as exc:
            raise OutputError(f"cannot write {path} ({exc.strerror or exc}); choose another {flag}") from None
    if args.json is not None and os.path.realpath(args.json) == os.path.realpath(args.out):
        raise OutputError(f"--json {args.json} is the --out file; give the record a path of its own")


def _write(path: Path, flag: str, force: bool, write: Callable[[Path], None], what: str) -> str | None:
    """Write one output after the tour, checked again by the output guard (the tour took minutes); None when
    written. When it cannot be written the content is not lost: ``write`` puts it in a new file in the system's
    temporary folder (``dssp-calibrate-WHAT-XXXXXXXX.json``), it is printed on stdout, and the problem is returned as
    one line saying where it is."""
    from dssp_core.output_guard import check_output_file  # deferred: loads numpy

    try:
        check_output_file(path, force=force, flag=flag)
        write(path)
    except (DSSPError, OSError) as exc:
        problem = str(exc) if isinstance(exc, DSSPError) else f"cannot write {path} ({exc.strerror or exc})"
        kept = None
        try:
            fd, kept = tempfile.mkstemp(prefix=f"dssp-calibrate-{what.replace(' ', '-')}-", suffix=".json")
            os.close(fd)
            write(Path(kept))
            print(Path(kept).read_text(), end="", flush=True)
        except (DSSPError, OSError) as again:
            if kept is not None:
                with contextlib.suppress(OSError):
                    os.unlink(kept)
            return (
                f"{problem} — and the {what} could not be kept in the temporary folder either ({again}): the "
                f"result printed above is all there is"
            )
        return f"{problem} — the {what} is kept in {kept} (and printed above): move it where it belongs"
    print(f"wrote {path} ({what})")
    return None


def _table(views, detections, result) -> list[str]:
    lines = [" pose  corners  reproj px  residual mm  residual deg"]
    used = iter(result.residuals) if result is not None else None
    for view, found in zip(views, detections):
        if found.ok:
            r = next(used) if used is not None else None
            res = f"{r.mm:11.2f}  {r.deg:12.3f}" if r is not None else f"{'-':>11}  {'-':>12}"
            lines.append(f"{view.index + 1:5d}  {found.corners:7d}  {found.reprojection_px:9.2f}  {res}")
        else:
            lines.append(
                f"{view.index + 1:5d}  {found.corners:7d}  {'-':>9}  {'-':>11}  {'-':>12}  refused: {found.reason}"
            )
    return lines


def _matrix(m) -> str:
    return "\n".join("  [" + ", ".join(f"{v: .6f}" for v in row) + "]" for row in m)


def _calibrate(args, stops: Stops, sim) -> int:
    import numpy as np  # deferred: loads numpy

    from dssp_core.files import atomic_write_text  # deferred: with the rest
    from dssp_data.arm_kinematics import flange_pose  # deferred: loads numpy
    from dssp_data.pointcloud.extrinsics import save_camera_to_gripper, save_extrinsics  # deferred: loads numpy
    from hardware.calibration.charuco import detect_board, load_board  # deferred: loads cv2
    from hardware.calibration.hand_eye import distance, solve_hand_eye  # deferred: loads cv2
    from hardware.calibration.pose_plan import auto_poses, load_poses  # deferred: loads numpy
    from hardware.calibration.tour import CalibrationTour, check_robot  # deferred: loads numpy
    from hardware.clock import REAL_CLOCK  # deferred: loads numpy
    from hardware.piper.limits import MAX_JOINT_SPEED  # deferred: loads numpy
    from hardware.rig import Rig  # deferred: loads numpy
    from hardware.run_loop import LoopSettings, Runner  # deferred: loads onnxruntime
    from hardware.safety import SafetyConfig  # deferred: loads numpy

    _check(args, sim)  # every flag, before a device opens or a file is written
    board = load_board(args.board)
    if args.poses is not None:
        poses, plan = load_poses(args.poses), f"--poses {args.poses}"  # a plan that can pass, or refused here
    else:
        poses, plan = (lambda start: auto_poses(start, args.auto)), f"--auto {args.auto}"  # checked at the start pose
    safety = SafetyConfig.load(args.safety, "safety") if args.safety else SafetyConfig()
    safety.check_speed(args.control_rate, MAX_JOINT_SPEED)
    _check_outputs(args)
    if stops.reason is not None:
        print(f"stopped by {stops.reason} before the arm moved; nothing was sent", file=sys.stderr)
        return stops.code
    with contextlib.ExitStack() as stack:
        if sim is not None:
            twin = sim.open(args.mode, board)
            stack.callback(twin.close)
            camera, robot, clock, where = twin.camera, twin.robot, twin.clock, twin.description
            check_robot(robot.description)
        else:
            from hardware.camera import open_camera  # deferred: loads numpy
            from hardware.piper.piper_robot import open_robot  # deferred: loads can

            twin = None
            robot = open_robot(args.can, interface=args.interface or INTERFACE)  # what it is; no bus opened yet
            check_robot(robot.description)  # one arm, before the camera or the bus opens
            camera = open_camera(args.camera, serial=args.serial, color=True)  # not started yet
            clock, where = REAL_CLOCK, f"{args.camera} and the arm on {args.can}"
        tour = CalibrationTour(
            poses, camera, clock, gripper="close" if args.mode == "eye-to-hand" else "hold", where=plan
        )
        print(
            f"{args.mode} with {where}; board {board.squares_x} x {board.squares_y} squares of "
            f"{1e3 * board.square_m:g} mm ({board.dictionary}); moves at {args.control_rate:g} Hz through the safety layer"
        )
        stack.enter_context(camera)
        rig = Rig(None, robot, np.eye(4), safety, clock=clock)
        with rig:
            runner = Runner(tour, rig, None, LoopSettings(control_rate_hz=args.control_rate))
            stops.during(runner.request_stop)
            try:
                summary = runner.run()
            finally:
                stops.during(None)
                runner.close()
        truth = twin.truth() if twin is not None else None
    if summary["fault"]:
        print(f"error: the tour ended by a fault: {summary['fault']}; the arm holds its last target", file=sys.stderr)
        return 1
    if stops.reason is not None and summary["ended_by"] == stops.reason:
        print(
            f"stopped by {stops.reason} after {len(tour.views)} of {len(tour.poses)} poses; nothing was written",
            file=sys.stderr,
        )
        return stops.code

    views = tour.views
    detections = [detect_board(v.frame.color, v.frame.intrinsics, board) for v in views]
    good = [(v, d) for v, d in zip(views, detections) if d.ok]
    try:
        result = solve_hand_eye(
            [flange_pose(v.joints) for v, _ in good],
            [d.board_to_camera for _, d in good],
            args.mode,
            centre=board.centre,
        )
    except Exception:
        print("\n".join(_table(views, detections, None)))
        raise
    print("\n".join(_table(views, detections, result)))
    rms_mm, rms_deg = result.rms
    i, worst = result.worst
    print(
        f"{result.name} (OpenCV's {result.method}; {len(good)} of {len(views)} views, rotation spread "
        f"{result.rotation_spread_deg:.1f} deg about a second axis):\n{_matrix(result.transform)}"
    )
    print(
        "the methods' disagreement with it: "
        + ", ".join(f"{name} {mm:.2f} mm / {deg:.3f} deg" for name, (mm, deg) in result.disagreement.items())
    )
    print(
        f"residuals: {rms_mm:.2f} mm / {rms_deg:.3f} deg RMS; the worst against its limits, pose {good[i][0].index + 1}: "
        f"{worst.mm:.2f} mm / {worst.deg:.3f} deg"
    )
    truth_error = distance(result.transform, truth) if truth is not None else None
    if truth_error is not None:
        print(f"the twin's true {result.name} is {truth_error[0]:.2f} mm / {truth_error[1]:.3f} deg from it")
    result.check()
    if stops.reason is not None:
        print(f"stopped by {stops.reason}; nothing was written", file=sys.stderr)
        return stops.code
    notes = (
        f"dssp-calibrate {args.mode}: {len(good)} views, OpenCV {result.method}, residuals {rms_mm:.2f} mm / "
        f"{rms_deg:.3f} deg RMS; board {board.squares_x}x{board.squares_y} {1e3 * board.square_m:g} mm {board.dictionary}"
    )
    if args.mode == "eye-to-hand":

        def calibration(path: Path) -> None:
            save_extrinsics(path, result.transform, frame="base", notes=notes)
    else:

        def calibration(path: Path) -> None:
            save_camera_to_gripper(path, result.transform, notes=notes)

    problems = [_write(args.out, "--out", args.force, calibration, result.name)]
    if args.json is not None:
        text = (
            json.dumps(calibration_record(args, board, views, detections, result, truth_error, where), indent=1) + "\n"
        )
        problems.append(
            _write(args.json, "--json", args.force, lambda path: atomic_write_text(path, text), "calibration record")
        )
    problems = [problem for problem in problems if problem is not None]
    if problems:
        raise OutputError("; ".join(problems))
    return 0


def calibration_record(args, board, views, detections, result, truth_error, where: str) -> dict:
    """What ``--json`` keeps of a calibration: the settings, each view's row (corners, reprojection, residual, or why
    it was refused), the result, the methods' disagreement, the residuals' RMS and, on the twin, the distance of the
    result from the true pose (mm, deg)."""
    used = iter(result.residuals)
    rows = []
    for view, found in zip(views, detections):
        row = {"pose": view.index + 1, "corners": int(found.corners), "joints": [float(v) for v in view.joints]}
        if found.ok:
            r = next(used)
            row.update(reprojection_px=float(found.reprojection_px), residual_mm=float(r.mm), residual_deg=float(r.deg))
        else:
            row["refused"] = found.reason
        rows.append(row)
    rms_mm, rms_deg = result.rms
    return {
        "mode": args.mode,
        "rig": where,
        "rate_hz": args.control_rate,
        "poses": "auto" if args.poses is None else str(args.poses),
        "board": board.to_dict(),
        "views": rows,
        "result": result.name,
        "method": result.method,
        "transform": [[float(v) for v in row] for row in result.transform],
        "disagreement": {name: [float(mm), float(deg)] for name, (mm, deg) in result.disagreement.items()},
        "rms_mm": rms_mm,
        "rms_deg": rms_deg,
        "rotation_spread_deg": float(result.rotation_spread_deg),
        "truth_error": None if truth_error is None else [float(truth_error[0]), float(truth_error[1])],
    }


def main(
    argv: list[str] | None = None, sim: SimulatedCalibrationRig | None = None, prog: str = "dssp-calibrate"
) -> int:
    stops = Stops()  # first: from here every stop is a clean one
    try:
        args = build_parser(sim, prog).parse_args(argv)
        return run_cli(lambda: _calibrate(args, stops, sim))
    finally:
        stops.restore()


if __name__ == "__main__":
    sys.exit(main())

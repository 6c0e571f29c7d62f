"""What ``dssp-calibrate`` / ``dssp-sim calibrate`` refuse, and when: files that are not files, poses that are not
numbers, a key given twice, a plan that cannot pass the hand-eye solve, outputs that cannot be written, flags that
do not fit the rig — each one ``error:`` line and exit 2 before the rig opens, the arm moves or a file is written; and
an output that fails only after the tour loses nothing. The refusals run against a rig that fails the test if it is
opened; the tours run on the ideal robot (a fake clock) or once on the MuJoCo twin."""

from __future__ import annotations

import errno
import json
import os
import shutil
import tempfile
import threading
from pathlib import Path

import numpy as np
import pytest
from conftest import CALIBRATION_START, one_error_line, refusal
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dssp_core import files
from dssp_core.errors import CalibrationError, ConfigError
from dssp_data.arm_kinematics import flange_pose
from dssp_data.pointcloud.extrinsics import load_extrinsics
from dssp_sim.calibration_twin import CalibrationTwin, TwinRigs
from hardware.calibration.hand_eye import MIN_POSES, PoseSpread, check_views, distance
from hardware.calibration.pose_plan import MAX_POSES, auto_poses, load_poses
from hardware.calibration.tour import CalibrationTour
from hardware.cli.calibrate import main as calibrate_main
from hardware.clock import FakeClock
from hardware.ideal_robot import IdealRobot
from hardware.piper.limits import piper_description
from hardware.rig import Rig
from hardware.run_loop import LoopSettings, Runner
from hardware.safety import SafetyConfig

GOOD = auto_poses(CALIBRATION_START, 16)  # a plan that passes (as many poses as the plans drawn below hold at most)
HYPOTHESIS = {
    "deadline": None,
    "derandomize": True,
    "database": None,
    "max_examples": 25,
    "suppress_health_check": [HealthCheck.function_scoped_fixture],
}


class NeverOpened:
    """A simulated rig that fails the test when the command opens it: what is refused is refused before."""

    def open(self, mode, board):
        raise AssertionError("the rig was opened")


def run(capsys, *argv, sim=None):
    """``dssp-sim calibrate`` in-process on ``sim`` (default: a rig that must not open), or ``dssp-calibrate`` when
    ``sim`` is False: (exit code, stdout, stderr); a flag argparse refuses exits 2 with its one line."""
    sim = NeverOpened() if sim is None else sim or None
    try:
        code = calibrate_main(
            [str(a) for a in argv], sim=sim, prog="dssp-calibrate" if sim is None else "dssp-sim calibrate"
        )
    except SystemExit as exc:
        code = exc.code
    out, err = capsys.readouterr()
    return code, out, err


def refused(capsys, *argv, sim=None) -> str:
    """The :func:`conftest.refusal` line of the command on ``argv`` (``run``)."""
    return refusal(run(capsys, *argv, sim=sim))


def write_plan(path: Path, poses) -> Path:
    path.write_text(json.dumps({"poses": np.asarray(poses).tolist()}))
    return path


# -- files that are not files ----------------------------------------------------------------------------------------
class Watchdog:
    """Opens a FIFO's other end if the command is still blocked on it after ``seconds`` (a regression then fails
    the test instead of hanging it)."""

    def __init__(self, fifo: Path, seconds: float = 20.0) -> None:
        self.fifo, self.fired = fifo, False
        self.timer = threading.Timer(seconds, self._unblock)

    def _unblock(self) -> None:
        self.fired = True
        try:
            os.close(os.open(self.fifo, os.O_WRONLY | os.O_NONBLOCK))
        except OSError:
            pass

    def __enter__(self):
        self.timer.start()
        return self

    def __exit__(self, *exc) -> None:
        self.timer.cancel()


def hostile(kind: str, folder: Path, flag: str) -> Path:
    path = folder / f"{flag.strip('-')}-{kind}"
    if kind == "fifo":
        os.mkfifo(path)
    elif kind == "device":
        return Path("/dev/zero")
    elif kind == "directory":
        path.mkdir()
    elif kind == "deep":
        path.write_text("[" * 100_000 + "]" * 100_000)
    elif kind == "twice":
        key = "poses" if flag == "--poses" else "squares_x" if flag == "--board" else "max_joint_step"
        value = GOOD.tolist() if flag == "--poses" else 5 if flag == "--board" else 0.01
        path.write_text(f'{{"{key}": {json.dumps(value)}, "{key}": {json.dumps(value)}}}')
    return path


WORDS = {"fifo": "FIFO", "device": "device", "directory": "directory", "deep": "nested more than", "twice": "twice"}


@pytest.mark.parametrize("flag", ["--poses", "--board", "--safety"])
@pytest.mark.parametrize("kind", sorted(WORDS))
def test_a_file_that_is_not_a_file_is_one_line_before_the_rig_opens(tmp_path, capsys, flag, kind):
    path = hostile(kind, tmp_path, flag)
    argv = ["--mode", "eye-to-hand", "--out", tmp_path / "calib.json", flag, path]
    if flag != "--poses":
        argv += ["--auto", "12"]
    with Watchdog(path) as watchdog:
        line = refused(capsys, *argv)
    assert not watchdog.fired, "the command blocked on the FIFO"
    assert str(path) in line and WORDS[kind] in line, line
    assert not (tmp_path / "calib.json").exists()


# -- poses that are not numbers, a key given twice -------------------------------------------------------------------
NOT_NUMBERS = st.one_of(
    st.sampled_from(["0.1", "1e-3", "", "nan"]),
    st.text(max_size=6),
    st.booleans(),
    st.none(),
    st.lists(st.floats(-1, 1), min_size=1, max_size=2),
    st.dictionaries(st.text(max_size=2), st.integers(), max_size=1),
)


@settings(**HYPOTHESIS)
@given(i=st.integers(0, len(GOOD) - 1), j=st.integers(0, 5), bad=NOT_NUMBERS)
def test_a_joint_that_is_not_a_number_is_refused_naming_it(tmp_path_factory, i, j, bad):
    poses = GOOD.tolist()
    poses[i][j] = bad
    path = tmp_path_factory.mktemp("poses") / "poses.json"
    path.write_text(json.dumps({"poses": poses}))
    with pytest.raises(ConfigError, match=rf"pose {i + 1} gives J{j + 1} as .*not a number") as caught:
        load_poses(path)
    assert "\n" not in str(caught.value)


@settings(**HYPOTHESIS)
@given(i=st.integers(0, len(GOOD) - 1), j=st.integers(0, 5), big=st.sampled_from([10**400, -(10**309)]))
def test_a_joint_beyond_any_float_is_refused_naming_it(tmp_path_factory, i, j, big):
    poses = GOOD.tolist()
    poses[i][j] = big
    path = tmp_path_factory.mktemp("poses") / "poses.json"
    path.write_text(json.dumps({"poses": poses}))
    with pytest.raises(ConfigError, match=rf"pose {i + 1} gives J{j + 1} as .*not a finite number"):
        load_poses(path)


@pytest.mark.parametrize("second", ["first", "last"])
def test_poses_given_twice_are_refused_not_one_of_them_toured(tmp_path, capsys, second):
    other = auto_poses(CALIBRATION_START + 0.05, 12)
    lists = [json.dumps(GOOD.tolist()), json.dumps(other.tolist())][:: 1 if second == "last" else -1]
    path = tmp_path / "poses.json"
    path.write_text(f'{{"poses": {lists[0]}, "notes": "x", "poses": {lists[1]}}}')
    line = refused(capsys, "--mode", "eye-to-hand", "--poses", path, "--out", tmp_path / "calib.json")
    assert "gives the key poses twice" in line and str(path) in line, line


# -- a plan that cannot pass is refused before anything moves --------------------------------------------------------
@settings(**HYPOTHESIS)
@given(
    count=st.integers(1, 16),
    distinct=st.integers(1, 16),
    scale=st.sampled_from([0.0, 0.005, 0.03, 0.2, 1.0]),
    joints=st.sampled_from(["all", "J6 only"]),
)
def test_a_plan_is_held_to_the_solves_own_rule_before_the_rig_opens(
    tmp_path_factory, capsys, count, distinct, scale, joints
):
    """A plan of ``distinct`` poses, repeated up to ``count``, spread ``scale`` times the generated plan's: refused
    exactly when its views, detected perfectly, would be refused by the solve (one rule, PoseSpread), and then
    before the rig opens — too few poses, too few distinct orientations, rotations about one axis or too small."""
    distinct = min(distinct, count)
    offsets = (GOOD - CALIBRATION_START) * scale
    if joints == "J6 only":
        offsets[:, :5] = 0.0
    plan = (CALIBRATION_START + offsets[:distinct])[np.arange(count) % distinct]
    grippers = [flange_pose(q) for q in plan]
    solvable = PoseSpread.of(grippers).problem("poses") is None
    try:
        check_views(grippers)
        assert solvable
    except CalibrationError:
        assert not solvable
    if count < MIN_POSES or distinct < MIN_POSES or scale == 0.0 or joints == "J6 only":
        assert not solvable
    if count >= MIN_POSES and distinct >= MIN_POSES and scale == 1.0 and joints == "all":
        assert solvable
    folder = tmp_path_factory.mktemp("plan")
    path = write_plan(folder / "poses.json", plan)
    if solvable:
        assert np.array_equal(load_poses(path), plan)
        return
    line = refused(capsys, "--mode", "eye-in-hand", "--poses", path, "--out", folder / "calib.json")
    assert f"--poses {path}: a calibration plan that cannot pass" in line, line
    assert not (folder / "calib.json").exists()


@pytest.mark.parametrize("n", [0, 3, MIN_POSES - 1, MAX_POSES + 1, 100_000])
def test_auto_is_bounded_when_parsed(tmp_path, capsys, n):
    line = refused(capsys, "--mode", "eye-to-hand", "--auto", n, "--out", tmp_path / "calib.json")
    assert f"--auto: N must be {MIN_POSES} to {MAX_POSES} poses" in line and f"got {n}" in line, line


def test_a_generated_plan_that_cannot_pass_is_refused_at_the_start_before_the_first_move():
    """--auto's poses come from where the arm starts: they are checked there, before the first command."""
    clock = FakeClock()
    start = np.append(CALIBRATION_START, 1.0)
    robot = IdealRobot(piper_description(1), start, clock)
    tour = CalibrationTour(
        lambda joints: np.repeat(joints[None], 12, axis=0), None, clock, where="--auto 12", events=lambda line: None
    )
    with Rig(None, robot, np.eye(4), SafetyConfig(), clock=clock) as rig:
        runner = Runner(tour, rig, None, LoopSettings(control_rate_hz=10))
        with pytest.raises(
            ConfigError,
            match=r"--auto 12: a calibration plan that cannot pass: the 12 poses turn "
            r"the gripper to 1 distinct orientation",
        ):
            runner.run()
        runner.close()
    assert np.array_equal(robot.position, start)  # at most the final hold, where it stood


# -- outputs and the other flags, before the rig opens ---------------------------------------------------------------
def output_cases(tmp_path: Path) -> dict[str, tuple[list, str]]:
    poses = write_plan(tmp_path / "poses.json", GOOD)
    (tmp_path / "a-file").write_text("x")
    (tmp_path / "a-folder").mkdir()
    (tmp_path / "record.json").write_text("{}")
    out = tmp_path / "calib.json"
    return {
        "--json is --out": (["--auto", 12, "--out", out, "--json", out], "is the --out file"),
        "--out is the poses": (["--poses", poses, "--out", poses, "--force"], "is also an input"),
        "a name too long": (["--auto", 12, "--out", tmp_path / ("c" * 250 + ".json")], "longer than the"),
        "a folder too long": (["--auto", 12, "--out", tmp_path / ("d" * 300) / "c.json"], "cannot write"),
        "under a file": (["--auto", 12, "--out", tmp_path / "a-file" / "c.json"], "is a file, not a folder"),
        "a folder": (["--auto", 12, "--out", tmp_path / "a-folder"], "exists and is not a file"),
        "an existing --json": (["--auto", 12, "--out", out, "--json", tmp_path / "record.json"], "pass --force"),
    }


@pytest.mark.parametrize(
    "case",
    [
        "--json is --out",
        "--out is the poses",
        "a name too long",
        "a folder too long",
        "under a file",
        "a folder",
        "an existing --json",
    ],
)
def test_an_output_that_cannot_be_written_is_refused_before_the_rig_opens(tmp_path, capsys, case):
    argv, words = output_cases(tmp_path)[case]
    before = sorted(p.name for p in tmp_path.iterdir())
    line = refused(capsys, "--mode", "eye-to-hand", *argv)
    assert words in line, line
    assert sorted(p.name for p in tmp_path.iterdir()) == before


@pytest.mark.parametrize(
    "argv, words",
    [
        (["--serial", "123"], "--serial 123: the twin has no RealSense"),
        (["--interface", "socketcan"], "--interface socketcan: the twin has no"),
        (["--camera", "d435"], "dssp-sim calibrate runs the twin"),
        (["--control-rate", "0"], "--control-rate must be in"),
        (["--control-rate", "100"], "above the arm's"),
    ],
)
def test_the_twins_flags_are_checked_before_it_opens(tmp_path, capsys, argv, words):
    line = refused(capsys, "--mode", "eye-to-hand", "--auto", 12, "--out", tmp_path / "calib.json", *argv)
    assert words in line, line


@pytest.mark.parametrize(
    "argv, words",
    [
        (["--interface", "bogus"], "'bogus' is not a python-can interface"),
        (["--can", "can0,can1"], "calibration moves one arm"),
        (["--can", "sim"], "drives a real arm"),
    ],
)
def test_the_robots_flags_are_checked_before_anything_opens(tmp_path, capsys, argv, words):
    code, out, err = run(
        capsys,
        "--camera",
        "d435",
        "--can",
        "can0",
        "--mode",
        "eye-to-hand",
        "--auto",
        12,
        "--out",
        tmp_path / "calib.json",
        *argv,
        sim=False,
    )
    assert code == 2 and words in one_error_line(err), err
    assert "board 7 x 5" not in out  # refused before the rig was opened and announced


# -- an output that fails after the tour loses nothing ---------------------------------------------------------------
class FolderTakenRigs(TwinRigs):
    """The twin, but while it opens the folder of --out becomes a file (another program, a full disk, ...)."""

    def __init__(self, folder: Path) -> None:
        super().__init__()
        self.folder = folder

    def open(self, mode, board):
        shutil.rmtree(self.folder)
        self.folder.write_text("not a folder any more")
        return super().open(mode, board)


def test_an_output_that_fails_after_the_tour_is_kept_and_printed(tmp_path, capsys, monkeypatch):
    folder, records, temp = tmp_path / "calibrations", tmp_path / "records", tmp_path / "temp"
    for f in (folder, records, temp):
        f.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(temp))
    real = files.atomic_write_text

    def full_disk(path, text):
        if Path(path).parent == records:
            raise OSError(errno.ENOSPC, "No space left on device")
        real(path, text)

    monkeypatch.setattr(files, "atomic_write_text", full_disk)
    rigs = FolderTakenRigs(folder)
    code, out, err = run(
        capsys,
        "--mode",
        "eye-to-hand",
        "--auto",
        MIN_POSES,
        "--out",
        folder / "calib.json",
        "--json",
        records / "record.json",
        sim=rigs,
    )
    assert code == 2, err
    line = one_error_line(err)
    assert "is a file, not a folder" in line and "No space left on device" in line, line
    [calibration] = temp.glob("dssp-calibrate-camera_to_base-*.json")
    [record] = temp.glob("dssp-calibrate-calibration-record-*.json")
    assert str(calibration) in line and str(record) in line, line
    assert calibration.read_text() in out and record.read_text() in out  # printed too
    kept, kept_record = load_extrinsics(calibration), json.loads(record.read_text())
    assert np.allclose(kept_record["transform"], kept, atol=1e-9)
    mm, deg = distance(kept, CalibrationTwin("eye-to-hand").truth())
    assert mm <= 2.0 and deg <= 0.5, (mm, deg)  # the tour's result, kept whole
    assert folder.is_file() and not list(records.iterdir())  # nothing half-written where the outputs were asked for


def test_when_the_temporary_folder_fails_too_the_line_says_what_is_left(tmp_path, monkeypatch):
    from hardware.cli.calibrate import _write

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "missing"))
    (tmp_path / "a-file").write_text("x")
    line = _write(
        tmp_path / "a-file" / "calib.json",
        "--out",
        False,
        lambda path: files.atomic_write_text(path, "{}"),
        "camera_to_base",
    )
    assert "is a file, not a folder" in line and "could not be kept in the temporary folder either" in line, line
    assert "\n" not in line and not (tmp_path / "missing").exists()

"""The Piper's own joint limits, read from its firmware before anything is enabled or recorded.

The query (0x472) and its answer (0x473) against piper-sdk, the library on the other side: its encoder writes our
query byte for byte, its parser reads our answer (and any answer) to the same integers, and it reads the simulated
arm's answers to its own queries. The simulated arms (the CAN simulator and the MuJoCo Piper) answer with the limits
they are configured with. The verdict (accepted iff each firmware range holds the safety layer's) is checked on
random ranges. Then the commands: dssp-run and dssp-record against a simulated arm whose firmware limits are empty
(min = max), inverted (min > max), narrower than the safety settings, or never answered are refused with one line and
exit code 2, and the CAN bus shows that nothing but the query was sent — no enable (0x471), no mode, joint or gripper
command; healthy limits start as before.
"""

from __future__ import annotations

import functools
import math

import can
import numpy as np
import pytest
from conftest import channel, one_error_line
from hypothesis import given, settings
from hypothesis import strategies as st
from piper_sdk import C_PiperInterface_V2
from piper_sdk.piper_msgs.msg_v2 import ArmMsgSearchMotorMaxAngleSpdAccLimit, ArmMsgType, PiperMessage
from piper_sdk.protocol.protocol_v2 import C_PiperParserV2
from waiting import wait_for

from dssp_core.errors import ArmError
from hardware.can_log import read_log
from hardware.clock import FakeClock
from hardware.piper import codec, piper_robot
from hardware.piper.arm import PiperArm
from hardware.piper.can_simulator import SimulatedPiper
from hardware.piper.firmware_limits import factory_limits
from hardware.piper.limits import FIRMWARE_LOWER_DEG, FIRMWARE_UPPER_DEG, JOINT_LOWER, JOINT_UPPER, piper_description
from hardware.rig import Rig
from hardware.robot import FirmwareLimits, Robot
from hardware.safety import SafetyConfig, firmware_limits_problem

# The SDK opens its bus with python-can's deprecated ``bustype=`` argument.
pytestmark = pytest.mark.filterwarnings("ignore:The 'bustype' argument is deprecated:DeprecationWarning")

DECIDEG = math.radians(0.1)  # one wire unit of a firmware limit (rad)
FACTORY = factory_limits(3.0)
# What the firmware must never send before its limits are read: enable, e-stop/reset, mode, joints, gripper.
MOTION_IDS = {codec.MOTOR_ENABLE, codec.MOTION_CTRL_1, codec.MOTION_CTRL_2, *codec.JOINT_CTRL_IDS, codec.GRIPPER_CTRL}


def with_joint(joint: int, lo_deg: float, hi_deg: float) -> FirmwareLimits:
    """The factory limits with joint ``joint`` (0-based) set to lo..hi degrees."""
    lower, upper = FACTORY.lower.copy(), FACTORY.upper.copy()
    lower[joint], upper[joint] = math.radians(lo_deg), math.radians(hi_deg)
    return FirmwareLimits(lower, upper, FACTORY.max_speed)


# The corrupted arms of the start-up tests: (firmware limits, or None for one that never answers; the joint named,
# the words of the refusal).
CORRUPTED = {
    "empty": (with_joint(1, 0.0, 0.0), "J2", "0.0..0.0 deg (empty: min = max)"),
    "inverted": (with_joint(2, 0.0, -170.0), "J3", "0.0..-170.0 deg (inverted: min > max)"),
    "narrower": (with_joint(0, -100.0, 100.0), "J1", "-100.0..100.0 deg (narrower)"),
    "silent": (None, "J1,J2,J3,J4,J5,J6", "did not answer the joint-limit query (0x472)"),
}


# ---- the frames, against piper-sdk --------------------------------------------------------------------------
@pytest.mark.parametrize("motor", range(1, 7))
@pytest.mark.parametrize("content", [codec.QUERY_ANGLE_SPEED, codec.QUERY_ACCELERATION])
def test_our_query_is_the_sdks_byte_for_byte(motor, content):
    message = PiperMessage()
    message.type_ = ArmMsgType.PiperMsgSearchMotorMaxAngleSpdAccLimit
    message.arm_search_motor_max_angle_spd_acc_limit = ArmMsgSearchMotorMaxAngleSpdAccLimit(motor, content)
    sdk_frame = can.Message()
    assert C_PiperParserV2().EncodeMessage(message, sdk_frame)
    ours = codec.MotorLimitQuery(motor, content).to_frame()
    assert (ours.arbitration_id, bytes(ours.data)) == (sdk_frame.arbitration_id, bytes(sdk_frame.data))
    assert codec.Decoder().decode(ours) == codec.MotorLimitQuery(motor, content)


def sdk_reads(frame: can.Message):
    """piper-sdk's parser on one 0x473 frame: (motor_num, max_angle_limit, min_angle_limit, max_joint_spd)."""
    out = PiperMessage()
    assert C_PiperParserV2().DecodeMessage(frame, out)
    m = out.arm_feedback_current_motor_angle_limit_max_spd
    return m.motor_num, m.max_angle_limit, m.min_angle_limit, m.max_joint_spd


@settings(max_examples=200, deadline=None)
@given(data=st.binary(min_size=8, max_size=8))
def test_any_answer_reads_the_same_in_the_sdk_and_in_our_decoder(data):
    frame = can.Message(arbitration_id=codec.MOTOR_LIMIT_FEEDBACK, data=data, is_extended_id=False)
    ours = codec.Decoder().decode(frame)
    assert isinstance(ours, codec.MotorLimitFeedback)
    motor, max_angle, min_angle, max_speed = sdk_reads(frame)
    assert ours.motor == motor
    assert round(math.degrees(ours.max_angle) * 10) == max_angle
    assert round(math.degrees(ours.min_angle) * 10) == min_angle
    assert round(ours.max_speed * 1000) == max_speed
    assert bytes(ours.to_frame().data)[:7] == data[:7]  # byte 7 is reserved: we send 0


@settings(max_examples=100, deadline=None)
@given(
    motor=st.integers(1, 6),
    max_angle=st.integers(-32768, 32767),
    min_angle=st.integers(-32768, 32767),
    max_speed=st.integers(0, 65535),
)
def test_the_sdk_reads_our_answer_to_the_intended_integers(motor, max_angle, min_angle, max_speed):
    message = codec.MotorLimitFeedback(motor, max_angle * DECIDEG, min_angle * DECIDEG, max_speed / 1000)
    assert sdk_reads(message.to_frame()) == (motor, max_angle, min_angle, max_speed)


def test_the_sdk_queries_the_simulated_arm_and_reads_its_limits():
    """piper-sdk's own query (SearchMotorMaxAngleSpdAccLimit, motor by motor) answered by our simulator: the SDK reads
    the factory table in its units (0.1 degree, 0.001 rad/s); a corrupted J2 reads as min = max. (The SDK keeps one
    message object for every motor in GetAllMotorAngleLimitMaxSpd, so each answer is read as it comes.)"""
    name = channel("sdk")
    sim = SimulatedPiper(name, "virtual", firmware_limits=with_joint(1, 0.0, 0.0))
    sim.start()
    sdk = C_PiperInterface_V2(name, judge_flag=False, can_auto_init=False)
    sdk.CreateCanBus(name, bustype="virtual", judge_flag=False)
    sdk.ConnectPort()
    try:
        read = []
        for motor in range(1, 7):
            sdk.SearchMotorMaxAngleSpdAccLimit(motor, codec.QUERY_ANGLE_SPEED)
            current = lambda: sdk.GetCurrentMotorAngleLimitMaxVel().current_motor_angle_limit_max_vel  # noqa: E731
            wait_for(lambda: current().motor_num == motor, what=f"the SDK reads motor {motor}'s answer")
            m = current()
            read.append((m.max_angle_limit, m.min_angle_limit, m.max_joint_spd))
        expected = [(round(10 * hi), round(10 * lo), 3000) for lo, hi in zip(FIRMWARE_LOWER_DEG, FIRMWARE_UPPER_DEG)]
        expected[1] = (0, 0, 3000)
        assert read == expected
        assert sim.queries_received >= 6 and sim.commands_received == 0  # a query is not a command
    finally:
        sdk.DisconnectPort()
        sim.stop()


# ---- the simulated arms answer -----------------------------------------------------------------------------------
def read_limits(sim: SimulatedPiper) -> FirmwareLimits:
    """Our driver asks a stepped simulator for its limits; returns what it reported."""
    arm = PiperArm(sim.channel, "virtual")
    arm.connect()
    try:
        assert arm.firmware_limits().missing == tuple(range(6))  # nothing before the query
        arm.query_limits()
        sim.step(0.0)
        wait_for(lambda: not arm.firmware_limits().missing, what="six answers")
        arm.query_limits()  # all answered: nothing more is asked
        return arm.firmware_limits()
    finally:
        arm.close()


def test_the_simulated_arm_answers_with_its_configured_limits():
    for configured in (None, CORRUPTED["inverted"][0]):
        sim = SimulatedPiper(channel("sim"), "virtual", firmware_limits=configured)
        sim.start(thread=False)
        try:
            reported = read_limits(sim)
            assert sim.queries_received == 6
        finally:
            sim.stop()
        expected = configured or FACTORY
        np.testing.assert_allclose(reported.lower, expected.lower, atol=DECIDEG / 2)
        np.testing.assert_allclose(reported.upper, expected.upper, atol=DECIDEG / 2)
        np.testing.assert_allclose(reported.max_speed, 3.0)
        assert reported.arm.startswith("the arm on test-sim-")
        assert "MotorAngleLimitMaxSpdSet(motor_num=2" in reported.advice[1]


def test_the_mujoco_piper_answers_with_its_mjcf_ranges():
    from dssp_sim.env import PiperEnv
    from dssp_sim.mujoco_arm import MujocoPiper

    env = PiperEnv("tap", seed=0)
    try:
        sim = MujocoPiper(env, channel("mujoco"))
        sim.start(thread=False)
        try:
            reported = read_limits(sim)
        finally:
            sim.stop()
    finally:
        env.close()
    np.testing.assert_allclose(reported.lower, JOINT_LOWER, atol=DECIDEG / 2)  # the MJCF's hinges carry limits.py's
    np.testing.assert_allclose(reported.upper, JOINT_UPPER, atol=DECIDEG / 2)
    assert firmware_limits_problem(reported, JOINT_LOWER, JOINT_UPPER) is None  # rounded to 0.1 degree, still healthy


# ---- the verdict --------------------------------------------------------------------------------------------------
angles = st.floats(-3.2, 3.2, allow_nan=False)


@settings(max_examples=300, deadline=None)
@given(
    firmware=st.lists(st.tuples(angles, angles), min_size=6, max_size=6),
    allowed=st.lists(st.tuples(angles, angles).map(sorted), min_size=6, max_size=6),
)
def test_limits_are_accepted_iff_each_firmware_range_holds_the_safety_range(firmware, allowed):
    reported = FirmwareLimits([lo for lo, _ in firmware], [hi for _, hi in firmware], np.full(6, 3.0), arm="the arm")
    lower, upper = np.array(allowed).T
    holds = all(lo < hi and lo <= a_lo and hi >= a_hi for (lo, hi), (a_lo, a_hi) in zip(firmware, allowed))
    problem = firmware_limits_problem(reported, lower, upper)
    assert (problem is None) == holds, problem
    if problem is not None:  # one line: the arm, the first bad joint, both ranges, what to do
        j = next(
            i
            for i, ((lo, hi), (a_lo, a_hi)) in enumerate(zip(firmware, allowed))
            if not (lo < hi and lo <= a_lo and hi >= a_hi)
        )
        assert problem.startswith(f"the arm: its firmware limits J{j + 1} to ") and "\n" not in problem
        assert f"{math.degrees(lower[j]):.1f}..{math.degrees(upper[j]):.1f} deg" in problem and "start again" in problem


@settings(max_examples=100, deadline=None)
@given(offsets=st.lists(st.floats(-1.0, 1.0), min_size=2, max_size=2))
def test_a_firmware_limit_within_half_its_step_of_the_safety_range_is_that_range_rounded(offsets):
    """The firmware keeps its limits in 0.1 degree: a limit less than 0.05 degree inside the safety range is the
    same limit, rounded; one further inside is narrower."""
    lower, upper = JOINT_LOWER.copy(), JOINT_UPPER.copy()
    inside = np.array(offsets) * DECIDEG  # how far inside the safety range each end of J4 lies
    reported_lower, reported_upper = lower.copy(), upper.copy()
    reported_lower[3] += inside[0]
    reported_upper[3] -= inside[1]
    reported = FirmwareLimits(reported_lower, reported_upper, np.full(6, 3.0), resolution=DECIDEG)
    problem = firmware_limits_problem(reported, lower, upper)
    assert (problem is None) == bool(np.all(inside <= DECIDEG / 2)), (inside, problem)


@settings(max_examples=200, deadline=None)
@given(
    answers=st.lists(st.lists(st.tuples(angles, angles), min_size=6, max_size=6), min_size=1, max_size=3),
    allowed=st.lists(
        st.tuples(angles, st.floats(0.01, 3.0)).map(lambda a: (a[0], a[0] + a[1])), min_size=6, max_size=6
    ),
)
def test_several_answers_on_one_bus_are_refused_iff_one_of_them_is(answers, allowed):
    """A repeated query, or a leader answering beside its follower: what is kept of a motor's answers is refused
    exactly when one of them alone would be — a bad answer is never hidden by a good one."""
    from hardware.piper.firmware_limits import LimitAnswers

    lower, upper = np.array(allowed).T
    kept = LimitAnswers()
    verdicts = []
    for answer in answers:
        for motor, (lo, hi) in enumerate(answer, start=1):
            kept.update(codec.MotorLimitFeedback(motor, hi, lo, 3.0))
        alone = FirmwareLimits([lo for lo, _ in answer], [hi for _, hi in answer], np.full(6, 3.0))
        verdicts.append(firmware_limits_problem(alone, lower, upper) is None)
    assert (firmware_limits_problem(kept.limits("the arm on can0", "can0"), lower, upper) is None) == all(verdicts)


def test_a_robot_without_limits_of_its_own_passes_unasked():
    from hardware.ideal_robot import IdealRobot

    clock = FakeClock()
    Rig(None, IdealRobot(piper_description(1), np.zeros(7), clock), np.eye(4), clock=clock).check_firmware_limits()
    assert clock.now() == 0.0  # nothing waited for


def test_the_factory_table_holds_the_nominal_limits():
    assert firmware_limits_problem(FACTORY, JOINT_LOWER, JOINT_UPPER) is None
    assert np.all(FACTORY.lower <= JOINT_LOWER) and np.all(FACTORY.upper >= JOINT_UPPER)


# ---- the wait, on the rig's clock ---------------------------------------------------------------------------------
class QuietArm(Robot):
    """An arm that sends feedback but never answers the limit query; enabling it would be a bug."""

    dof = 7
    description = property(lambda self: piper_description(1))
    connect = close = emergency_stop = disable = lambda self: None

    def __init__(self):
        self.queries = []

    def state(self):
        return None

    def enable(self, timeout=2.0):
        raise AssertionError("an arm whose limits are unknown was enabled")

    def command(self, target):
        raise AssertionError("an arm whose limits are unknown was commanded")

    def query_firmware_limits(self):
        self.queries.append(self.clock.now())

    def firmware_limits(self):
        return (FirmwareLimits(np.full(6, np.nan), np.full(6, np.nan), np.full(6, np.nan), arm="the arm on can0"),)


def test_an_unanswered_query_is_refused_after_its_timeout_on_the_rigs_clock():
    """Asked every 0.1 s, given up after 1 s of the rig's clock: on a manual clock no wall time passes, and the
    refusal names the arm, the joints and what to do. A stop request ends the wait at once, refusing nothing."""
    import hardware.rig as rig_module

    clock, arm = FakeClock(start=100.0), QuietArm()
    arm.clock = clock
    rig = Rig(None, arm, np.eye(4), SafetyConfig(), clock=clock)
    with pytest.raises(
        ArmError,
        match=r"^the arm on can0 did not answer the joint-limit query \(0x472\) for "
        r"J1,J2,J3,J4,J5,J6 within 1 s.*start again$",
    ):
        rig.check_firmware_limits()
    assert 101.0 < clock.now() <= 101.005 + 1e-9 and rig_module.LIMIT_QUERY_TIMEOUT == 1.0
    np.testing.assert_allclose(np.diff(arm.queries), 0.1, atol=0.0051)
    assert len(arm.queries) == 10
    arm.queries.clear()
    rig.check_firmware_limits(stopped=lambda: True)
    assert arm.queries == []


def test_the_limits_checked_are_the_rigs_less_the_safety_margin():
    """The range the firmware must hold is what the safety layer lets the policy command: a firmware J1 of
    +-149 deg is refused under the nominal +-150 deg, and accepted with a 0.05 rad margin or narrower rig limits."""

    class Reporting(QuietArm):
        def firmware_limits(self):
            reported = with_joint(0, -149.0, 149.0)
            return (FirmwareLimits(reported.lower, reported.upper, reported.max_speed, arm="the arm on can0"),)

    clock = FakeClock()
    arm = Reporting()
    arm.clock = clock
    with pytest.raises(ArmError, match=r"J1 to -149.0..149.0 deg \(narrower\).*-150.0..150.0 deg"):
        Rig(None, arm, np.eye(4), SafetyConfig(), clock=clock).check_firmware_limits()
    Rig(None, arm, np.eye(4), SafetyConfig(limit_margin=0.05), clock=clock).check_firmware_limits()
    described = piper_description(1)
    lower, upper = described.lower.copy(), described.upper.copy()
    lower[0], upper[0] = -2.5, 2.5
    narrowed = Rig(None, arm, np.eye(4), SafetyConfig(), clock=clock, limits=(lower, upper, described.gripper))
    narrowed.check_firmware_limits()
    assert arm.queries == []  # every joint had answered: nothing was asked


# ---- the commands ---------------------------------------------------------------------------------------------------
def simulated_arms(monkeypatch, kind: str | None) -> None:
    """``--can sim`` builds simulated arms with the firmware limits of ``kind`` (None: the factory table)."""
    if kind is None:
        return
    limits = CORRUPTED[kind][0]
    options = {"answers_limit_query": False} if limits is None else {"firmware_limits": limits}
    monkeypatch.setattr(piper_robot, "SimulatedPiper", functools.partial(SimulatedPiper, **options))
    if kind == "silent":
        monkeypatch.setattr("hardware.rig.LIMIT_QUERY_TIMEOUT", 0.05)  # the simulated arm answers in microseconds


def bus_ids(log_dir) -> list[int]:
    (blf,) = log_dir.glob("can_*.blf")
    return [frame.arbitration_id for frame in read_log(blf)]


@pytest.mark.parametrize("kind", list(CORRUPTED))
def test_dssp_run_refuses_corrupted_firmware_limits_before_enabling(kind, tmp_path, capsys, monkeypatch):
    from hardware.cli.run import main as run_main

    simulated_arms(monkeypatch, kind)
    log_dir = tmp_path / "log"
    code = run_main(
        [
            "--policy",
            "hold",
            "--camera",
            "tabletop",
            "--can",
            "sim",
            "--max-steps",
            "3",
            "--quiet",
            "--log-dir",
            str(log_dir),
        ]
    )
    captured = capsys.readouterr()
    line = one_error_line(captured.err)
    _, joint, words = CORRUPTED[kind]
    assert code == 2 and line.startswith("error: the arm on dssp-sim-") and words in line, line
    assert joint in line and "start again" in line
    if kind != "silent":
        assert f"{joint} to " in line and "the safety settings let the policy command" in line
        assert f"MotorAngleLimitMaxSpdSet(motor_num={joint[1]}" in line
    ids = bus_ids(log_dir)
    assert not MOTION_IDS & set(ids), [hex(i) for i in ids]  # nothing enabled, nothing commanded
    assert ids.count(codec.MOTOR_LIMIT_QUERY) >= 6
    assert ids.count(codec.MOTOR_LIMIT_FEEDBACK) == (0 if kind == "silent" else 6)


def test_dssp_run_with_healthy_limits_reads_them_then_enables(tmp_path, capsys):
    from hardware.cli.run import main as run_main

    code = run_main(
        [
            "--policy",
            "hold",
            "--camera",
            "tabletop",
            "--can",
            "sim",
            "--max-steps",
            "3",
            "--quiet",
            "--log-dir",
            str(tmp_path / "log"),
        ]
    )
    assert code == 0, capsys.readouterr()
    ids = bus_ids(tmp_path / "log")
    enabled = ids.index(codec.MOTOR_ENABLE)
    assert ids[:enabled].count(codec.MOTOR_LIMIT_QUERY) == 6 and ids[:enabled].count(codec.MOTOR_LIMIT_FEEDBACK) == 6
    assert codec.MOTOR_LIMIT_QUERY not in ids[enabled:]  # asked once, before enabling


def test_a_dry_run_sends_nothing_not_even_the_query(tmp_path, capsys, monkeypatch):
    from hardware.cli.run import main as run_main

    simulated_arms(monkeypatch, "empty")  # a dry run enables nothing: the limits are not its to judge
    code = run_main(
        [
            "--policy",
            "hold",
            "--camera",
            "tabletop",
            "--can",
            "sim",
            "--max-steps",
            "3",
            "--quiet",
            "--dry-run",
            "--log-dir",
            str(tmp_path / "log"),
        ]
    )
    assert code == 0, capsys.readouterr()
    ids = bus_ids(tmp_path / "log")
    assert codec.MOTOR_LIMIT_QUERY not in ids and not MOTION_IDS & set(ids)


@pytest.mark.parametrize("kind", list(CORRUPTED))
def test_dssp_record_refuses_a_follower_with_corrupted_limits_before_recording(kind, tmp_path, capsys, monkeypatch):
    """The recorder's one frame is the query: a follower with bad limits, or none, is refused before the dataset is
    written, and nothing else went out on the bus."""
    from hardware.cli.record import main as record_main

    limits = CORRUPTED[kind][0]
    name = channel("rec")
    follower = SimulatedPiper(name, "virtual", firmware_limits=limits, answers_limit_query=limits is not None)
    if kind == "silent":
        monkeypatch.setattr("hardware.rig.LIMIT_QUERY_TIMEOUT", 0.05)
    heard = can.Bus(interface="virtual", channel=name)
    follower.start()
    try:
        code = record_main(
            [
                "--camera",
                "tabletop",
                "--can",
                name,
                "--interface",
                "virtual",
                "--out",
                str(tmp_path / "demo.zarr"),
                "--quiet",
            ]
        )
    finally:
        follower.stop()
    sent = []
    while (frame := heard.recv(timeout=0)) is not None:
        sent.append(frame.arbitration_id)
    heard.shutdown()
    line = one_error_line(capsys.readouterr().err)
    _, joint, words = CORRUPTED[kind]
    assert code == 2 and line.startswith(f"error: the arm on {name}") and words in line and joint in line, line
    assert not (tmp_path / "demo.zarr").exists() and not (tmp_path / "demo.zarr.can").exists()
    assert not MOTION_IDS & set(sent) and sent.count(codec.MOTOR_LIMIT_QUERY) >= 6
    assert follower.commands_received == 0

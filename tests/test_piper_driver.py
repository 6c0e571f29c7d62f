"""PiperArm / PiperRobot against SimulatedPiper on in-process virtual CAN buses (one fresh channel per test).

Most tests drive the simulator deterministically (``start(thread=False)`` + ``step(dt)``) so joint motion is
exact; the driver's receive thread still runs, so reads of its feedback wait (bounded) for the frames.
"""

import json
from concurrent.futures import ThreadPoolExecutor
from concurrent.futures import TimeoutError as FutureTimeout

import can
import numpy as np
import pytest
from conftest import MDEG, UM, channel
from waiting import wait_for

from dssp_core.errors import ArmError, CanError
from dssp_data.observation import piper_layout
from hardware.clock import FakeClock
from hardware.piper import codec
from hardware.piper.arm import PiperArm
from hardware.piper.bus import open_bus
from hardware.piper.can_simulator import SimulatedPiper
from hardware.piper.limits import GRIPPER_STROKE_MAX, JOINT_LOWER, JOINT_UPPER
from hardware.piper.piper_robot import PiperRobot, open_robot
from hardware.robot import RobotDescription


def synced(arm: PiperArm, sim: SimulatedPiper) -> None:
    """Wait until the driver's joint and gripper feedback equal the simulator's state."""

    def same():
        fb = arm.feedback()
        return (
            fb.joints is not None
            and fb.gripper is not None
            and np.allclose(fb.joints, sim.joints, atol=MDEG)
            and abs(fb.gripper.stroke - sim.gripper_stroke) <= UM
        )

    wait_for(same, what="feedback equal to the simulator")


def step_while(sims, future, dt: float = 0.0):
    """Step deterministic simulators until a background call finishes; return its result (or raise its error)."""
    while True:
        for sim in sims:
            sim.step(dt)
        try:
            return future.result(timeout=0.002)  # the call's end, or the next round of steps
        except FutureTimeout:
            pass


def drained(arm: PiperArm, raw: can.BusABC) -> None:
    """Wait until the driver has handled every frame sent before this call: a marker frame of an unknown ID
    goes out last on the virtual bus (which keeps the order of sends) and is counted once it is read."""
    before = arm.decoder.counts["unknown_id"]
    raw.send(can.Message(arbitration_id=0x123, data=bytes(8), is_extended_id=False))
    wait_for(lambda: arm.decoder.counts["unknown_id"] > before, what="the marker frame read")


def enable(arms, sims, timeout=3.0):
    with ThreadPoolExecutor(len(arms)) as pool:
        futures = [pool.submit(arm.enable, timeout) for arm in arms]
        for f in futures:
            step_while(sims, f)


@pytest.fixture
def rig():
    """A deterministic simulator (2 rad/s at 100 %) and a connected driver on one virtual channel."""
    ch = channel("rig")
    sim = SimulatedPiper(ch, "virtual", max_joint_speed=2.0, gripper_speed=0.1)
    sim.start(thread=False)
    arm = PiperArm(ch, "virtual")
    arm.connect()
    yield sim, arm
    arm.close()
    sim.stop()


def status_after_step(arm, sim, predicate):
    sim.step(0.0)
    return wait_for(lambda: (lambda s: s if predicate(s) else None)(arm.status()), what="status")


# ---- enable -----------------------------------------------------------------------------------------------
def test_enable_is_confirmed_from_feedback(rig):
    sim, arm = rig
    sim.step(0.0)
    wait_for(lambda: arm.feedback().status is not None)
    assert not arm.status().enabled and not sim.enabled
    enable([arm], [sim])
    assert sim.enabled
    fb = arm.feedback()
    assert fb.drivers_enabled and fb.gripper.enabled
    st = status_after_step(arm, sim, lambda s: s.enabled)
    assert not st.error and not st.estop and st.detail == ""


def test_enable_times_out_without_an_arm():
    clock = FakeClock()
    arm = PiperArm(channel("nobody"), "virtual", clock=clock)
    arm.connect()
    try:
        with pytest.raises(ArmError, match=r"did not confirm enable within 0\.3 s \(no driver or gripper feedback"):
            arm.enable(0.3)
        assert 0.3 <= clock.now() < 0.31  # it waited on the arm's clock, and no longer than asked
    finally:
        arm.close()


def test_enable_times_out_when_the_arm_stays_silent():
    ch = channel("silent")
    sim = SimulatedPiper(ch, "virtual")
    sim.start()
    arm = PiperArm(ch, "virtual")
    arm.connect()
    try:
        wait_for(lambda: arm.feedback().status is not None)
        sim.pause_feedback()
        with pytest.raises(ArmError) as info:
            arm.enable(0.3)
        assert "\n" not in str(info.value) and "retry" in str(info.value)
        assert sim.enabled  # the request arrived; only the confirmation is missing
    finally:
        arm.close()
        sim.stop()


# ---- motion ------------------------------------------------------------------------------------------------
def test_targets_are_tracked_at_the_speed_limit(rig):
    sim, arm = rig
    enable([arm], [sim])
    target = np.array([1.0, 0.05, -1.0, 0.0, 0.3, -0.02])
    arm.command_joints(target)
    sim.step(0.1)
    np.testing.assert_array_equal(sim.joints, np.zeros(6))  # standby mode: no motion yet

    arm.set_joint_mode(50)  # 2 rad/s * 50 % = 1 rad/s -> 0.1 rad per 0.1 s
    sim.step(0.1)
    np.testing.assert_allclose(sim.joints, [0.1, 0.05, -0.1, 0.0, 0.1, -0.02], atol=MDEG)
    sim.step(0.1)
    np.testing.assert_allclose(sim.joints, [0.2, 0.05, -0.2, 0.0, 0.2, -0.02], atol=MDEG)
    synced(arm, sim)
    assert arm.feedback().status.motion_status == 1  # not reached
    arm.set_joint_mode(100)  # 0.2 rad per 0.1 s
    sim.step(0.1)
    np.testing.assert_allclose(sim.joints, [0.4, 0.05, -0.4, 0.0, 0.3, -0.02], atol=MDEG)
    for _ in range(5):
        sim.step(0.1)
    np.testing.assert_allclose(sim.joints, target, atol=MDEG)
    synced(arm, sim)
    np.testing.assert_allclose(arm.feedback().joints, target, atol=MDEG)
    assert arm.feedback().status.motion_status == 0 and arm.feedback().status.ctrl_mode == 1

    arm.command_gripper(0.05, 2.0)  # 0.1 m/s
    sim.step(0.2)
    assert sim.gripper_stroke == pytest.approx(0.02, abs=1e-12)
    sim.step(0.5)
    synced(arm, sim)
    assert arm.feedback().gripper.stroke == pytest.approx(0.05, abs=UM)
    assert arm.feedback().gripper.effort == pytest.approx(2.0)


def test_only_joint_move_mode_moves(rig):
    sim, arm = rig
    enable([arm], [sim])
    with can.Bus(interface="virtual", channel=arm.channel) as raw:  # CAN mode, but MOVE P (Cartesian)
        raw.send(codec.MotionCtrl2(codec.CTRL_MODE_CAN, codec.MOVE_MODE_P, 100).to_frame())
    arm.command_joints(np.array([0.1, 0.1, -0.1, 0.1, 0.1, 0.1]))
    sim.step(0.5)
    np.testing.assert_array_equal(sim.joints, np.zeros(6))
    assert sim.mode == (1, 0, 100)


def test_targets_beyond_the_limits_are_clamped_and_flagged(rig):
    sim, arm = rig
    enable([arm], [sim])
    arm.set_joint_mode(100)
    arm.command_joints(np.array([3.0, 0.1, 0.5, 0.0, 0.0, 0.0]))  # J1 > 2.6179, J3 > 0
    sim.step(0.0)
    assert sim.joint_targets[0] == JOINT_UPPER[0] and sim.joint_targets[2] == 0.0
    for _ in range(4):
        sim.step(0.5)
    assert sim.joints[0] == JOINT_UPPER[0] and sim.joints[2] == 0.0
    st = status_after_step(arm, sim, lambda s: s.error)
    assert "joint limit J1,J3" in st.detail and "beyond joint limit" in st.detail
    fb = arm.feedback()
    assert fb.status.arm_status == 0x04 and fb.status.joint_limit_bits == 0b101
    assert fb.joints[0] == pytest.approx(JOINT_UPPER[0], abs=MDEG)

    arm.command_joints(np.array([2.0, 0.1, -0.5, 0.0, 0.0, 0.0]))
    st = status_after_step(arm, sim, lambda s: not s.error)
    assert st.enabled and st.detail == ""

    # Targets exactly at the limits (rounded on the wire by up to half a unit beyond them) are not flagged.
    at_limits = np.where(np.arange(6) % 2 == 0, JOINT_UPPER, JOINT_LOWER)
    arm.command_joints(at_limits)
    sim.step(0.0)
    assert sim.error_code == 0 and sim.arm_status == 0
    np.testing.assert_allclose(sim.joint_targets, at_limits, atol=MDEG)


def test_emergency_stop_holds_and_resume_needs_enable(rig):
    sim, arm = rig
    enable([arm], [sim])
    arm.set_joint_mode(50)
    arm.command_joints(np.array([1.0, 0, 0, 0, 0, 0]))
    sim.step(0.1)
    arm.emergency_stop()
    sim.step(0.1)
    assert sim.estop and sim.joints[0] == pytest.approx(0.1)
    st = status_after_step(arm, sim, lambda s: s.estop)
    assert "emergency stop" in st.detail and not st.error
    arm.command_joints(np.array([-1.0, 0, 0, 0, 0, 0]))
    sim.step(0.5)
    assert sim.joints[0] == pytest.approx(0.1)  # still holding

    arm.resume()
    st = status_after_step(arm, sim, lambda s: not s.estop and not s.enabled)
    assert not st.error and not sim.enabled  # the reset leaves the motors unpowered
    enable([arm], [sim])
    arm.set_joint_mode(50)
    arm.command_joints(np.array([0.0, 0, 0, 0, 0, 0]))
    sim.step(0.05)
    assert sim.joints[0] == pytest.approx(0.05)


def test_error_bits_appear_in_status_and_stop_motion(rig):
    sim, arm = rig
    enable([arm], [sim])
    arm.set_joint_mode(100)
    sim.raise_error(1 << 2)  # J3 communication error
    arm.command_joints(np.array([0.5, 0, 0, 0, 0, 0]))
    sim.step(0.1)
    assert sim.joints[0] == 0.0
    st = status_after_step(arm, sim, lambda s: s.error)
    assert "communication error J3" in st.detail and "joint communication error" in st.detail
    sim.clear_error()
    arm.command_joints(np.array([0.5, 0, 0, 0, 0, 0]))
    sim.step(0.1)
    assert sim.joints[0] == pytest.approx(0.2)
    assert not status_after_step(arm, sim, lambda s: not s.error).error


# ---- feedback and timestamps ------------------------------------------------------------------------------
def test_feedback_timestamps_are_arrival_times_and_state_uses_the_oldest():
    ch = channel("stamps")
    clock = FakeClock(start=100.0)
    sim = SimulatedPiper(ch, "virtual")
    sim.start(thread=False)
    arm = PiperArm(ch, "virtual", clock=clock)
    arm.connect()
    robot = PiperRobot([arm])
    try:
        assert robot.state() is None
        sim.step(0.0)
        state = wait_for(robot.state)
        fb = arm.feedback()
        assert fb.joints_time == fb.gripper_time == 100.0  # stamped on the arm's clock when they arrived
        assert state.timestamp == 100.0

        # Fresh joint frames only, 0.25 s later: the state's time stays at the older gripper frame.
        clock.advance(0.25)
        with can.Bus(interface="virtual", channel=ch) as raw:
            for i in range(3):
                raw.send(codec.JointFeedback(i, 0.0, 0.0).to_frame())
            drained(arm, raw)
        fb2 = arm.feedback()
        assert fb2.joints_time == 100.25 and fb2.gripper_time == 100.0
        assert robot.state().timestamp == 100.0
    finally:
        arm.close()
        sim.stop()


def test_state_needs_all_joint_frames_and_the_gripper():
    ch = channel("parts")
    arm = PiperArm(ch, "virtual")
    arm.connect()
    robot = PiperRobot([arm])
    try:
        with can.Bus(interface="virtual", channel=ch) as raw:
            raw.send(codec.JointFeedback(0, 0.1, 0.2).to_frame())
            raw.send(codec.JointFeedback(1, -0.3, 0.4).to_frame())
            raw.send(codec.GripperFeedback(0.035).to_frame())
            wait_for(lambda: arm.feedback().gripper is not None)
            assert arm.feedback().joints is None and robot.state() is None
            raw.send(codec.JointFeedback(2, 0.5, -0.6).to_frame())
            state = wait_for(robot.state)
            np.testing.assert_allclose(state.position, [0.1, 0.2, -0.3, 0.4, 0.5, -0.6, 0.5], atol=MDEG)
            assert state.status[0].error and "0x2A1" in state.status[0].detail  # no status frame yet
            raw.send(can.Message(arbitration_id=0x123, data=bytes(8), is_extended_id=False))
            raw.send(can.Message(arbitration_id=0x2A8, data=bytes(3), is_extended_id=False))
            wait_for(lambda: arm.decoder.counts["unknown_id"] == 1 and arm.decoder.counts["bad_dlc"] == 1)
            assert arm.feedback().gripper.stroke == pytest.approx(0.035)
    finally:
        arm.close()


def test_paused_feedback_goes_stale():
    ch = channel("stale")
    sim = SimulatedPiper(ch, "virtual")
    sim.start()
    clock = FakeClock()
    arm = PiperArm(ch, "virtual", stale_after=0.1, clock=clock)
    arm.connect()
    try:
        wait_for(lambda: arm.feedback().status is not None)
        assert not arm.status().error
        sim.pause_feedback()
        with can.Bus(interface="virtual", channel=ch) as raw:
            drained(arm, raw)  # what the simulator sent before the pause has arrived
            t_paused = arm.feedback().status_time
            assert not arm.status().error  # 0 s old
            clock.advance(0.2)
            drained(arm, raw)  # nothing more came while paused
        assert arm.feedback().status_time == t_paused
        st = arm.status()
        assert st.error and "no status frame for 0.20 s" in st.detail
        sim.resume_feedback()
        wait_for(lambda: arm.feedback().status_time > t_paused)
        assert not arm.status().error
    finally:
        arm.close()
        sim.stop()


# ---- errors -------------------------------------------------------------------------------------------------
def test_send_failures_raise_can_error():
    ch = channel("sendfail")
    arm = PiperArm(ch, "virtual", send_timeout=0.02)
    with pytest.raises(CanError, match="not connected"):
        arm.emergency_stop()
    blocker = can.Bus(interface="virtual", channel=ch, rx_queue_size=1)  # a listener that never reads
    arm.connect()
    try:
        arm.emergency_stop()  # fills the listener's queue
        with pytest.raises(CanError, match=r"sending frame 0x150 .* failed") as info:
            arm.emergency_stop()
        assert "\n" not in str(info.value)
        with pytest.raises(CanError, match="0x155"):
            arm.command_joints(np.zeros(6))
    finally:
        blocker.shutdown()
        arm.close()
    with pytest.raises(CanError, match="not connected"):
        arm.command_gripper(0.01)


def test_bad_commands_raise_arm_error(rig):
    sim, arm = rig
    with pytest.raises(ArmError, match="6 finite"):
        arm.command_joints(np.array([0, 0, np.nan, 0, 0, 0]))
    with pytest.raises(ArmError, match="6 finite"):
        arm.command_joints(np.zeros(5))
    with pytest.raises(ArmError, match="cannot be encoded"):
        arm.command_joints(np.array([1e9, 0, 0, 0, 0, 0]))
    with pytest.raises(ArmError, match="gripper"):
        arm.command_gripper(float("nan"))
    with pytest.raises(ArmError, match="0..100"):
        arm.set_joint_mode(101)
    with pytest.raises(ArmError, match="14 finite"):
        PiperRobot([arm, arm]).command(np.zeros(7))


def test_open_bus_errors_are_one_line():
    for ch, interface, needle in [
        ("", "virtual", "empty"),
        ("dssp-no-such-can9", "socketcan", "ip link set"),
        ("10.1.2.3", "udp_multicast", "multicast group"),
    ]:
        with pytest.raises(CanError, match=needle) as info:
            open_bus(ch, interface)
        assert "\n" not in str(info.value)


# ---- robot --------------------------------------------------------------------------------------------------
def test_two_arms_are_fourteen_values_left_then_right():
    left_ch, right_ch = channel("left"), channel("right")
    q_left, q_right = np.array([0.1, 0.2, -0.3, 0.4, -0.5, 0.6]), np.array([-0.6, 1.5, -1.4, 0.3, 0.2, -0.1])
    sims = [
        SimulatedPiper(left_ch, initial_joints=q_left, initial_stroke=0.014),
        SimulatedPiper(right_ch, initial_joints=q_right, initial_stroke=0.056),
    ]
    arms = [PiperArm(left_ch, "virtual"), PiperArm(right_ch, "virtual")]
    robot = PiperRobot(arms, speed_percent=80, gripper_effort=1.5, simulators=sims)
    for sim in sims:
        sim.start(thread=False)  # deterministic; connect() leaves started simulators alone
    robot.connect()
    try:
        assert robot.dof == 14
        for sim in sims:
            sim.step(0.0)
        state = wait_for(robot.state)
        expected = np.concatenate([q_left, [0.2], q_right, [0.8]])
        np.testing.assert_allclose(state.position, expected, atol=MDEG)
        assert len(state.status) == 2

        enable(arms, sims)
        target = np.array([0.11, 0.21, -0.31, 0.41, -0.51, 0.61, 0.3, -0.61, 1.51, -1.41, 0.31, 0.21, -0.11, 0.9])
        robot.command(target)
        for sim in sims:
            sim.step(0.0)
        np.testing.assert_allclose(sims[0].joint_targets, target[:6], atol=MDEG)
        np.testing.assert_allclose(sims[1].joint_targets, target[7:13], atol=MDEG)
        assert sims[0].gripper_target == pytest.approx(0.3 * GRIPPER_STROKE_MAX, abs=UM)
        assert sims[1].gripper_target == pytest.approx(0.9 * GRIPPER_STROKE_MAX, abs=UM)
        assert sims[0].mode == (1, 1, 80) and sims[1].mode == (1, 1, 80)
        for sim in sims:
            sim.step(1.0)
        wait_for(lambda: np.allclose(robot.state().position, target, atol=2 * MDEG), what="both arms at target")
    finally:
        robot.close()
    assert not any(sim.started for sim in sims)


@pytest.mark.parametrize("spec, dof", [("sim", 7), ("sim:2", 14)])
def test_open_robot_sim(spec, dof):
    robot = open_robot(spec)
    assert robot.dof == dof and len(robot.simulators) == dof // 7
    with robot:
        assert all(sim.running for sim in robot.simulators)
        wait_for(robot.state)
        robot.enable(3.0)
        target = np.tile([0.2, 0.3, -0.2, 0.1, -0.1, 0.25, 0.6], dof // 7)

        def commanded_and_reached() -> bool:  # the arms' threads move them on wall time
            robot.command(target)
            return np.allclose(robot.state().position, target, atol=2 * MDEG)

        wait_for(commanded_and_reached, what="every arm at the target")
        assert all(not s.error and s.enabled for s in robot.status())
        robot.simulators[-1].raise_error(1 << 8)
        wait_for(lambda: robot.status()[-1].error)
        robot.emergency_stop()
        wait_for(lambda: all(s.estop for s in robot.status()))
    assert not any(sim.running for sim in robot.simulators)


def test_the_robot_describes_itself():
    """What the loop, the safety layer and the observation contract read from the robot, not from constants."""
    one, two = open_robot("sim").description, open_robot("sim:2").description
    assert (one.dof, one.n_arms, two.dof, two.n_arms) == (7, 1, 14, 2) and one.model == "AgileX Piper"
    assert one.names[0] == "J1 rad" and two.names[7] == "right.J1 rad" and two.names[13] == "right.gripper opening 0..1"
    assert np.flatnonzero(two.gripper).tolist() == [6, 13]
    np.testing.assert_array_equal(two.lower[:6], JOINT_LOWER)
    np.testing.assert_array_equal(two.upper[7:13], JOINT_UPPER)
    assert (two.lower[13], two.upper[13]) == (0.0, 1.0)  # the gripper's opening
    assert two.layout == piper_layout(2)  # the observation contract's layout
    assert two.max_joint_speed == pytest.approx(3.14159) and two.feedback_hz == 200.0
    with pytest.raises(ValueError):
        two.lower[0] = 0.0  # read-only
    with pytest.raises(ValueError, match="7 values"):
        RobotDescription("x", piper_layout(1), np.zeros(6), np.ones(6), np.zeros(6, bool), 1.0, 1.0)
    with pytest.raises(ValueError, match="lower <= upper"):
        RobotDescription("x", piper_layout(1), np.ones(7), np.zeros(7), np.zeros(7, bool), 1.0, 1.0)
    assert json.loads(json.dumps(two.to_dict()))["gripper"][13] is True


@pytest.mark.parametrize("spec", ["", "sim:3", "sim:0", "can0,,can1", "a,b,c", "simulator"])
def test_open_robot_rejects_bad_specs(spec):
    if spec == "simulator":  # a plain channel name: accepted as a real bus, never opened here
        assert open_robot(spec).arms[0].channel == "simulator"
        return
    with pytest.raises(ArmError, match="spec"):
        open_robot(spec)


def test_open_robot_real_bus_spec_and_connect_failure():
    robot = open_robot("dssp-no-such-can8, dssp-no-such-can9")
    assert [a.channel for a in robot.arms] == ["dssp-no-such-can8", "dssp-no-such-can9"] and robot.dof == 14
    with pytest.raises(CanError, match="dssp-no-such-can8"):
        robot.connect()

"""The official piper-sdk (AgileX) as an oracle for our frames, on in-process virtual CAN buses.

(a) The SDK listening on the bus decodes what our driver sends (mode/speed, joint targets, gripper) to the
    values we meant, and our decoder reads the SDK's command frames back to the SDK's integers.
(b) SDK commands (EnableArm, MotionCtrl_2, JointCtrl, GripperCtrl, EmergencyStop, DisableArm) drive our
    SimulatedPiper, and the SDK reads the simulator's feedback (joints, status, error bits, gripper, drivers).

The SDK keeps one interface per channel name (a singleton) and logs instead of raising on send errors, so
each test uses a fresh channel and checks effects, not return values.
"""

import math
import uuid

import can
import numpy as np
import pytest
from conftest import MDEG
from piper_sdk import C_PiperInterface_V2
from waiting import wait_for

from hardware.piper import codec
from hardware.piper.arm import PiperArm
from hardware.piper.can_simulator import SimulatedPiper
from hardware.piper.limits import JOINT_LOWER, JOINT_UPPER

# The SDK opens its bus with python-can's deprecated ``bustype=`` argument.
pytestmark = pytest.mark.filterwarnings("ignore:The 'bustype' argument is deprecated:DeprecationWarning")


@pytest.fixture
def sdk_channel():
    """A fresh virtual channel with a connected piper-sdk interface on it: (channel, sdk)."""
    name = f"sdk-{uuid.uuid4().hex[:10]}"
    sdk = C_PiperInterface_V2(name, judge_flag=False, can_auto_init=False)
    sdk.CreateCanBus(name, bustype="virtual", judge_flag=False)
    sdk.ConnectPort()
    yield name, sdk
    sdk.DisconnectPort()


def mdeg(q):
    return [round(math.degrees(v) * 1000) for v in q]


def sdk_joint_ctrl(sdk):
    j = sdk.GetArmJointCtrl().joint_ctrl
    return [j.joint_1, j.joint_2, j.joint_3, j.joint_4, j.joint_5, j.joint_6]


def sdk_joint_feedback(sdk):
    j = sdk.GetArmJointMsgs().joint_state
    return [j.joint_1, j.joint_2, j.joint_3, j.joint_4, j.joint_5, j.joint_6]


# ---- (a) our frames, the SDK's reading -----------------------------------------------------------------------
def test_sdk_decodes_the_driver_commands(sdk_channel):
    name, sdk = sdk_channel
    arm = PiperArm(name, "virtual")
    arm.connect()
    rng = np.random.default_rng(0)
    try:
        for i in range(25):
            q = rng.uniform(JOINT_LOWER, JOINT_UPPER)
            stroke = 0.001 * (i + 1) + 0.0000004  # distinct per round: tells when the SDK has read this round
            effort = round(float(rng.uniform(0, 5)), 3)
            speed = int(rng.integers(0, 101))
            arm.set_joint_mode(speed)
            arm.command_joints(q)
            arm.command_gripper(stroke, effort)
            expected_stroke = round(stroke * 1e6)
            wait_for(lambda: sdk.GetArmGripperCtrl().gripper_ctrl.grippers_angle == expected_stroke, what="SDK read")
            grip = sdk.GetArmGripperCtrl().gripper_ctrl
            assert (grip.grippers_effort, grip.status_code, grip.set_zero) == (round(effort * 1000), 1, 0)
            assert sdk_joint_ctrl(sdk) == mdeg(q)
            mode = sdk.GetArmModeCtrl().mode_ctrl
            assert (mode.ctrl_mode, mode.move_mode, mode.move_spd_rate_ctrl, mode.mit_mode) == (1, 1, speed, 0)
        # Decoded by the SDK, back in radians: within half a wire unit of what we commanded.
        np.testing.assert_allclose(np.radians(np.array(sdk_joint_ctrl(sdk)) / 1000), q, atol=MDEG / 2 + 1e-12)
    finally:
        arm.close()


def test_our_decoder_reads_the_sdk_commands(sdk_channel):
    name, sdk = sdk_channel
    decoder = codec.Decoder()
    with can.Bus(interface="virtual", channel=name) as listener:
        joints = [150000, 1, -170000, 99999, -69999, 120000]
        sdk.MotionCtrl_2(0x01, 0x01, 42, 0x00)
        sdk.JointCtrl(*joints)
        sdk.GripperCtrl(65432, 4321, 0x03, 0xAE)
        sdk.EnableArm(7)
        sdk.DisableArm(3)
        sdk.EmergencyStop(0x01)
        sdk.EmergencyStop(0x02)
        received = []
        while len(received) < 9:
            frame = listener.recv(timeout=2.0)
            assert frame is not None, f"only {len(received)} frames from the SDK"
            message = decoder.decode(frame)
            if message is not None:
                received.append(message)
    mode, j12, j34, j56, grip, enable, disable, stop, resume = received
    assert mode == codec.MotionCtrl2(1, 1, 42, 0, 0, 0)
    assert [codec.rad_to_mdeg(v) for m in (j12, j34, j56) for v in (m.first, m.second)] == joints
    assert grip == codec.GripperCtrl(0.065432, 4.321, 3, 0xAE)
    assert enable == codec.MotorEnable(7, 2) and enable.enable
    assert disable == codec.MotorEnable(3, 1) and not disable.enable
    assert stop == codec.MotionCtrl1(1) and resume == codec.MotionCtrl1(2)


# ---- (b) the SDK's commands, our simulator ----------------------------------------------------------------
def test_sdk_drives_the_simulator_and_reads_its_feedback(sdk_channel):
    name, sdk = sdk_channel
    sim = SimulatedPiper(name, "virtual", max_joint_speed=3.0)
    sim.start()
    try:
        wait_for(lambda: sdk.GetArmStatus().time_stamp > 0, what="SDK sees status")
        assert sdk.GetArmEnableStatus() == [False] * 6
        sdk.EnableArm(7)
        wait_for(lambda: sim.enabled, what="simulator enabled")
        wait_for(lambda: sdk.GetArmEnableStatus() == [True] * 6, what="SDK sees drivers enabled")

        target = [20000, 30000, -25000, 10000, -15000, 45000]  # 0.001 degree

        def commanded_and_reached() -> bool:  # the simulator's thread moves it on wall time
            sdk.MotionCtrl_2(0x01, 0x01, 100, 0x00)  # as the SDK's demos do before each joint command
            sdk.JointCtrl(*target)
            sdk.GripperCtrl(30000, 1000, 0x01, 0)
            return np.allclose(sim.joints, np.radians(np.array(target) / 1000), atol=MDEG)

        wait_for(commanded_and_reached, what="the simulator at the SDK's target")
        wait_for(lambda: sim.gripper_stroke == pytest.approx(0.03, abs=1e-9), what="gripper at 30 mm")
        wait_for(lambda: sdk_joint_feedback(sdk) == target, what="SDK reads the reached joints")
        wait_for(lambda: sdk.GetArmGripperMsgs().gripper_state.grippers_angle == 30000, what="SDK reads 30 mm")
        gripper = sdk.GetArmGripperMsgs().gripper_state
        assert gripper.foc_status.driver_enable_status and gripper.grippers_effort == 1000
        status = sdk.GetArmStatus().arm_status
        assert (status.ctrl_mode.value, status.arm_status.value, status.mode_feed.value) == (1, 0, 1)
        assert status.motion_status.value == 0 and status.err_code == 0

        # Error bits: our layout (limit bits in the high byte, comm bits in the low byte) as the SDK reads it.
        sim.raise_error((1 << 8) | (1 << 2))
        wait_for(lambda: sdk.GetArmStatus().arm_status.err_code == 0x0104, what="SDK reads error bits")
        err = sdk.GetArmStatus().arm_status.err_status
        assert err.joint_1_angle_limit and err.communication_status_joint_3
        assert not (err.joint_3_angle_limit or err.communication_status_joint_1 or err.joint_2_angle_limit)
        assert sdk.GetArmStatus().arm_status.arm_status.value == 0x05
        sim.clear_error()

        # Out-of-range target: clamped, flagged with arm status 0x04 and the J2 limit bit.
        sdk.JointCtrl(20000, 190000, -25000, 10000, -15000, 45000)
        wait_for(lambda: sdk.GetArmStatus().arm_status.err_status.joint_2_angle_limit, what="J2 limit flag")
        assert sdk.GetArmStatus().arm_status.arm_status.value == 0x04
        assert sim.joint_targets[1] == JOINT_UPPER[1]

        sdk.EmergencyStop(0x01)
        wait_for(lambda: sdk.GetArmStatus().arm_status.arm_status.value == 0x01, what="SDK reads e-stop")
        held = sim.joints
        read = sim.decoder.counts["decoded"]
        for _ in range(10):
            sdk.JointCtrl(0, 0, 0, 0, 0, 0)  # three frames each
        wait_for(lambda: sim.decoder.counts["decoded"] >= read + 30, what="the simulator read the commands")
        stamp = sdk.GetArmStatus().time_stamp
        wait_for(lambda: sdk.GetArmStatus().time_stamp > stamp, what="a feedback round after them")
        np.testing.assert_array_equal(sim.joints, held)

        sdk.EmergencyStop(0x02)  # resume: a reset, motors unpowered afterwards
        wait_for(lambda: not sim.estop and not sim.enabled, what="resumed and unpowered")
        wait_for(lambda: sdk.GetArmEnableStatus() == [False] * 6, what="SDK sees drivers disabled")
        assert sdk.GetArmStatus().arm_status.arm_status.value == 0x00

        sdk.EnableArm(7)
        wait_for(lambda: sim.enabled, what="re-enabled")
        sdk.DisableArm(7)
        wait_for(lambda: not sim.enabled, what="disabled by the SDK")
    finally:
        sim.stop()

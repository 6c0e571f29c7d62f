"""Piper CAN codec: round trips of every frame, hand-computed bytes, range errors, and a fuzzed decoder."""

import math

import can
import numpy as np
import pytest
from conftest import MDEG, UM
from hypothesis import given, settings
from hypothesis import strategies as st

from hardware.piper import codec
from hardware.piper.codec import (
    ArmStatusFeedback,
    Decoder,
    GripperCtrl,
    GripperFeedback,
    JointCtrl,
    JointFeedback,
    MotionCtrl1,
    MotionCtrl2,
    MotorEnable,
    MotorHighSpeed,
    MotorLowSpeed,
)
from hardware.piper.limits import GRIPPER_STROKE_MAX, JOINT_LOWER, JOINT_UPPER, JointLimits


def roundtrip(message):
    frame = message.to_frame()
    assert frame.arbitration_id == message.ID and not frame.is_extended_id
    assert frame.dlc == 8 and len(frame.data) == 8
    decoder = Decoder()
    out = decoder.decode(frame)
    assert decoder.counts == {"decoded": 1}
    assert type(out) is type(message)
    return out


@pytest.mark.parametrize(
    "message",
    [
        MotionCtrl1(codec.ESTOP_STOP),
        MotionCtrl1(codec.ESTOP_RESUME, 3, 4),
        MotionCtrl2(1, 1, 50),
        MotionCtrl2(0, 4, 100, 0xAD, 7, 2),
        MotorEnable(7, 2),
        MotorEnable(3, 1),
        MotorEnable(0xFF, 2),
        ArmStatusFeedback(1, 4, 1, 0, 1, 9, 0x3F2A),
        ArmStatusFeedback(),
        MotorHighSpeed(6, speed=-1.234, current=2.5, position=-123456),
        MotorLowSpeed(1, voltage=24.6, driver_temp=-5, motor_temp=-40, status=0x40, bus_current=1.25),
        MotorLowSpeed(6, voltage=0.0, driver_temp=120, motor_temp=127, status=0xFF, bus_current=65.535),
    ],
)
def test_exact_roundtrip_of_integer_and_fixed_point_frames(message):
    assert roundtrip(message) == message


@pytest.mark.parametrize("pair", [0, 1, 2])
def test_joint_frames_roundtrip_within_one_wire_unit(pair):
    for cls, ids in ((JointCtrl, codec.JOINT_CTRL_IDS), (JointFeedback, codec.JOINT_FEEDBACK_IDS)):
        message = cls(pair, JOINT_LOWER[2 * pair] + 0.123456, JOINT_UPPER[2 * pair + 1] - 0.654321)
        out = roundtrip(message)
        assert out.ID == ids[pair] and out.pair == pair
        assert abs(out.first - message.first) <= MDEG / 2 and abs(out.second - message.second) <= MDEG / 2


def test_gripper_frames_roundtrip():
    out = roundtrip(GripperCtrl(0.0421234, 2.5, codec.GRIPPER_ENABLE_CLEAR, codec.GRIPPER_SET_ZERO))
    assert abs(out.stroke - 0.0421234) <= UM / 2 and out.effort == 2.5
    assert (out.code, out.set_zero) == (3, 0xAE)
    fb = roundtrip(GripperFeedback(0.0699996, -0.75, 0xC0))
    assert abs(fb.stroke - 0.0699996) <= UM / 2 and fb.effort == -0.75 and fb.enabled and fb.status == 0xC0
    assert not GripperFeedback(0.01, 0.0, 0x80).enabled


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(-100.0, 100.0, allow_nan=False), min_size=6, max_size=6))
def test_joint_targets_roundtrip_any_angle(q):
    frames = codec.joint_ctrl_frames(np.array(q))
    assert [f.arbitration_id for f in frames] == [0x155, 0x156, 0x157]
    decoder = Decoder()
    decoded = [decoder.decode(f) for f in frames]
    back = np.array([v for m in decoded for v in (m.first, m.second)])
    np.testing.assert_allclose(back, q, rtol=0, atol=MDEG / 2 + 1e-12)


# ---- hand-computed bytes -------------------------------------------------------------------------------------
def test_joint_target_bytes():
    # 90 deg = 90000 = 0x00015F90; -45 deg = -45000 = 0xFFFF5038 (two's complement)
    frame = JointCtrl(0, math.radians(90), math.radians(-45)).to_frame()
    assert frame.arbitration_id == 0x155
    assert bytes(frame.data) == bytes([0x00, 0x01, 0x5F, 0x90, 0xFF, 0xFF, 0x50, 0x38])
    assert JointCtrl(2, 0.0, 0.0).to_frame().arbitration_id == 0x157


def test_command_bytes():
    # 0.05 m = 50000 um = 0x0000C350; 1 N·m = 1000 = 0x03E8; code 1 (enable)
    assert bytes(GripperCtrl(0.05, 1.0).to_frame().data) == bytes.fromhex("0000C35003E80100")
    assert bytes(MotionCtrl2(1, 1, 50).to_frame().data) == bytes.fromhex("0101320000000000")
    assert bytes(MotionCtrl1(1).to_frame().data) == bytes.fromhex("0100000000000000")
    assert bytes(MotorEnable(7, 2).to_frame().data) == bytes.fromhex("0702000000000000")
    assert MotorEnable(7, 2).to_frame().arbitration_id == 0x471


def test_feedback_bytes_decode():
    d = Decoder()
    status = d.decode(can.Message(arbitration_id=0x2A1, data=bytes.fromhex("0100010001000204"), is_extended_id=False))
    assert status == ArmStatusFeedback(ctrl_mode=1, arm_status=0, mode_feed=1, motion_status=1, error_code=0x0204)
    assert status.joint_limit_bits == 0b10 and status.comm_error_bits == 0b100  # J2 limit, J3 comm
    # 35000 um, -200 mN·m (0xFF38), status 0x40 (enabled)
    grip = d.decode(can.Message(arbitration_id=0x2A8, data=bytes.fromhex("000088B8FF384000"), is_extended_id=False))
    assert grip == GripperFeedback(0.035, -0.2, 0x40) and grip.enabled
    # 240 x 0.1 V, 30 °C, -30 °C (0xE2), status 0x40, 500 mA
    low = d.decode(can.Message(arbitration_id=0x263, data=bytes.fromhex("00F0001EE24001F4"), is_extended_id=False))
    assert low == MotorLowSpeed(3, 24.0, 30, -30, 0x40, 0.5) and low.driver_enabled
    joints = d.decode(can.Message(arbitration_id=0x2A6, data=bytes.fromhex("00015F90FFFF5038"), is_extended_id=False))
    assert joints.pair == 1 and joints.first == pytest.approx(math.radians(90), abs=1e-12)
    assert joints.second == pytest.approx(math.radians(-45), abs=1e-12)
    assert d.counts == {"decoded": 4}


# ---- range errors ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_non_finite_values_are_refused(bad):
    with pytest.raises(ValueError, match="finite"):
        JointCtrl(0, bad, 0.0).to_frame()
    with pytest.raises(ValueError, match="finite"):
        GripperCtrl(bad).to_frame()
    with pytest.raises(ValueError, match="finite"):
        GripperCtrl(0.01, bad).to_frame()
    with pytest.raises(ValueError):
        codec.joint_ctrl_frames(np.array([0, 0, bad, 0, 0, 0]))


def test_int32_overflow_is_refused_at_the_boundary():
    top = (2**31 - 1) / codec._MDEG_PER_RAD
    assert codec.rad_to_mdeg(top) == 2**31 - 1
    with pytest.raises(ValueError, match="out of range"):
        JointCtrl(1, 0.0, top + 2 * MDEG).to_frame()
    with pytest.raises(ValueError, match="out of range"):
        JointFeedback(0, -top - 2 * MDEG, 0.0).to_frame()
    with pytest.raises(ValueError, match="out of range"):
        GripperCtrl(3000.0).to_frame()  # 3e9 um > int32


def test_field_ranges_are_checked():
    with pytest.raises(ValueError, match="effort"):
        GripperCtrl(0.01, 5.001).to_frame()
    with pytest.raises(ValueError, match="effort"):
        GripperCtrl(0.01, -0.1).to_frame()
    with pytest.raises(ValueError, match="speed_percent"):
        MotionCtrl2(1, 1, 101).to_frame()
    with pytest.raises(ValueError, match="motor"):
        MotorEnable(256, 2).to_frame()
    with pytest.raises(ValueError, match="error_code"):
        ArmStatusFeedback(error_code=1 << 16).to_frame()
    with pytest.raises(ValueError, match="6 values"):
        codec.joint_ctrl_frames(np.zeros(7))


# ---- decoder ------------------------------------------------------------------------------------------------
def test_decoder_counts_each_reason():
    good = bytes(8)
    cases = [
        (can.Message(arbitration_id=0x2A1, is_error_frame=True, data=good, check=False), "error_frame"),
        (can.Message(arbitration_id=0x2A1, is_remote_frame=True, dlc=8, is_extended_id=False), "remote_frame"),
        (can.Message(arbitration_id=0x2A1, data=good, is_extended_id=True), "extended_id"),
        (can.Message(arbitration_id=0x800, data=good, is_extended_id=False, check=False), "bad_id"),
        (can.Message(arbitration_id=0x2A1, data=good, is_extended_id=False, is_fd=True), "fd_frame"),
        (can.Message(arbitration_id=0x123, data=good, is_extended_id=False), "unknown_id"),
        (can.Message(arbitration_id=0x2A5, data=bytes(7), is_extended_id=False), "bad_dlc"),
        (can.Message(arbitration_id=0x2A5, data=good, dlc=4, is_extended_id=False, check=False), "bad_dlc"),
        (can.Message(arbitration_id=0x2A5, data=bytes(12), is_extended_id=False, is_fd=False, check=False), "bad_dlc"),
    ]
    d = Decoder()
    for frame, reason in cases:
        before = d.counts[reason]
        assert d.decode(frame) is None
        assert d.counts[reason] == before + 1, reason
    assert d.counts["decoded"] == 0 and sum(d.counts.values()) == len(cases)


ALL_IDS = sorted(codec.KNOWN_IDS)


@settings(max_examples=400, deadline=None)
@given(
    arbitration_id=st.one_of(st.sampled_from(ALL_IDS), st.integers(0, 0x7FF), st.integers(0, 2**29 + 5)),
    data=st.binary(min_size=0, max_size=64),
    dlc=st.one_of(st.none(), st.integers(0, 64)),
    extended=st.booleans(),
    remote=st.booleans(),
    error=st.booleans(),
    fd=st.booleans(),
)
def test_decoder_never_raises_and_counts_every_frame(arbitration_id, data, dlc, extended, remote, error, fd):
    frame = can.Message(
        arbitration_id=arbitration_id,
        data=data,
        dlc=dlc,
        is_extended_id=extended,
        is_remote_frame=remote,
        is_error_frame=error,
        is_fd=fd,
        check=False,
    )
    d = Decoder()
    out = d.decode(frame)
    assert sum(d.counts.values()) == 1
    (reason,) = d.counts
    assert reason in Decoder.REASONS + ("decoded",)
    clean = not (extended or remote or error or fd) and arbitration_id in codec.KNOWN_IDS
    if clean and len(data) == 8 and frame.dlc == 8:
        assert reason == "decoded" and out is not None and out.ID == arbitration_id
    else:
        assert out is None and reason != "decoded"
    if not (extended or remote or error or fd) and arbitration_id <= 0x7FF and arbitration_id not in codec.KNOWN_IDS:
        assert reason == "unknown_id"


def test_decoder_accepts_frames_from_the_sdk_layout_for_every_known_id():
    d = Decoder()
    for frame_id in ALL_IDS:
        assert d.decode(can.Message(arbitration_id=frame_id, data=bytes(range(8)), is_extended_id=False)) is not None
    assert d.counts == {"decoded": len(ALL_IDS)}


# ---- limits -------------------------------------------------------------------------------------------------
def test_joint_limits_tile_and_clip():
    one = JointLimits.piper()
    assert one.dof == 7 and one.lower[6] == 0.0 and one.upper[6] == 1.0
    np.testing.assert_array_equal(one.lower[:6], JOINT_LOWER)
    two = one.tile(2)
    assert two.dof == 14 and two.n_arms == 2
    np.testing.assert_array_equal(two.upper[7:], one.upper)
    x = np.full(14, 10.0)
    clipped = two.clip(x)
    np.testing.assert_array_equal(clipped, two.upper)
    assert list(two.violations(x)) == list(range(14))
    assert list(two.violations(two.lower)) == []
    assert list(one.violations(np.array([0, 0, 0, 0, 0, 0, np.nan]))) == [6]
    with pytest.raises(ValueError):
        one.lower[0] = 1.0  # read-only
    with pytest.raises(ValueError):
        JointLimits(np.zeros(6), np.ones(6))
    assert GRIPPER_STROKE_MAX == 0.07

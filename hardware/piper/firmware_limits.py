"""The joint limits a Piper's own firmware enforces, read over CAN: the query, the answers, what to do about bad ones.

    answers = LimitAnswers()
    bus.send(*answers.query_frames())           # 0x472 content 1 for every motor that has not answered
    answers.update(message)                     # each 0x473 the receive thread decodes
    answers.limits("the arm on can0", "can0")   # a FirmwareLimits: (6,) rad, NaN where no answer came

Several answers for one motor (a repeated query; on a teleoperation bus both arms may answer) are kept as their
intersection, the range that none of them allows beyond: a bad answer is never hidden by a good one. The verdict on
the limits is the safety layer's (:func:`hardware.safety.firmware_limits_problem`), at start-up
(:meth:`hardware.rig.Rig.check_firmware_limits`).
"""

from __future__ import annotations

import math
import threading

import can
import numpy as np

from hardware.piper import codec
from hardware.piper.limits import FIRMWARE_LOWER_DEG, FIRMWARE_UPPER_DEG, N_JOINTS
from hardware.robot import FirmwareLimits


def reset_advice(channel: str, joint: int) -> str:
    """What to do about joint ``joint`` (0-based) of the arm on ``channel`` when its firmware limits are wrong."""
    lo, hi = FIRMWARE_LOWER_DEG[joint], FIRMWARE_UPPER_DEG[joint]
    return (
        f"reset J{joint + 1}'s limits to {lo:g}..{hi:g} deg with AgileX's Piper tool or piper-sdk "
        f"(C_PiperInterface_V2({channel!r}).MotorAngleLimitMaxSpdSet(motor_num={joint + 1}, "
        f"max_angle_limit={round(10 * hi)}, min_angle_limit={round(10 * lo)}), in 0.1 deg), then start again"
    )


def factory_limits(max_speed: float | np.ndarray) -> FirmwareLimits:
    """The limits a Piper's firmware holds as shipped (:data:`~hardware.piper.limits.FIRMWARE_LOWER_DEG` /
    ``UPPER_DEG``), with ``max_speed`` rad/s per joint: what a simulated arm reports unless told otherwise."""
    return FirmwareLimits(
        np.radians(FIRMWARE_LOWER_DEG),
        np.radians(FIRMWARE_UPPER_DEG),
        np.broadcast_to(np.asarray(max_speed, dtype=np.float64), (N_JOINTS,)),
        arm="the factory table",
        resolution=codec.LIMIT_RESOLUTION,
    )


class LimitAnswers:
    """The 0x473 answers heard on one bus since the last :meth:`clear` (thread-safe): per motor J1..J6 the
    intersection of its answers (lower: the largest min, upper: the smallest max, max speed: the smallest)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.clear()

    def clear(self) -> None:
        with self._lock:
            self._lower = np.full(N_JOINTS, math.nan)
            self._upper = np.full(N_JOINTS, math.nan)
            self._speed = np.full(N_JOINTS, math.nan)

    def update(self, message: codec.MotorLimitFeedback) -> None:
        """Take one answer (an answer for a motor outside 1..6 is ignored)."""
        if not 1 <= message.motor <= N_JOINTS:
            return
        j = message.motor - 1
        with self._lock:
            first = math.isnan(self._lower[j])
            self._lower[j] = message.min_angle if first else max(self._lower[j], message.min_angle)
            self._upper[j] = message.max_angle if first else min(self._upper[j], message.max_angle)
            self._speed[j] = message.max_speed if first else min(self._speed[j], message.max_speed)

    def query_frames(self) -> list[can.Message]:
        """0x472 (angle limits and max speed) for every motor that has not answered."""
        with self._lock:
            missing = np.flatnonzero(np.isnan(self._lower))
        return [codec.MotorLimitQuery(int(j) + 1, codec.QUERY_ANGLE_SPEED).to_frame() for j in missing]

    def limits(self, arm: str, channel: str) -> FirmwareLimits:
        """The answers so far as ``arm``'s FirmwareLimits (NaN where a motor has not answered); ``channel``: its bus,
        for the advice."""
        with self._lock:
            lower, upper, speed = self._lower.copy(), self._upper.copy(), self._speed.copy()
        return FirmwareLimits(
            lower,
            upper,
            speed,
            arm=arm,
            resolution=codec.LIMIT_RESOLUTION,
            advice=tuple(reset_advice(channel, j) for j in range(N_JOINTS)),
        )

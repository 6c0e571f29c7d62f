"""The safety layer between the policy and the arms: every command passes here, nothing else sends.

    safety = Safety(SafetyConfig(), lower, upper, start=robot_state.position)
    decision = safety.decide(action, now=clock.now(), camera_time=frame.timestamp,
                             state=robot.state(), deadline_missed=False)
    if decision.command is not None:
        robot.command(decision.command)       # within the limits, by construction and by a final check

Rules, in order, each tick (all positions in policy units, (dof,): per arm [J1..J6 rad, gripper 0..1]):
1. A latched fault (arm error or e-stop reported, or a stop requested) → no command at all, ever again.
2. Arm error / e-stop in the feedback → latch the fault, send nothing, report.
3. Stale or missing joint feedback, stale or missing camera frame, an inference deadline miss, no
   action, or an action with NaN/inf or the wrong shape → **hold**: resend the last safe target.
4. Otherwise the action is clipped to the joint/gripper limits, then to at most ``max_step`` away from
   the last safe target (per joint, per tick, like LeRobot's ``max_relative_target``), and becomes the
   new safe target.
The first safe target is the measured position at start, clipped to the limits. Every event (hold,
clip, refusal, fault) is recorded with its time in :attr:`Safety.events`.

The layer reads no clock: every time is passed in (``now``, ``camera_time``, ``state.timestamp``), all
seconds on the loop's clock (:mod:`hardware.clock`), so ages and event times are whatever that clock says.

Before anything is enabled, start-up reads the joint limits the arms' own firmware enforces and refuses those that
would clip or fault inside what this layer lets the policy command (:func:`allowed_range`): empty (min = max),
inverted (min > max) or narrower (:func:`firmware_limits_problem`; asked and waited for by
:meth:`hardware.rig.Rig.check_firmware_limits`).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any, ClassVar

import numpy as np

from dssp_core.errors import ConfigError
from dssp_core.schema import Settings, setting
from hardware.robot import FirmwareLimits, RobotState


@dataclass(frozen=True)
class SafetyConfig(Settings):
    """Thresholds of the safety layer (seconds, radians and gripper fraction per tick); a ``--safety`` file.

    Every field is type-checked (JSON ``"false"`` is not false) and range-checked on construction.
    ``max_joint_step`` is also checked against the arm's speed at the control rate by ``dssp-run``.
    """

    SECTION: ClassVar[str] = "safety"

    max_joint_step: float = setting(0.05, gt=0, le=0.5, unit="rad per tick")  # 0.5 rad/s at 10 Hz
    max_gripper_step: float = setting(0.2, gt=0, le=1.0, unit="of the opening per tick")
    camera_timeout: float = setting(0.25, gt=0, le=5.0, unit="s")  # an older frame is stale
    feedback_timeout: float = setting(0.1, gt=0, le=5.0, unit="s")  # older joint feedback is stale
    deadline_hold: bool = setting(True)  # hold when the policy missed the tick's deadline
    disable_on_exit: bool = setting(False)  # disable the motors after the final hold (arms without brakes drop!)
    limit_margin: float = setting(0.0, ge=0, lt=0.5, unit="rad")  # kept away from each joint limit

    def check_speed(self, control_rate_hz: float, max_joint_speed: float) -> None:
        """Refuse a per-tick joint step that, at ``control_rate_hz``, asks more than the arm's joint speed
        (``max_joint_speed`` rad/s: the robot's, ``Robot.description``)."""
        speed = self.max_joint_step * control_rate_hz
        if speed > max_joint_speed + 1e-9:
            raise ConfigError(
                f"safety.max_joint_step {self.max_joint_step:g} rad per tick at {control_rate_hz:g} Hz is {speed:.3g} rad/s, "
                f"above the arm's {max_joint_speed:g} rad/s: lower max_joint_step to at most {max_joint_speed / control_rate_hz:.4g}"
            )


def allowed_range(config: SafetyConfig, lower, upper, gripper_mask) -> tuple[np.ndarray, np.ndarray]:
    """What the safety layer lets the policy command: (lower (dof,), upper (dof,)), the limits with ``limit_margin``
    kept away from each joint's (not the gripper's)."""
    gripper = np.asarray(gripper_mask, bool)
    margin = np.where(gripper, 0.0, config.limit_margin)
    return np.asarray(lower, np.float64) + margin, np.asarray(upper, np.float64) - margin


GENERIC_ADVICE = "reset the arm's joint limits with its maker's tool, then start again"


def _deg(lo: float, hi: float) -> str:
    return f"{math.degrees(lo):.1f}..{math.degrees(hi):.1f} deg"


def firmware_limits_problem(reported: FirmwareLimits, lower, upper) -> str | None:
    """Why the joint limits ``reported`` by an arm's firmware cannot serve the range ``lower``..``upper`` ((n,) rad,
    that arm's joints in :func:`allowed_range`), as one line naming the arm, the joint, both ranges and what to do;
    None when every joint's firmware range contains it. A joint is refused whose firmware range is missing (no
    answer), empty (min = max), inverted (min > max) or narrower than the safety range by more than half the
    firmware's ``resolution`` (it would clip or fault inside what the policy may command). The first such joint
    is named."""
    lower, upper = np.asarray(lower, np.float64), np.asarray(upper, np.float64)
    if lower.shape != reported.lower.shape or upper.shape != reported.upper.shape:
        raise ValueError(f"{reported.arm}: {reported.lower.size} joints reported, the safety range has {lower.size}")
    tolerance = reported.resolution / 2
    for j in range(lower.size):
        lo, hi = float(reported.lower[j]), float(reported.upper[j])
        if not (math.isfinite(lo) and math.isfinite(hi)):
            what = "no answer"
        elif lo == hi:
            what = "empty: min = max"
        elif lo > hi:
            what = "inverted: min > max"
        elif lo > lower[j] + tolerance or hi < upper[j] - tolerance:
            what = "narrower"
        else:
            continue
        advice = reported.advice[j] if j < len(reported.advice) else GENERIC_ADVICE
        shown = "no limits" if what == "no answer" else _deg(lo, hi)
        return (
            f"{reported.arm}: its firmware limits J{j + 1} to {shown} ({what}), but the safety settings let the "
            f"policy command {_deg(lower[j], upper[j])} ({lower[j]:.4g}..{upper[j]:.4g} rad): the arm would clip "
            f"or fault inside that range; {advice}"
        )
    return None


@dataclass(frozen=True)
class SafetyEvent:
    time: float  # seconds on the loop's clock
    tick: int
    kind: str  # hold | clip | refuse | fault | stop
    detail: str

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass
class Decision:
    """What to send this tick: ``command`` (dof,) or None (send nothing), and why."""

    command: np.ndarray | None
    held: bool = False
    clipped: bool = False
    events: list[SafetyEvent] = field(default_factory=list)


class Safety:
    """Turns policy actions into commands that are always within the limits and the per-tick step.

    lower, upper: (dof,) limits in policy units; gripper_mask: (dof,) bool, True for gripper entries
    (their per-tick step is ``max_gripper_step``); start: (dof,) measured position at start.
    """

    def __init__(self, config: SafetyConfig, lower, upper, gripper_mask, start):
        self.config = config
        self.gripper = np.asarray(gripper_mask, bool)
        self.lower, self.upper = allowed_range(config, lower, upper, self.gripper)
        if (
            self.lower.shape != self.upper.shape
            or self.gripper.shape != self.lower.shape
            or np.any(self.lower > self.upper)
        ):
            raise ConfigError(
                "safety limits: lower, upper and gripper mask must have one shape and lower <= upper (minus the margin)"
            )
        self.dof = self.lower.shape[0]
        self.max_step = np.where(self.gripper, config.max_gripper_step, config.max_joint_step)
        start = np.asarray(start, np.float64)
        if start.shape != (self.dof,) or not np.all(np.isfinite(start)):
            raise ConfigError(f"safety needs a finite start position of shape ({self.dof},), got {start.shape}")
        self.last_safe = np.clip(start, self.lower, self.upper)
        outside = np.flatnonzero(np.abs(self.last_safe - start) > self.max_step)
        if outside.size:
            raise ConfigError(
                f"the robot starts outside its limits on entries {outside.tolist()} (position {np.round(start[outside], 3).tolist()}, "
                f"limits {np.round(self.lower[outside], 3).tolist()}..{np.round(self.upper[outside], 3).tolist()}): "
                "move it inside by hand first"
            )
        self.fault: str | None = None
        self.events: list[SafetyEvent] = []
        self.tick = 0

    # ------------------------------------------------------------------ decisions
    def _event(self, now: float, kind: str, detail: str, decision: Decision) -> None:
        event = SafetyEvent(now, self.tick, kind, detail)
        self.events.append(event)
        decision.events.append(event)

    def _hold(self, now: float, why: str, decision: Decision) -> Decision:
        decision.command, decision.held = self.last_safe.copy(), True
        self._event(now, "hold", why, decision)
        return decision

    def decide(
        self,
        action,
        now: float,
        camera_time: float | None,
        state: RobotState | None,
        deadline_missed: bool = False,
    ) -> Decision:
        """The command for this tick. ``action``: (dof,) policy units; times are seconds on the loop's clock."""
        decision = Decision(command=None)
        previous = self.last_safe.copy()
        try:
            if self.fault is not None:
                return decision
            if state is not None:
                bad = [
                    f"arm {i}: {s.detail or ('e-stop' if s.estop else 'error')}"
                    for i, s in enumerate(state.status)
                    if s.estop or s.error
                ]
                if bad:
                    self.fault = "; ".join(bad)
                    self._event(now, "fault", f"{self.fault}: commands stopped", decision)
                    return decision
            if deadline_missed and self.config.deadline_hold:  # first: it also makes the inputs look stale
                return self._hold(now, "inference missed the tick's deadline", decision)
            if state is None:
                return self._hold(now, "no joint feedback yet", decision)
            age = now - state.timestamp
            if age > self.config.feedback_timeout:
                return self._hold(
                    now,
                    f"joint feedback is {1e3 * age:.0f} ms old (> {1e3 * self.config.feedback_timeout:.0f} ms)",
                    decision,
                )
            if camera_time is None:
                return self._hold(now, "no camera frame", decision)
            age = now - camera_time
            if age > self.config.camera_timeout:
                return self._hold(
                    now,
                    f"camera frame is {1e3 * age:.0f} ms old (> {1e3 * self.config.camera_timeout:.0f} ms)",
                    decision,
                )
            if action is None:
                return self._hold(now, "no action this tick", decision)
            try:
                target = np.asarray(action, np.float64).reshape(-1)
            except (TypeError, ValueError):
                return self._refuse(now, "an action that is not numeric", decision)
            if target.shape != (self.dof,):
                return self._refuse(now, f"an action of {target.size} values (the robot takes {self.dof})", decision)
            if not np.all(np.isfinite(target)):
                return self._refuse(now, "an action with NaN/inf", decision)
            limited = np.clip(target, self.lower, self.upper)
            stepped = np.clip(limited, self.last_safe - self.max_step, self.last_safe + self.max_step)
            if np.any(limited != target):
                self._event(now, "clip", f"joint limits on {np.flatnonzero(limited != target).tolist()}", decision)
            if np.any(stepped != limited):
                self._event(now, "clip", f"per-tick step on {np.flatnonzero(stepped != limited).tolist()}", decision)
            decision.clipped = bool(decision.events)
            self.last_safe = stepped
            decision.command = stepped.copy()
            return decision
        finally:
            if decision.command is not None:
                self.check(decision.command, previous)
            self.tick += 1

    def _refuse(self, now: float, what: str, decision: Decision) -> Decision:
        self._event(now, "refuse", f"refused {what}", decision)
        return self._hold(now, "after a refused action", decision)

    def stop(self, now: float, why: str) -> Decision:
        """Latch a stop (signal, error): returns the final hold; nothing is commanded after it."""
        decision = Decision(command=None)
        if self.fault is None:
            self._hold(now, f"final hold: {why}", decision)
            self.fault = why
            self._event(now, "stop", why, decision)
        return decision

    # ------------------------------------------------------------------ the last line
    def check(self, command: np.ndarray, previous: np.ndarray) -> None:
        """Raise if a command breaks a limit or the per-tick step (a bug, never a policy output).

        The run loop treats this as a fault: it stops commanding and ends in a hold.
        """
        if command.shape != (self.dof,) or not np.all(np.isfinite(command)):
            raise SafetyViolation("a non-finite or mis-shaped command reached the final check")
        if np.any(command < self.lower - 1e-12) or np.any(command > self.upper + 1e-12):
            raise SafetyViolation("a command outside the limits reached the final check")
        if np.any(np.abs(command - previous) > self.max_step + 1e-12):
            raise SafetyViolation("a command beyond the per-tick step reached the final check")


class SafetyViolation(RuntimeError):
    """A command that the rules should have made impossible: a bug; nothing is sent."""

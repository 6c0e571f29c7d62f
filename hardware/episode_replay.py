"""Replay one episode's actions on the arms through the safety layer, to check a recording before training.

    result = replay_episode("demo.zarr", 3, "can0", send=False)   # dry run: nothing is sent

Every recorded action (dof,) in policy units goes through :class:`~hardware.safety.Safety` exactly as in
``dssp-run`` (joint limits, per-tick step, stale feedback holds), at the dataset's control rate. A dry run
(the default) reads the arm's feedback (if ``can`` is given) but neither enables nor commands it: it
reports what the safety layer would do, starting from where the arm is. With ``send`` the arm is enabled
and commanded, paced at the rate, and ends in a hold at the last command. Without ``can`` the dry run
starts from the episode's first recorded state and assumes ideal tracking.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable

import numpy as np

from dssp_data.replay_buffer import ReplayBufferReader
from dssp_core.errors import ConfigError, DSSPError
from hardware.clock import REAL_CLOCK, Clock
from hardware.pacing import Pacer
from hardware.robot import ARM_DOF, RobotState, check_rate
from hardware.piper.limits import piper_description
from hardware.safety import Safety, SafetyConfig

FAR_START = 0.3
"""rad: a first action farther than this from the arm's position is pointed out (the safety layer ramps it)."""


def replay_episode(path, episode: int, can: str | None, *, send: bool = False, interface: str = "socketcan",
                   rate_hz: float | None = None, safety_config: SafetyConfig = SafetyConfig(),
                   events: Callable[[str], None] = print, should_stop: Callable[[], bool] = lambda: False,
                   feedback_timeout: float = 3.0, clock: Clock = REAL_CLOCK) -> dict:
    """Replay ``episode`` of dataset ``path``; returns a summary dict (ticks, commands sent, clips, holds,
    largest change the safety layer made, final tracking error when sent). ``clock``: the timeline of the pacing,
    the feedback wait and the safety layer's times (:mod:`hardware.clock`), the one the arms stamp their feedback
    on."""
    reader = ReplayBufferReader(path)
    ep = reader.episode(episode, extras=False)
    actions = ep.action.astype(np.float64)
    dof = actions.shape[1]
    if dof % ARM_DOF:
        raise DSSPError(f"{path}: actions have {dof} values; a Piper replay needs 7 per arm [J1..J6 rad, gripper 0..1]")
    if rate_hz is not None:
        rate = check_rate(rate_hz)
    else:
        rate = reader.control_rate_hz  # a value that is not a rate: a DatasetError naming the attribute
        if rate is None:
            raise ConfigError(f"{path} does not record its control rate: pass --rate HZ")
        rate = check_rate(rate, flag=f"{path}'s control_rate_hz attribute")
    if send and can is None:
        raise ConfigError("--send needs --can (the arms to command)")
    robot = None
    if can is not None:
        from hardware.piper.piper_robot import open_robot

        robot = open_robot(can, interface=interface)
        if robot.dof != dof:
            raise ConfigError(f"the episode has {dof} action values but --can {can} gives {robot.dof} (7 per arm)")
    described = robot.description if robot is not None else piper_description(dof // ARM_DOF)  # no arms: a Piper's
    safety_config.check_speed(float(rate), described.max_joint_speed)
    counts: Counter = Counter()
    changed = 0.0
    sent = 0
    tracking = None
    stopped = None
    try:
        if robot is not None:
            robot.connect()
            deadline = clock.now() + feedback_timeout
            while (state := robot.state()) is None:
                if clock.now() > deadline:
                    raise DSSPError(f"no feedback from {can} within {feedback_timeout:g} s: check the bus and that the arm is powered")
                clock.sleep(0.01)
            start = state.position
            where = "the arm's position"
        else:
            start = ep.state[0].astype(np.float64) if ep.state.shape[1] == dof else actions[0]
            where = "the recorded first state"
        distance = float(np.max(np.abs(actions[0] - start)))
        if distance > FAR_START:
            events(f"note: the first action is {distance:.2f} rad from {where}: the safety layer ramps it by at most "
                   f"{safety_config.max_joint_step} rad per tick")
        safety = Safety(safety_config, described.lower, described.upper, described.gripper, start)
        if send:
            robot.enable()
        period = 1.0 / float(rate)
        pacer = Pacer(clock, period)  # a late tick starts the schedule again: no burst of commands to catch up
        last = start.copy()
        for k, action in enumerate(actions):
            if should_stop():
                stopped = "stop requested"
                break
            now = clock.now()
            if robot is not None:
                state = robot.state()
            else:
                state = RobotState(last.copy(), now, ())
            decision = safety.decide(action, now=now, camera_time=now, state=state)
            for event in decision.events:
                counts[event.kind] += 1
            if decision.command is None:
                stopped = f"safety fault: {safety.fault}"
                break
            changed = max(changed, float(np.max(np.abs(decision.command - action))))
            last = decision.command
            if send:
                robot.command(decision.command)
                sent += 1
                pacer.wait()
        final = safety.stop(clock.now(), stopped or "replay done")
        if send and final.command is not None:  # end in a hold at the last safe command
            robot.command(final.command)
        if send:
            clock.sleep(min(1.0, 5 * period))
            state = robot.state()
            if state is not None:
                tracking = float(np.max(np.abs(state.position - last)))
    finally:
        if robot is not None:
            robot.close()
    return {
        "episode": episode, "steps": len(actions), "rate_hz": float(rate), "sent": sent, "dry_run": not send,
        "holds": counts.get("hold", 0), "clips": counts.get("clip", 0), "refused": counts.get("refuse", 0),
        "max_change": changed, "tracking_error": tracking, "ended_by": stopped or "done",
        "start_distance": distance,
    }

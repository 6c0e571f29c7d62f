"""Replay one episode's actions on the arms through the safety layer, to check a recording before training.

    result = replay_episode("demo.zarr", 3, "can0", send=False)   # dry run: nothing is sent

The replay is the control loop of ``dssp-run`` (:class:`hardware.run_loop.Runner`) with the recorded episode as
its policy source (:class:`hardware.policies.recorded.RecordedEpisode`): every recorded action (dof,) in policy
units goes through :class:`~hardware.safety.Safety` exactly as a model's would (joint limits, per-tick step, stale
feedback holds), one per tick at the dataset's control rate, and the loop ends in its final hold. A dry run (the
default) reads the arm's feedback (if ``can`` is given) but neither enables nor commands it: it reports what the
safety layer would do, starting from where the arm is. With ``send`` the arm is enabled and commanded. Without
``can`` the episode runs against :class:`~hardware.ideal_robot.IdealRobot` (ideal tracking from the episode's first
recorded state) on a simulated clock, so it takes no longer than its arithmetic.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from dssp_core.errors import ConfigError
from dssp_core.schema import check_rate
from hardware.clock import REAL_CLOCK, Clock, FakeClock
from hardware.ideal_robot import IdealRobot
from hardware.piper.limits import piper_description
from hardware.policies.recorded import RecordedEpisode
from hardware.rig import Rig
from hardware.robot import ARM_DOF
from hardware.run_loop import LoopSettings, Runner
from hardware.safety import SafetyConfig
from hardware.subscribers import Subscriber, Tick

FAR_START = 0.3
"""rad: a first action farther than this from the arm's position is pointed out (the safety layer ramps it)."""


class _ReplayWatch(Subscriber):
    """The distance of the first action from where the arm starts (pointed out when far), and the largest change the
    safety layer made to a recorded action (policy units)."""

    def __init__(self, first_action: np.ndarray, where: str, events: Callable[[str], None]):
        self.first_action, self.where, self.events = first_action, where, events
        self.distance: float | None = None
        self.largest = 0.0

    def on_start(self, loop) -> None:
        state = loop.robot.state()
        if state is None:
            return
        self.distance = float(np.max(np.abs(self.first_action - state.position)))
        if self.distance > FAR_START:
            self.events(
                f"note: the first action is {self.distance:.2f} rad from {self.where}: the safety layer ramps it "
                f"by at most {loop.safety_config.max_joint_step} rad per tick"
            )

    def on_tick(self, tick: Tick) -> None:
        action, command = tick.record["action"], tick.record["command"]
        if action is not None and command is not None:
            self.largest = max(self.largest, float(np.max(np.abs(command - action))))


def replay_episode(
    path,
    episode: int,
    can: str | None,
    *,
    send: bool = False,
    interface: str = "socketcan",
    control_rate_hz: float | None = None,
    safety_config: SafetyConfig = SafetyConfig(),
    events: Callable[[str], None] = print,
    attach_stop: Callable[[Callable[[str], None] | None], None] = lambda request: None,
    feedback_timeout: float = 3.0,
    clock: Clock | None = None,
) -> dict:
    """Replay ``episode`` of dataset ``path``; returns a summary dict (ticks, commands sent, clips, holds,
    largest change the safety layer made, final tracking error when sent, what ended it). ``attach_stop`` is given
    the loop's stop request while the loop runs and None after (:meth:`hardware.cli.stops.Stops.during`): a stop
    ends the replay between two commands in its hold, ``ended_by`` the stop's reason. ``clock``: the timeline of
    the pacing, the feedback wait and the safety layer (:mod:`hardware.clock`), the one the arms stamp their
    feedback on; None: the real clock with an arm, a simulated one without."""
    source = RecordedEpisode.load(path, episode)
    dof = source.actions.shape[1]
    if control_rate_hz is not None:
        rate = check_rate(control_rate_hz)
    else:
        rate = source.control_rate_hz  # a value that is not a rate: a DatasetError naming the attribute
        if rate is None:
            raise ConfigError(f"{path} does not record its control rate: pass --control-rate HZ")
        rate = check_rate(rate, flag=f"{path}'s control_rate_hz attribute")
    if send and can is None:
        raise ConfigError("--send needs --can (the arms to command)")
    if can is not None:
        from hardware.piper.piper_robot import open_robot  # deferred: loads can

        clock = clock or REAL_CLOCK
        robot = open_robot(can, interface=interface)
        if robot.dof != dof:
            raise ConfigError(f"the episode has {dof} action values but --can {can} gives {robot.dof} (7 per arm)")
    else:
        clock = clock or FakeClock()
        robot = IdealRobot(piper_description(dof // ARM_DOF), source.first_state, clock)  # no arms: a Piper's
    safety_config.check_speed(float(rate), robot.description.max_joint_speed)
    watch = _ReplayWatch(source.actions[0], "the recorded first state" if can is None else "the arm's position", events)
    rig = Rig(None, robot, np.eye(4), safety_config, clock=clock)
    runner = Runner(
        source,
        rig,
        None,
        LoopSettings(control_rate_hz=rate, dry_run=can is not None and not send, startup_timeout=feedback_timeout),
        subscribers=[watch],
    )
    tracking = None
    attach_stop(runner.request_stop)
    try:
        with rig:
            summary = runner.run()
            if send and runner.fault is None:  # how far the arm is from the last command once it has settled
                clock.sleep(min(1.0, 5.0 / rate))
                state = robot.state()
                if state is not None and runner.safety is not None:
                    tracking = float(np.max(np.abs(state.position - runner.safety.last_safe)))
    finally:
        attach_stop(None)
        runner.close()
    counts = summary["events"]
    return {
        "episode": episode,
        "steps": len(source.actions),
        "rate_hz": float(rate),
        "ticks": summary["ticks"],
        "sent": summary["commands_sent"] if can is not None else 0,
        "dry_run": not send,
        "holds": counts.get("hold", 0),
        "clips": counts.get("clip", 0),
        "refused": counts.get("refuse", 0),
        "max_change": watch.largest,
        "tracking_error": tracking,
        "ended_by": summary["ended_by"],
        "fault": summary["fault"],
        "start_distance": watch.distance,
    }

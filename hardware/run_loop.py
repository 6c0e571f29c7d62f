"""The robot's control loop: camera → point cloud → policy source → safety → arms, at a fixed rate.

    rig = Rig(camera, robot, camera_to_base, SafetyConfig())          # hardware.rig: the devices, opened together
    with rig:
        source = ModelPolicy(onnx_policy, control_rate_hz=10)                  # hardware.policies: what decides the action
        runner = Runner(source, rig, cloud_config, LoopSettings(control_rate_hz=10))
        summary = runner.run()    # until max_steps, the source's end, a stop request (a signal, a lost output) or a fault

Each tick:
1. take the newest camera frame and the newest joint feedback; if the feedback, or the camera of a source that
   needs the point cloud, is missing or stale, **hold** (resend the last safe target) and leave the source alone
   (a frozen camera must not fill the model's memory with copies of one frame);
2. otherwise build the point cloud (``dssp_data.pointcloud``, the same pipeline that builds datasets) when the
   source needs it, and ask the source for the action (:mod:`hardware.policies`: the exported model —
   ``dssp_deploy.ChunkedControl``, the history every tick, a new chunk every H_a ticks —, a recorded episode, the
   arm held); an empty cloud, or a cloud or joint state with NaN/inf or a value far outside the model's training
   range (refused by the runtime before any graph runs), is no observation: hold, the history left alone; a chunk
   the runtime refuses (NaN/inf, an action outside the action range) is no action: hold, the tick undone
   (``dssp_deploy.ranges``);
3. the safety layer turns the action into a command (limits, per-tick step; a deadline miss holds);
4. send it (not with ``dry_run``), hand the tick to the subscribers (:mod:`hardware.subscribers`: the episode
   log, the status line, Rerun views, …), sleep to the next tick (:class:`hardware.pacing.Pacer`).
A fault (arm error or e-stop, a send failure, an error in the source) ends the loop in a hold: nothing is sent
after it. Shapes: cloud (P, C) float32; state, action and command (dof,) in policy units. Before the first tick,
:meth:`Runner.start` checks the joint limits the arms' firmware enforces against the safety layer's
(:meth:`hardware.rig.Rig.check_firmware_limits`) and only then enables the arms.

A source that commands nothing (:attr:`hardware.policies.PolicySource.commands` false: the leader arm of
``dssp-record``, which drives its follower over the bus itself) runs the same loop without the safety layer: nothing
is enabled, sent or held, the start waits for no stream (the subscribers — the recorder — judge the streams each
tick), and the action is what the source reports for the log.

Time: the tick times, the inputs' ages, the tick's deadline, the start-up waits and the pacing are read
from the rig's ``clock`` (:mod:`hardware.clock`; ``time.monotonic`` by default), the clock the camera and the arms
stamp their arrivals on. The latencies (``*_ms``) are compute cost, measured with ``time.perf_counter``
whatever the clock.
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from dssp_core.errors import CameraError, ConfigError, DSSPError, NonFiniteObservation
from dssp_core.schema import DEFAULT_CONTROL_RATE_HZ, check_rate
from dssp_data.pointcloud import EmptyCloudError, PointCloudConfig, frame_to_cloud
from dssp_deploy.ranges import ChunkOutOfRange, ObservationOutOfRange
from hardware.pacing import Pacer, RateMeter, latency_stats
from hardware.policies import PolicySource
from hardware.rig import Rig
from hardware.safety import Safety, SafetyViolation
from hardware.subscribers import Subscriber, Tick


@dataclass(frozen=True)
class LoopSettings:
    control_rate_hz: float = DEFAULT_CONTROL_RATE_HZ
    max_steps: int | None = None  # None: until stopped
    dry_run: bool = False  # compute actions, send nothing (the arms are not enabled)
    startup_timeout: float = 5.0  # s (of the runner's clock) to wait for the first frame and feedback
    resync: float = 0.0  # s a tick may end late before the schedule starts again from now (hardware.pacing.Pacer)

    def __post_init__(self):
        check_rate(self.control_rate_hz)
        if not 0.0 <= self.resync <= 10.0:
            raise ConfigError(f"resync must be in [0, 10] s, got {self.resync!r}")
        if self.max_steps is not None and self.max_steps < 1:
            raise ConfigError(f"--max-steps must be at least 1, got {self.max_steps}")


class Runner:
    def __init__(
        self,
        source: PolicySource,
        rig: Rig,
        cloud_config: PointCloudConfig | None,
        settings: LoopSettings,
        subscribers: Sequence[Subscriber] = (),
    ):
        """``source``: what decides the action (:mod:`hardware.policies`; checked here against the robot and the
        point-cloud pipeline). ``rig``: the camera, the arms, the safety settings and the clock
        (:class:`hardware.rig.Rig`; opened by the caller, ``with rig:``), the limits the robot's own unless the rig
        narrows them; a rig without a camera runs only a source that needs no point cloud. ``cloud_config``: the
        point-cloud pipeline's settings (None: the source needs none). ``subscribers``: what else happens on each
        tick — the episode log, the status line, Rerun views, … (:mod:`hardware.subscribers`), told in this order;
        :meth:`close` gives them the summary."""
        if source.needs_cloud and (rig.camera is None or cloud_config is None):
            raise ConfigError(
                f"the policy source {source.name!r} needs point clouds: give the rig a camera and the loop "
                "the point-cloud settings"
            )
        source.check(rig.description, cloud_config)
        self.source, self.rig, self.camera, self.robot = source, rig, rig.camera, rig.robot
        self.cloud_config, self.camera_to_base = cloud_config, rig.camera_to_base
        self.safety_config, self.settings, self.limits = rig.safety, settings, rig.joint_limits()
        self.clock, self.subscribers = rig.clock, list(subscribers)
        self._closed = False
        self.period = 1.0 / settings.control_rate_hz
        self.safety: Safety | None = None
        self.stop_reason: str | None = None
        self.fault: str | None = None
        self.ended_by: str | None = None  # what ended the run, recorded where it ended (None: it has not ended)
        self.disabled = False  # the motors were disabled at the end (SafetyConfig.disable_on_exit)
        self.ticks = 0
        self.sent = 0
        self.holds = 0
        self.policy_ticks = 0
        self.event_counts: Counter = Counter()
        self.latencies: dict[str, list[float]] = {"cloud": [], "observe": [], "chunk": [], "tick": []}
        self.commanding = bool(source.commands)  # False: the loop only listens (no safety layer, nothing sent)
        self.pacer = Pacer(self.clock, self.period, resync=settings.resync)
        self._rate = RateMeter()

    # ----------------------------------------------------------------- lifecycle
    def request_stop(self, why: str) -> None:
        """Ask the loop to end at the next tick with a final hold (signal handlers call this)."""
        self.stop_reason = self.stop_reason or why

    def start(self) -> None:
        """Wait for the first frame (a source that needs the point cloud) and feedback, check the joint limits the
        arms' firmware enforces against the safety layer's (:meth:`hardware.rig.Rig.check_firmware_limits`: one line
        and nothing enabled when they would clip or fault inside it; not in dry run, which sends nothing), set up the
        safety layer, enable the arms (not in dry run), reset the source with the measured position. A stop requested
        before the arms are enabled ends the start there: nothing is enabled or sent. A source that commands nothing
        starts at once (no stream awaited, no safety layer, the source reset with the feedback if there is any)."""
        if not self.commanding:
            state = self.robot.state()
            self.source.reset(None if state is None else np.array(state.position, dtype=np.float64))
            for subscriber in self.subscribers:
                subscriber.on_start(self)
            return
        timeout = self.settings.startup_timeout
        deadline = self.clock.now() + timeout
        if self.source.needs_cloud and self._wait(self.camera.latest, deadline) is None and self.stop_reason is None:
            raise CameraError(
                f"{self.camera.name}: no frame within {timeout:g} s; check the cable/USB3 port or the recording"
            )
        state = self._wait(self.robot.state, deadline)
        if self.stop_reason is not None:
            return
        if state is None:
            raise DSSPError(
                f"no joint feedback within {timeout:g} s: check the CAN bus (bitrate 1 Mbit/s, cabling) and that the arm is powered"
            )
        if not self.settings.dry_run:  # before anything is enabled: the arms' own limits hold the safety layer's range
            self.rig.check_firmware_limits(stopped=lambda: self.stop_reason is not None)
            if self.stop_reason is not None:
                return
        lower, upper, gripper = self.limits
        self.safety = Safety(self.safety_config, lower, upper, gripper, state.position)
        if not self.settings.dry_run:
            self.robot.enable()
        self.source.reset(np.array(state.position, dtype=np.float64))
        for subscriber in self.subscribers:
            subscriber.on_start(self)

    def _wait(self, get: Callable[[], Any], deadline: float) -> Any:
        """The first ``get()`` that is not None, polled on the clock until ``deadline`` or a stop request; else None."""
        value = get()
        while value is None and self.clock.now() <= deadline and self.stop_reason is None:
            self.clock.sleep(0.005)
            value = get()
        return value

    # ----------------------------------------------------------------- one tick
    def tick(self) -> dict[str, Any]:
        """One control tick; returns its log record."""
        assert self.safety is not None or not self.commanding, "start() first"
        t0, scheduled = self.clock.now(), self.pacer.next_tick
        w0 = time.perf_counter()
        frame = self.camera.latest() if self.camera is not None else None
        state = self.robot.state()
        record: dict[str, Any] = {
            "tick": self.ticks,
            "time": t0,
            "state": None,
            "action": None,
            "command": None,
            "held": False,
        }
        cloud = None
        action = None
        new_chunk = None
        deadline_missed = False
        cfg = self.safety_config
        needs_cloud = self.source.needs_cloud
        camera_fresh = frame is not None and t0 - frame.timestamp <= cfg.camera_timeout
        fresh = state is not None and t0 - state.timestamp <= cfg.feedback_timeout and (camera_fresh or not needs_cloud)
        if frame is not None:
            record["frame_age_ms"] = 1e3 * (t0 - frame.timestamp)
        if state is not None:
            record["state"] = state.position
            record["feedback_age_ms"] = 1e3 * (t0 - state.timestamp)
        observed = fresh and self.fault is None
        if observed and needs_cloud:
            c0 = time.perf_counter()
            try:
                cloud, cloud_info = frame_to_cloud(frame, self.cloud_config, self.camera_to_base)
            except EmptyCloudError as exc:  # nothing in the workspace: no observation, hold
                observed, record["events"] = False, [f"no observation: {exc}"]
                self.event_counts["empty_cloud"] += 1
            else:
                if cloud_info.n_padded:
                    record["cloud_padded"] = int(cloud_info.n_padded)
                    self.event_counts["padded_cloud"] += 1
            record["cloud_ms"] = 1e3 * (time.perf_counter() - c0)
            self.latencies["cloud"].append(record["cloud_ms"])
        if observed:
            try:
                act = self.source.act(cloud, state.position)
            except (
                NonFiniteObservation,
                ObservationOutOfRange,
            ) as exc:  # refused before the history saw it: no observation, hold
                cloud, record["events"] = None, [f"no observation: {exc}"]
                self.event_counts[
                    "non_finite_observation" if isinstance(exc, NonFiniteObservation) else "observation_out_of_range"
                ] += 1
            except ChunkOutOfRange as exc:  # refused, the tick undone: no action, hold
                cloud, record["events"] = None, [f"no action: {exc}"]
                self.event_counts["chunk_out_of_range"] += 1
            except Exception as exc:  # the source failed: hold and end
                self._fault(t0, f"policy error ({self.source.name}): {exc}")
            else:
                action = None if act.action is None else np.asarray(act.action, dtype=np.float64)
                record["action"] = action
                if act.observe_ms is not None:
                    record["observe_ms"] = act.observe_ms
                    self.latencies["observe"].append(act.observe_ms)
                if act.chunk_ms is not None:
                    record["chunk_ms"] = act.chunk_ms
                    self.latencies["chunk"].append(act.chunk_ms)
                new_chunk = act.chunk
                self.policy_ticks += 1
                elapsed = self.clock.now() - t0
                deadline_missed = act.over_budget or elapsed > self.period
                record["events"] = list(act.events)
        now = self.clock.now()
        if not self.commanding:  # the source's action is a report; nothing is decided or sent
            self._end_tick(record, w0, t0, scheduled, frame, cloud, new_chunk)
            return record
        # a source that takes no point cloud is not gated by the camera: the frame's time is the tick's own
        camera_time = (frame.timestamp if frame else None) if needs_cloud else now
        try:
            decision = self.safety.decide(
                action, now=now, camera_time=camera_time, state=self.robot.state(), deadline_missed=deadline_missed
            )
        except SafetyViolation as exc:
            self._fault(now, f"safety check failed: {exc}")
            decision = None
        if decision is not None:
            for event in decision.events:
                self.event_counts[event.kind] += 1
            record["safety"] = [e.to_dict() for e in decision.events]
            record["held"] = decision.held
            if self.safety.fault and self.fault is None:
                self.fault = self.safety.fault
            if decision.command is not None:
                self._send(decision.command, record)
        self._end_tick(record, w0, t0, scheduled, frame, cloud, new_chunk)
        return record

    def _end_tick(
        self, record: dict[str, Any], w0: float, t0: float, scheduled: float, frame, cloud, new_chunk
    ) -> None:
        """Count the tick and hand it to the subscribers."""
        record["tick_ms"] = 1e3 * (time.perf_counter() - w0)
        self.latencies["tick"].append(record["tick_ms"])
        self.holds += bool(record["held"])
        self.ticks += 1
        self._rate.mark(t0)
        tick = Tick(record, frame, cloud, new_chunk, self, scheduled)
        for subscriber in self.subscribers:
            subscriber.on_tick(tick)

    def _send(self, command: np.ndarray, record: dict[str, Any]) -> None:
        record["command"] = command
        if self.settings.dry_run:
            return
        try:
            self.robot.command(command)
            self.sent += 1
        except DSSPError as exc:
            record["command"] = None
            self._fault(self.clock.now(), f"send failed: {exc}")

    def _fault(self, now: float, why: str) -> None:
        """End commanding: the safety layer latches, the last safe target stays the arm's target."""
        self.fault = self.fault or why
        if self.safety is not None and self.safety.fault is None:
            self.safety.stop(now, why)
            self.event_counts["fault"] += 1

    # ----------------------------------------------------------------- the loop
    def run(self) -> dict[str, Any]:
        """Start, then tick until max_steps, a stop request, a fault or an error; each ending is recorded where it
        happens (``ended_by``) and passes :meth:`finish`. A stop requested before the start enables nothing."""
        try:
            if self.stop_reason is None:
                self.start()
            self.pacer.start()
            while self.fault is None and self.stop_reason is None:
                if self.settings.max_steps is not None and self.ticks >= self.settings.max_steps:
                    self.ended_by = "max steps"
                    break
                if self.source.done:
                    self.ended_by = "done"
                    break
                self.tick()
                self.pacer.wait()
        except BaseException as exc:
            self.ended_by = self.ended_by or describe_ending(exc)
            raise
        finally:
            self.finish(self.ended_by or self.fault or self.stop_reason)
        return self.summary()

    def finish(self, why: str) -> None:
        """The final hold (the last safe target once more), then disable if configured. ``why`` is what ended the
        run: recorded as ``ended_by`` unless the ending was recorded before."""
        self.ended_by = self.ended_by or why
        if self.safety is None:  # never started: nothing was enabled or sent
            return
        final = self.safety.stop(self.clock.now(), why)
        if final.command is not None and not self.settings.dry_run and self.fault is None:
            try:
                self.robot.command(final.command)
            except DSSPError as exc:
                self.fault = f"final hold failed: {exc}"
        if self.safety_config.disable_on_exit and not self.settings.dry_run:
            try:
                self.robot.disable()
                self.disabled = True
            except DSSPError as exc:
                self.fault = self.fault or f"disable failed: {exc}"

    @property
    def overruns(self) -> int:
        """Ticks that ended after the next one was due (:class:`hardware.pacing.Pacer`)."""
        return self.pacer.overruns

    def rate(self) -> float:
        """Measured tick rate (Hz) over the last 50 ticks."""
        return self._rate.rate()

    def close(self) -> dict[str, Any]:
        """Give every subscriber the summary (once; later calls only return it): after :meth:`run`, or after a
        start that failed. Returns the summary."""
        summary = self.summary()
        if not self._closed:
            self._closed = True
            for subscriber in self.subscribers:
                subscriber.on_end(summary)
        return summary

    def summary(self, overruns: int | None = None) -> dict[str, Any]:
        """The run in numbers; ``ended_by``: what ended it (None while it has not ended)."""
        return {
            "ticks": self.ticks,
            "policy_ticks": self.policy_ticks,
            "commands_sent": self.sent,
            "holds": self.holds,
            "overruns": self.overruns if overruns is None else overruns,
            "rate_hz": self.rate(),
            "target_rate_hz": self.settings.control_rate_hz,
            "dry_run": self.settings.dry_run,
            "ended_by": self.ended_by,
            "fault": self.fault,
            "disabled": self.disabled,
            "events": dict(self.event_counts),
            "latency_ms": {k: latency_stats(v) for k, v in self.latencies.items()},
            "safety_events": [e.to_dict() for e in (self.safety.events if self.safety else [])],
        }


def describe_ending(exc: BaseException) -> str:
    """What an exception that ended a run says in its summary: ``error: <message>`` (Python's Ctrl-C: SIGINT)."""
    if isinstance(exc, KeyboardInterrupt):
        return "SIGINT"
    return f"error: {exc}" if str(exc) else f"error: {type(exc).__name__}"

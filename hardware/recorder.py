"""The recording loop's tick: sample every stream, check its age, buffer the episode in memory.

    recorder = Recorder(StampedCamera(camera), [BusMonitor("can0")], cloud_config, camera_to_base, control_rate_hz=10)
    recorder.start(now)                 # refuses (RecorderNotReady) while a stream is missing
    sample = recorder.tick(now)         # once per control period
    episode, info = recorder.finish()   # Episode with extras + the episode's metadata; or recorder.abort()

Per tick (shapes in policy units, dof = 7 per arm, left then right):

- the camera's newest frame -> point cloud (P, C) through ``dssp_data.pointcloud.frame_to_cloud``, the
  pipeline the robot runs at deployment (a repeated frame reuses its cloud);
- every follower's feedback -> ``state`` (dof,) [J1..J6 rad, gripper opening];
- every leader's latest command -> the command (dof,), the ``action`` of the ``leader_command``
  convention; with ``next_state`` the action of step t is the state of step t + 1 (RoboTwin);
- the arrival time of each stream, and its age against :class:`RecordThresholds`: each step carries
  bit flags (``dssp_data.recording.STEP_PROBLEMS``), and the episode's metadata lists every problem.

Nothing is invented: a stale stream's last value is recorded and its steps flagged; a frame with no
point in the crop box repeats the previous step's cloud, flagged ``empty_cloud``. Nothing is written
here: the session (``hardware.record_session``) commits a finished episode.

The recorder reads no clock for its timeline: each tick's ``now`` comes from the session's clock
(:mod:`hardware.clock`), and every stream is stamped on that same clock (the bus monitors' and the
camera's ``clock``). Only ``started_unix``, the episode's calendar date, is wall time.
"""

from __future__ import annotations

import math
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from dssp_core.errors import ConfigError, DSSPError
from dssp_core.schema import Settings, check_rate, setting
from dssp_data.dataset_layout import Episode
from dssp_data.pointcloud import EmptyCloudError, PointCloudConfig, frame_to_cloud
from dssp_data.pointcloud.depth_frame import DepthFrame
from dssp_data.recording import (
    ACTION_CONVENTIONS,
    DEPTH_KEY,
    FLAGS_KEY,
    FRAME_KEY,
    PROBLEM_TEXT,
    STEP_PROBLEMS,
    flags_summary,
    problem_names,
)
from dssp_data.rerun_views import TickViews
from hardware.bus_monitor import BusMonitor, oldest
from hardware.camera.base import Camera
from hardware.pacing import RateMeter, latency_stats

_NAN = float("nan")


class RecorderNotReady(DSSPError):
    """An episode cannot start: a stream is missing or unusable (the message says which and why)."""


@dataclass(frozen=True)
class RecordThresholds(Settings):
    """When a stream counts as a problem (seconds; fractions of an episode's steps).

    camera_age / feedback_age / leader_age: a step whose newest frame of that stream is older is flagged.
    late_tick: a step sampled more than this fraction of a period after its schedule is late.
    max_dropped_fraction / max_late_fraction: above these fractions of steps with a repeated camera frame
    (dropped frames) or late ticks, the episode is marked. rate_tolerance: relative deviation of the
    measured rate from the target that marks the episode. Flagged stale steps always mark it.
    """

    SECTION: ClassVar[str] = "thresholds"

    camera_age: float = setting(0.25, gt=0, le=10.0, unit="s")
    feedback_age: float = setting(0.1, gt=0, le=10.0, unit="s")
    leader_age: float = setting(0.1, gt=0, le=10.0, unit="s")
    late_tick: float = setting(0.5, gt=0, le=1.0, unit="of a period")
    max_dropped_fraction: float = setting(0.1, gt=0, le=1.0, unit="of the steps")
    max_late_fraction: float = setting(0.1, gt=0, le=1.0, unit="of the steps")
    rate_tolerance: float = setting(0.05, gt=0, le=1.0, unit="relative")


class StampedCamera:
    """A camera's newest frame with its arrival time on the recorder's clock.

    With ``clock`` None the frame's own ``timestamp`` (``time.monotonic()`` at arrival) is used, which is
    the recorder's clock on a robot. With a clock (a :class:`hardware.clock.Clock` or any callable returning
    seconds: simulated or manual time), a frame is stamped with ``clock()`` when it is first seen.
    """

    def __init__(self, camera: Camera, clock: Callable[[], float] | None = None) -> None:
        self.camera, self.clock = camera, clock
        self._seen: tuple[tuple[int, float], float] | None = None  # (frame_key, stamp)

    def latest(self) -> tuple[DepthFrame | None, float]:
        frame = self.camera.latest()
        if frame is None:
            return None, _NAN
        if self.clock is None:
            return frame, float(frame.timestamp)
        if self._seen is None or self._seen[0] != frame_key(frame):
            self._seen = (frame_key(frame), self.clock())
        return frame, self._seen[1]


@dataclass
class Sample:
    """Every stream at one tick. Times are on the recorder's clock (s); positions (dof,) policy units."""

    now: float
    frame: DepthFrame | None
    camera_time: float
    state: np.ndarray | None
    state_time: float
    command: np.ndarray | None
    command_time: float
    arm_error: str | None
    flags: int = 0

    def age_ms(self, which: str) -> float:
        t = {"camera": self.camera_time, "state": self.state_time, "leader": self.command_time}[which]
        return (self.now - t) * 1e3 if math.isfinite(t) else _NAN


def frame_key(frame: DepthFrame) -> tuple[int, float]:
    """What tells two frames apart: (frame number, arrival time)."""
    return int(frame.frame_number), float(frame.timestamp)


class Recorder:
    """Samples the camera and the arms at each tick and buffers the current episode in memory.

    camera: the scene camera. monitors: one :class:`~hardware.bus_monitor.BusMonitor` per arm pair (left,
    right). cloud_config / camera_to_base (4, 4): the point-cloud pipeline's settings. control_rate_hz: the target
    control rate. action_convention: ``leader_command`` or ``next_state``. store_depth: keep each step's
    raw depth image (H, W) uint16 as the ``depth`` extra. views: Rerun views (:mod:`dssp_data.rerun_views`) of
    every recorded step (the caller closes them): depth, cloud, state, the action as the command, step problems.
    """

    def __init__(
        self,
        camera: StampedCamera,
        monitors: Sequence[BusMonitor],
        cloud_config: PointCloudConfig,
        camera_to_base: np.ndarray,
        control_rate_hz: float,
        *,
        action_convention: str = "leader_command",
        thresholds: RecordThresholds = RecordThresholds(),
        store_depth: bool = True,
        views: TickViews | None = None,
    ) -> None:
        if action_convention not in ACTION_CONVENTIONS:
            raise ConfigError(f"action convention {action_convention!r} is not one of {', '.join(ACTION_CONVENTIONS)}")
        check_rate(control_rate_hz)
        self.camera, self.monitors = camera, list(monitors)
        self.cloud_config = cloud_config
        self.camera_to_base = np.asarray(camera_to_base, dtype=np.float64)
        self.control_rate_hz, self.period = float(control_rate_hz), 1.0 / float(control_rate_hz)
        self.action_convention = action_convention
        self.thresholds = thresholds
        self.store_depth = store_depth
        self.views = views
        self.dof = 7 * len(self.monitors)
        self.recording = False
        self.episode_counts: Counter = Counter()
        self._rate = RateMeter()
        self._cloud_for: tuple[tuple[int, float], np.ndarray] | None = None  # (frame_key, its cloud)
        self._last_frame: tuple[int, float] | None = None
        self._reset_buffers()

    @property
    def needs_leader(self) -> bool:
        return self.action_convention == "leader_command"

    # ---- sampling -------------------------------------------------------------------------------------
    def sample(self, now: float) -> Sample:
        """Read every stream now; ``flags`` holds the stale-stream bits for the thresholds."""
        for monitor in self.monitors:
            monitor.check()
        frame, camera_time = self.camera.latest()
        followers = [m.follower() for m in self.monitors]
        leaders = [m.leader() for m in self.monitors]
        state = None if any(r.position is None for r in followers) else np.concatenate([r.position for r in followers])
        command = None if any(r.position is None for r in leaders) else np.concatenate([r.position for r in leaders])
        errors = [f"{m.name}: {e}" for m in self.monitors if (e := m.follower_error())]
        sample = Sample(
            now, frame, camera_time, state, oldest(followers), command, oldest(leaders), "; ".join(errors) or None
        )
        th = self.thresholds
        if frame is None or not now - camera_time <= th.camera_age:
            sample.flags |= STEP_PROBLEMS["camera_stale"]
        if state is None or not now - sample.state_time <= th.feedback_age:
            sample.flags |= STEP_PROBLEMS["feedback_stale"]
        if self.needs_leader and (command is None or not now - sample.command_time <= th.leader_age):
            sample.flags |= STEP_PROBLEMS["leader_stale"]
        if sample.arm_error:
            sample.flags |= STEP_PROBLEMS["arm_error"]
        return sample

    def _cloud(self, frame: DepthFrame) -> np.ndarray:
        if self._cloud_for is not None and self._cloud_for[0] == frame_key(frame):
            return self._cloud_for[1]
        cloud, _ = frame_to_cloud(frame, self.cloud_config, self.camera_to_base)
        self._cloud_for = (frame_key(frame), cloud)
        return cloud

    # ---- episodes ---------------------------------------------------------------------------------------
    def _reset_buffers(self) -> None:
        self._clouds: list[np.ndarray] = []
        self._states: list[np.ndarray] = []
        self._commands: list[np.ndarray] = []
        self._times: dict[str, list[float]] = {
            "timestamp": [],
            "camera_timestamp": [],
            "state_timestamp": [],
            "action_timestamp": [],
        }
        self._frames: list[int] = []
        self._flags: list[int] = []
        self._depth: list[np.ndarray] = []
        self._ages: dict[str, list[float]] = {"camera": [], "state": [], "leader": []}
        self.episode_counts = Counter()
        self.started_unix = _NAN

    def start(self, now: float) -> Sample:
        """Begin an episode at tick time ``now`` (no step recorded yet).

        Raises RecorderNotReady when the camera gives no frame or no point in the crop box, a follower sends
        no feedback, a leader no commands (leader_command convention), or a follower reports an error.
        """
        sample = self.sample(now)
        problems = []
        if sample.frame is None:
            problems.append("no camera frame yet")
        if sample.state is None:
            missing = [m.name for m in self.monitors if m.follower().position is None]
            problems.append(f"no follower feedback on {', '.join(missing)} (is the follower arm powered?)")
        if self.needs_leader and sample.command is None:
            missing = [m.name for m in self.monitors if m.leader().position is None]
            problems.append(
                f"no leader commands on {', '.join(missing)} (is the leader arm on the bus, in leader mode?)"
            )
        if sample.arm_error:
            problems.append(f"arm error: {sample.arm_error}")
        if sample.frame is not None:
            try:
                self._cloud(sample.frame)
            except EmptyCloudError as exc:
                problems.append(f"camera: {exc}")
        if problems:
            raise RecorderNotReady("cannot start an episode: " + "; ".join(problems))
        self._reset_buffers()
        self.recording = True
        self.started_unix = time.time()
        if self.views is not None:
            if self.views.last_tick < 0:
                self.views.camera(sample.frame.intrinsics.to_dict(), self.camera_to_base)
            self.views.text(self.views.last_tick + 1, "episode", "episode started")
        self._last_frame = None
        self._rate = RateMeter()
        return sample

    def tick(self, now: float, scheduled: float | None = None) -> Sample:
        """Sample the streams; while recording, append one step. ``scheduled``: when the tick was due (for
        late-tick detection; None = on time)."""
        sample = self.sample(now)
        self._rate.mark(now)
        if not self.recording:
            return sample
        if scheduled is not None and now - scheduled > self.thresholds.late_tick * self.period:
            sample.flags |= STEP_PROBLEMS["late_tick"]
        frame = sample.frame
        if frame is None:  # only possible before any frame ever: start() refuses that
            raise RecorderNotReady("the camera has delivered no frame")
        if self._last_frame is not None and frame_key(frame) == self._last_frame:
            sample.flags |= STEP_PROBLEMS["camera_repeat"]
        self._last_frame = frame_key(frame)
        try:
            cloud = self._cloud(frame)
        except EmptyCloudError:
            sample.flags |= STEP_PROBLEMS["empty_cloud"]
            cloud = self._clouds[-1] if self._clouds else None
            if cloud is None:
                raise
        state = sample.state if sample.state is not None else (self._states[-1] if self._states else None)
        command = sample.command if sample.command is not None else (self._commands[-1] if self._commands else state)
        if state is None:
            raise RecorderNotReady("no follower feedback")
        self._clouds.append(cloud)
        self._states.append(state)
        self._commands.append(command if command is not None else state)
        self._times["timestamp"].append(now)
        self._times["camera_timestamp"].append(sample.camera_time)
        self._times["state_timestamp"].append(sample.state_time)
        self._times["action_timestamp"].append(sample.command_time)
        self._frames.append(int(frame.frame_number))
        self._flags.append(sample.flags)
        if self.store_depth:
            self._depth.append(np.array(frame.depth, dtype=np.uint16, copy=True))
        for key in self._ages:
            self._ages[key].append(sample.age_ms(key))
        if self.views is not None:  # references to this step's arrays, never modified afterwards
            self.views.tick(
                self.views.last_tick + 1,
                depth=frame.depth,
                depth_unit=frame.depth_unit,
                cloud=cloud,
                state=self._states[-1],
                command=self._commands[-1],
                events=problem_names(sample.flags),
            )
        for name, bit in STEP_PROBLEMS.items():
            if sample.flags & bit:
                self.episode_counts[name] += 1
        return sample

    @property
    def steps(self) -> int:
        """Steps recorded in the current episode."""
        return len(self._states)

    def rate(self) -> float:
        """Measured tick rate (Hz) over the last 50 ticks."""
        return self._rate.rate()

    def abort(self) -> int:
        """Drop the current episode; returns how many steps it had."""
        steps = self.steps
        self.recording = False
        self._reset_buffers()
        return steps

    def finish(self) -> tuple[Episode, dict]:
        """End the episode: (Episode with its extras, metadata). Raises RecorderNotReady if it is too short."""
        self.recording = False
        n = self.steps
        need = 2 if self.action_convention == "next_state" else 1
        if n < need:
            self._reset_buffers()
            raise RecorderNotReady(f"the episode has {n} step(s): too short to keep")
        t0 = self._times["timestamp"][0]
        times = {k: np.asarray(v, dtype=np.float64) - t0 for k, v in self._times.items()}
        state = np.stack(self._states).astype(np.float32)
        flags = np.asarray(self._flags, dtype=np.uint8)
        keep = slice(None)
        if self.action_convention == "leader_command":
            action = np.stack(self._commands).astype(np.float32)
        else:  # RoboTwin: the action of step t is the state reached at t + 1; the last step has none
            action, keep = state[1:], slice(0, n - 1)
            times["action_timestamp"] = times["state_timestamp"][1:]
        extras = {k: v[keep] for k, v in times.items()}
        extras[FRAME_KEY] = np.asarray(self._frames, dtype=np.int64)[keep]
        extras[FLAGS_KEY] = flags[keep]
        if self.store_depth:
            extras[DEPTH_KEY] = np.stack(self._depth)[keep]
        episode = Episode(
            point_cloud=np.stack(self._clouds)[keep].astype(np.float32), state=state[keep], action=action, extras=extras
        )
        info = self._info(times["timestamp"], flags)
        self._reset_buffers()
        return episode, info

    def _info(self, ticks: np.ndarray, flags: np.ndarray) -> dict:
        n = len(ticks)
        duration = float(ticks[-1] - ticks[0]) if n > 1 else 0.0
        rate = (n - 1) / duration if duration > 0 else _NAN
        summary = flags_summary(flags)
        th = self.thresholds
        problems = []
        for name in ("camera_stale", "feedback_stale", "leader_stale", "empty_cloud", "arm_error"):
            if name in summary:
                problems.append({"kind": name, **summary[name], "what": PROBLEM_TEXT[name]})
        for name, limit in (("camera_repeat", th.max_dropped_fraction), ("late_tick", th.max_late_fraction)):
            if name in summary and summary[name]["steps"] > limit * n:
                problems.append({"kind": name, **summary[name], "what": PROBLEM_TEXT[name]})
        if math.isfinite(rate) and abs(rate - self.control_rate_hz) > th.rate_tolerance * self.control_rate_hz:
            problems.append({"kind": "rate", "measured_hz": round(rate, 3), "what": PROBLEM_TEXT["rate"]})
        ages = {key: latency_stats(values, digits=3) for key, values in self._ages.items()}
        if not self.needs_leader:
            ages.pop("leader", None)
        return {
            "started_unix": self.started_unix,
            "started": time.strftime("%Y-%m-%dT%H:%M:%S%z", time.localtime(self.started_unix)),
            "recorded_steps": n,
            "duration_s": round(duration, 6),
            "rate_hz": round(rate, 4) if math.isfinite(rate) else None,
            "target_rate_hz": self.control_rate_hz,
            "stream_age_ms": ages,
            "step_problems": summary,
            "problems": problems,
            "clean": not problems,
        }

    # ---- display ------------------------------------------------------------------------------------------
    def status_line(self, sample: Sample) -> str:
        """Stream ages (ms, ``!`` when beyond the threshold), rate, the episode's step and problem counts."""
        th = self.thresholds

        def age(key: str, limit: float) -> str:
            ms = sample.age_ms(key)
            if not math.isfinite(ms):
                return f"{key} --- !"
            return f"{key} {ms:4.0f}ms" + (" !" if ms > limit * 1e3 else "")

        parts = [age("camera", th.camera_age), age("state", th.feedback_age)]
        if self.needs_leader:
            parts.append(age("leader", th.leader_age))
        if sample.arm_error:
            parts.append(f"ARM ERROR: {sample.arm_error}")
        if self.episode_counts:
            parts.append("problems: " + " ".join(f"{k}={v}" for k, v in sorted(self.episode_counts.items())))
        head = f"REC step {self.steps:5d}" if self.recording else "idle"
        return f"{head}  {self.rate():5.1f} Hz  " + "  ".join(parts)

"""A recording session: operator commands, episodes committed or dropped, as a subscriber of the control loop.

    session = RecordSession(recorder, dataset, monitors, clock, SessionSettings(), events=print)
    summary = session.run(controls)     # controls.poll() -> "start" | "keep" | "discard" | "quit" | None

``run`` is ``dssp-run``'s loop (:class:`hardware.run_loop.Runner`) with the leader arm as its policy source
(:class:`hardware.policies.leader_arm.LeaderArm`: the leader drives the follower over the bus, the loop commands
nothing), the followers heard on the buses as its robot (:class:`hardware.bus_monitor.ListeningArms`) and this
session as its subscriber: each tick it takes the operator's command, samples every stream
(:class:`hardware.recorder.Recorder`, which records every tick, stale or not, with its problem flags) and ends
episodes.

Commands: ``start`` begins an episode (its CAN logs open, one per bus, under a partial name); ``keep`` ends
it and appends it to the dataset (:class:`~dssp_data.recording.RecordingDataset`: one crash-safe
append; the logs are renamed to ``episode_NNNNNN.<bus>.blf`` first); ``discard`` ends it and deletes it
and its logs; ``quit`` ends the session (refused while an episode is being recorded: keep or discard it
first). A stop request (SIGINT/SIGTERM) or the end of the command stream discards an unfinished episode,
since only the operator can say it is complete. With ``auto`` the session starts episodes itself and ends
each after ``max_steps`` or, on the simulated rig, when the task is done (kept if it succeeded). If an
append fails (a full disk, ...), the episode is written as a dataset of its own next to the dataset
(``<dataset>.unsaved-<session>-<n>``) before the error ends the session.

Timing: the loop ticks every 1 / rate seconds of its ``clock`` (:mod:`hardware.clock`: ``REAL_CLOCK``,
``time.monotonic``, on a robot; a tick that starts more than half a period late is flagged; up to a period late the
ticks stay on their grid) and sleeps on it between ticks. With a :class:`~dssp_sim.teleop.TeleopRig` the clock is
the rig's simulated one, whose sleep moves the simulation (lockstep). The ``auto`` start-up wait
(``ready_timeout``) is on ``clock``.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from dssp_core.errors import DSSPError
from dssp_data.recording import RecordingDataset, can_log_dir, can_log_name, partial_can_log_name
from dssp_data.replay_buffer_writer import write_replay_buffer
from hardware.bus_monitor import BusMonitor, ListeningArms
from hardware.clock import Clock
from hardware.policies.leader_arm import LeaderArm
from hardware.recorder import Recorder, RecorderNotReady
from hardware.rig import Rig
from hardware.run_loop import LoopSettings, Runner
from hardware.subscribers import Subscriber, Tick


@dataclass(frozen=True)
class SessionSettings:
    """max_steps: end (and keep) an episode after this many steps (None: only the operator ends it).
    auto: start episodes without a command; each ends after max_steps or when the simulated task is done.
    episodes: end the session after this many kept episodes (None: only on quit). ready_timeout: seconds (of the
    session's clock) ``auto`` waits for every stream before giving up. task: the task name stored with each
    episode."""

    max_steps: int | None = None
    auto: bool = False
    episodes: int | None = None
    ready_timeout: float = 5.0
    task: str | None = None


@dataclass
class SessionSummary:
    """What a session did: dataset indices of the kept episodes, how it ended, the dataset's size after."""

    kept: list[int] = field(default_factory=list)  # dataset indices
    kept_with_problems: list[int] = field(default_factory=list)
    discarded: int = 0
    failed: dict[str, int] = field(default_factory=dict)  # auto on the rig: task failures by reason
    steps: int = 0
    ended_by: str = ""
    repaired_steps: int = 0
    n_episodes: int = 0


class RecordSession(Subscriber):
    """Runs the loop for ``recorder`` and appends kept episodes to ``dataset``.

    monitors: the recorder's bus monitors (their per-episode CAN logs go to ``<dataset>.can/``).
    clock: the loop's and the recorder's clock, the one its streams are stamped on
    (:data:`~hardware.clock.REAL_CLOCK` or the rig's simulated clock). rig: the lockstep
    :class:`~dssp_sim.teleop.TeleopRig` (its scenes and task status), or None on a robot. events: prints one line
    per event (episode started, kept, discarded, problems). status: shows the live one-line status (or None).
    """

    def __init__(
        self,
        recorder: Recorder,
        dataset: RecordingDataset,
        monitors: Sequence[BusMonitor],
        clock: Clock,
        settings: SessionSettings,
        *,
        rig=None,
        events: Callable[[str], None] = print,
        status: Callable[[str], None] | None = None,
        session_tag: str | None = None,
    ) -> None:
        self.recorder, self.dataset, self.monitors = recorder, dataset, list(monitors)
        self.clock, self.settings, self.rig = clock, settings, rig
        self.events, self.status = events, status
        self.session_tag = session_tag or time.strftime("%Y%m%d-%H%M%S")
        self.log_dir = can_log_dir(dataset.path)
        self.summary = SessionSummary(repaired_steps=dataset.repaired_steps)
        self._stop_reason: str | None = None
        self._partial_logs: list[tuple[BusMonitor, Path]] = []
        self._episode_seed: int | None = None
        self._ready_deadline: float | None = None
        self._ended = False
        self.loop: Runner | None = None
        self.controls = None

    def request_stop(self, why: str) -> None:
        """End the session at the next tick, discarding an unfinished episode (signal handlers call this)."""
        self._stop_reason = self._stop_reason or why
        if self.loop is not None:
            self.loop.request_stop(why)

    # ---- episodes ----------------------------------------------------------------------------------------
    def _start(self, quiet: bool = False) -> str | None:
        """Begin an episode; returns None, or why it cannot start (also printed unless ``quiet``)."""
        if self.recorder.recording:
            self.events("already recording: keep (k) or discard (d) the episode first")
            return "already recording"
        if self.rig is not None:
            self._episode_seed = self.rig.new_episode()
        try:
            self.recorder.start(self.clock.now())
        except RecorderNotReady as exc:
            if self.rig is not None:
                self.rig.end_episode()
            if not quiet:
                self.events(str(exc))
            return str(exc)
        index = self.dataset.n_episodes
        self._partial_logs = []
        self.log_dir.mkdir(parents=True, exist_ok=True)
        try:
            for monitor in self.monitors:
                path = self.log_dir / partial_can_log_name(index, monitor.name, self.session_tag)
                monitor.begin_log(path)
                self._partial_logs.append((monitor, path))
        except DSSPError as exc:  # no episode without its CAN logs
            self._close_logs()
            self._drop_logs()
            self.recorder.abort()
            if self.rig is not None:
                self.rig.end_episode()
            self.events(f"cannot start an episode: {exc}")
            return str(exc)
        seed = f" (scene seed {self._episode_seed})" if self._episode_seed is not None else ""
        self.events(f"episode {index}: recording{seed}")
        return None

    def _close_logs(self) -> dict[str, int]:
        """Close the episode's CAN logs; returns frames per bus (a log that failed is reported)."""
        frames = {}
        for monitor, path in self._partial_logs:
            frames[monitor.name] = monitor.end_log()
            if monitor.log_error:
                self.events(f"warning: the CAN log {path.name} stopped early: {monitor.log_error}")
        return frames

    def _drop_logs(self) -> None:
        for _, path in self._partial_logs:
            try:
                path.unlink()
            except FileNotFoundError:
                pass
        self._partial_logs = []

    def _discard(self, why: str) -> None:
        self._close_logs()
        steps = self.recorder.abort()
        self._drop_logs()
        if self.rig is not None:
            self.rig.end_episode()
        self.summary.discarded += 1
        self.events(f"episode {self.dataset.n_episodes}: discarded ({why}, {steps} steps)")

    def _keep(self, ended_by: str, extra_info: dict | None = None) -> None:
        frames = self._close_logs()
        if self.rig is not None:
            self.rig.end_episode()
        try:
            episode, info = self.recorder.finish()
        except RecorderNotReady as exc:
            self._drop_logs()
            self.summary.discarded += 1
            self.events(f"episode {self.dataset.n_episodes}: discarded ({exc})")
            return
        index = self.dataset.n_episodes
        logs = {}
        for monitor, path in self._partial_logs:  # logs first: an episode in the dataset always has its logs
            final = self.log_dir / can_log_name(index, monitor.name)
            os.replace(path, final)
            logs[monitor.name] = final.name
        self._partial_logs = []
        log_errors = {m.name: m.log_error for m in self.monitors if m.log_error}
        info.update(
            {
                "ended_by": ended_by,
                "task": self.settings.task,
                "can_logs": logs,
                "can_frames": frames,
                **({"can_log_errors": log_errors} if log_errors else {}),
                **(extra_info or {}),
            }
        )
        try:
            self.dataset.commit(episode, info)
        except (DSSPError, OSError) as exc:
            self._rescue(episode, info, exc)
            raise
        self.summary.kept.append(index)
        self.summary.steps += episode.n_steps
        rate = f"{info['rate_hz']:.2f} Hz" if info["rate_hz"] else "- Hz"
        if info["problems"]:
            self.summary.kept_with_problems.append(index)
            listing = "; ".join(_describe_problem(p) for p in info["problems"])
            self.events(f"episode {index}: kept with PROBLEMS, {episode.n_steps} steps, {rate}: {listing}")
        else:
            self.events(f"episode {index}: kept, {episode.n_steps} steps, {rate}, clean")

    def _rescue(self, episode, info: dict, exc: BaseException) -> None:
        """The append failed: write the episode as a dataset of its own next to the dataset, so it is not lost."""

        target = self.dataset.path.with_name(
            f"{self.dataset.path.name}.unsaved-{self.session_tag}-{len(self.summary.kept)}"
        )
        try:
            write_replay_buffer(target, [episode], {**self.dataset.writer.attrs, "episode_info": [info]})
            self.events(f"error: appending the episode failed ({exc}); it was saved to {target}")
        except Exception as second:  # e.g. the disk is full: say so, the original error follows
            self.events(f"error: appending the episode failed ({exc}) and saving it to {target} failed too ({second})")

    def _auto_end(self) -> None:
        """Auto mode: end the episode when the simulated task is done or max_steps is reached."""
        rec = self.recorder
        if self.rig is not None:
            status = self.rig.episode_status()
            if status.done:
                sim = {"sim": {"seed": self._episode_seed, "success": bool(status.success), "reason": status.reason}}
                if status.success:
                    self._keep("auto: task done", sim)
                else:
                    reason = status.reason or "failed"
                    self.summary.failed[reason] = self.summary.failed.get(reason, 0) + 1
                    self._discard(f"task failed: {reason}")
                return
        if self.settings.max_steps is not None and rec.steps >= self.settings.max_steps:
            self._keep("auto: max steps")

    # ---- the loop ------------------------------------------------------------------------------------------
    def _handle(self, command: str | None) -> bool:
        """Apply one operator command; returns False when the session should end."""
        if command is None:
            return True
        if command == "start":
            self._start()
        elif command in ("keep", "discard"):
            if not self.recorder.recording:
                self.events(f"{command}: no episode is being recorded (start it with s)")
            elif command == "keep":
                self._keep("operator")
            else:
                self._discard("operator")
        elif command == "quit":
            if self.recorder.recording and not self.settings.auto:
                self.events("an episode is being recorded: keep (k) or discard (d) it before quitting")
                return True
            if self.recorder.recording:  # auto: the operator stops the unattended run
                self._discard("quit before the episode ended")
            self.summary.ended_by = "quit"
            return False
        elif command == "eof":
            if self.settings.auto:  # unattended: no commands needed
                return True
            if self.recorder.recording:
                self._discard("the command stream ended before keep")
            self.summary.ended_by = "end of commands"
            return False
        else:
            self.events(f"unknown command {command!r}: use s (start), k (keep), d (discard), q (quit)")
        return True

    def _enough(self) -> bool:
        return self.settings.episodes is not None and len(self.summary.kept) >= self.settings.episodes

    def _end(self, why: str | None = None) -> None:
        """The session ends (``why``, when it was not said already): the loop stops before its next tick."""
        if why is not None:
            self.summary.ended_by = why
        self._ended = True
        if self.loop is not None:
            self.loop.request_stop(self.summary.ended_by)

    # ---- the loop's subscriber ---------------------------------------------------------------------------
    def on_start(self, loop: Runner) -> None:
        self.loop = loop
        if self.settings.auto:
            self._ready_deadline = self.clock.now() + self.settings.ready_timeout

    def on_tick(self, tick: Tick) -> None:
        """One tick of the loop: an automatic end (judged on the world after the last step: the task done, or
        ``max_steps``), the operator's command, an automatic start, the sample, a ``max_steps`` keep."""
        if self._ended:
            return
        rec = self.recorder
        if self.settings.auto and rec.recording:
            self._auto_end()
        if self._enough():
            self._end(f"{len(self.summary.kept)} episodes kept")
            return
        if not self._handle(self.controls.poll()):
            self._end()
            return
        if self.settings.auto and not rec.recording:
            problem = self._start(quiet=True)
            if problem is None:
                self._ready_deadline = self.clock.now() + self.settings.ready_timeout
            elif self.clock.now() > self._ready_deadline:
                raise DSSPError(f"{problem} (waited {self.settings.ready_timeout:g} s)")
        sample = rec.tick(tick.record["time"], scheduled=tick.scheduled)
        if self.status is not None:
            self.status(
                f"ep {self.dataset.n_episodes}  "
                + rec.status_line(sample)
                + f"  kept {len(self.summary.kept)} discarded {self.summary.discarded}"
            )
        if (
            rec.recording
            and not self.settings.auto
            and self.settings.max_steps is not None
            and rec.steps >= self.settings.max_steps
        ):
            self._keep("max steps")
            if self._enough():
                self._end(f"{len(self.summary.kept)} episodes kept")

    def on_end(self, summary: dict) -> None:
        """The loop ended: an unfinished episode is discarded (a stop request), or dropped quietly (an error)."""
        rec = self.recorder
        why = self._stop_reason or summary.get("ended_by") or "the loop ended"
        if rec.recording:
            if self._stop_reason is not None or not str(why).startswith("error"):
                self._discard(f"stopped by {why} before keep")
            else:  # an exception: nothing unconfirmed is kept
                self._close_logs()
                rec.abort()
                self._drop_logs()
        if not self.summary.ended_by:
            self.summary.ended_by = str(why)
        self.summary.n_episodes = self.dataset.n_episodes

    def run(self, controls) -> SessionSummary:
        """The control loop (:class:`hardware.run_loop.Runner`) with the leader arm as its source and this session
        as its subscriber, until quit, a stop request, or ``episodes`` kept; returns the summary.
        ``controls.poll()`` gives the operator's next command (or None) once per tick."""
        rec = self.recorder
        self.controls = controls
        rig = Rig(None, ListeningArms(self.monitors), rec.camera_to_base, clock=self.clock)
        # up to a period late, the samples stay on their grid (a short stall is one late, flagged step)
        settings = LoopSettings(control_rate_hz=rec.control_rate_hz, resync=rec.period)
        runner = Runner(LeaderArm(self.monitors), rig, None, settings, subscribers=[self])
        if self._stop_reason is not None:
            runner.request_stop(self._stop_reason)
        self.loop = runner
        with rig:
            try:
                runner.run()
            finally:
                runner.close()
        return self.summary


def _describe_problem(problem: dict) -> str:
    if problem["kind"] == "rate":
        return f"{problem['what']} ({problem['measured_hz']:.2f} Hz)"
    return f"{problem['what']} at {problem['steps']} step(s) from step {problem['first_step']}"

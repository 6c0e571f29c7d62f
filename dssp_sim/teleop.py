"""The embedded teleoperation rig: a scripted leader, a simulated follower and the simulated camera, in lockstep.

What ``dssp-sim record`` (``dssp-record --camera mujoco --can mujoco``) records from, with no hardware:

- one python-can ``virtual`` bus shared, as on the real platform, by a leader and a follower;
- the leader is a :class:`~hardware.leader.ScriptedLeader` played by the task's scripted expert
  (``dssp_sim.experts``): each tick it sends the expert's target (0x151, 0x155..0x157, 0x159);
- the follower is :class:`~dssp_sim.mujoco_arm.MujocoPiper` (powered on at start as a follower arm would
  be), which obeys those frames with MuJoCo physics and sends its feedback;
- the camera is :class:`~dssp_sim.mujoco_camera.MujocoCamera` (depth through the RealSense software device).

Time is simulated (:class:`SimClock`), and the recording loop's pacing moves it: the loop samples every stream at
time t, then sleeps a period on the rig's clock, which is ``after_tick(dt)`` (the clock moves to t + dt, the
follower moves dt and reports, the camera renders) and ``before_tick()`` (the leader sends its command for
t + dt); a new episode's scene sends its first command at once. Each call returns once the recorder's bus
monitor has received every frame sent, so a recording is deterministic. ``pace``: simulated seconds per wall
second (None: as fast as the machine goes). Fault injection for tests and demos: ``pause_feedback`` /
``resume_feedback`` and ``freeze_camera``.
"""

from __future__ import annotations

import time
import uuid

import numpy as np

from dssp_core.errors import ConfigError
from dssp_sim.env import PiperEnv
from dssp_sim.experts import make_expert
from dssp_sim.mujoco_arm import MujocoPiper
from dssp_sim.mujoco_camera import MujocoCamera
from dssp_sim.settings import cloud_config_for
from dssp_sim.tasks import make_task
from hardware.cli.record import main
from hardware.clock import FakeClock
from hardware.leader import ScriptedLeader
from hardware.piper import codec


class SimClock(FakeClock):
    """Simulated time in seconds (a :class:`hardware.clock.Clock`): starts at 0; :meth:`sleep` moves the rig
    (``step(dt)``, given by the rig) and, with ``pace``, keeps to that many simulated seconds per wall second."""

    def __init__(self, step, pace: float | None = None) -> None:
        super().__init__(0.0)
        self.step, self.pace = step, pace
        self._origin: tuple[float, float] | None = None  # (simulated, wall) time the pace counts from

    def sleep(self, dt: float) -> None:
        if dt <= 0:
            return
        if self.pace and self._origin is None:
            self._origin = (self.t, time.monotonic())
        self.step(dt)
        if self.pace:
            ahead = self._origin[1] + (self.t - self._origin[0]) / self.pace - time.monotonic()
            if ahead > 0:
                time.sleep(ahead)


class TeleopRig:
    """The simulated leader/follower pair and camera for ``task`` (tap, swap, put2).

    ``channel``: the virtual bus to listen on. ``camera``: the scene camera. ``clock``: the simulated
    clock to stamp frames with, whose sleep moves the rig. Episode ``k`` of a session uses the scene of seed
    ``seed + k``. ``pace``: simulated seconds per wall second (None: as fast as possible).
    """

    def __init__(self, task: str = "tap", seed: int = 0, pace: float | None = None) -> None:
        self.task, self.seed = task, int(seed)
        self.env = PiperEnv(task, seed=self.seed)
        self.clock = SimClock(self._tick, pace)
        self.channel = f"dssp-teleop-{uuid.uuid4().hex[:8]}"
        self.follower = MujocoPiper(self.env, self.channel)
        self.camera = MujocoCamera(self.env)
        self.leader = ScriptedLeader(self.channel, "virtual", script=self._script)
        self.control_rate_hz = float(self.env.control_rate_hz)
        self.expert = None
        self.episode_seed: int | None = None
        self.camera_frozen = False
        self._monitor = None
        self._episodes = 0

    # ---- lifecycle ------------------------------------------------------------------------------------
    def start(self, monitor) -> None:
        """Open the buses and power the follower on (enable, as a follower arm is at the start of a session).
        ``monitor``: the recorder's :class:`~hardware.bus_monitor.BusMonitor` on :attr:`channel`, started."""
        self._monitor = monitor
        self.follower.start(thread=False)
        self.leader.start()
        self.camera.start()
        hold = self.env.state()
        self.leader.send_frames([codec.MotorEnable(codec.MOTOR_ALL, codec.MOTOR_ENABLE_FLAG).to_frame()])
        self.leader.send(hold)
        self.follower.step(0.0)
        self.camera.capture()
        self._sync()
        self.before_tick()

    def stop(self) -> None:
        self.camera.stop()
        self.leader.stop()
        self.follower.stop()
        self.env.close()

    def _sync(self) -> None:
        """Wait until the monitor has every frame the leader and the follower sent."""
        self._monitor.wait_for_frames(self.leader.frames_sent + self.follower.frames_sent)

    # ---- episodes --------------------------------------------------------------------------------------
    def new_episode(self) -> int:
        """Reset the scene (seed ``seed + k`` for the k-th episode) with a fresh expert; returns the seed."""
        self.episode_seed = self.seed + self._episodes
        self._episodes += 1
        self.env.reset(seed=self.episode_seed)
        self.follower.sync_from_env()
        self.expert = make_expert(self.env)
        self.leader.last_target = self.env.state()
        self.follower.step(0.0)
        if not self.camera_frozen:
            self.camera.capture()
        self._sync()
        self.before_tick()  # the expert's first command, sampled at this tick
        return self.episode_seed

    def end_episode(self) -> None:
        """The leader holds still from now on."""
        self.expert = None

    def _script(self) -> np.ndarray | None:
        return None if self.expert is None else self.expert.act(self.env)

    def before_tick(self) -> None:
        """The leader sends its command for this tick (the expert's target, or a hold between episodes)."""
        self.leader.step()
        self._sync()

    def after_tick(self, dt: float) -> None:
        """Simulated time moves ``dt`` s: the follower moves and reports, the camera renders."""
        self.clock.advance(dt)
        self.follower.step(dt)
        if not self.camera_frozen:
            self.camera.capture()
        self._sync()

    def answer(self) -> None:
        """The follower handles what it was sent so far (the joint-limit query) and reports, at the present time:
        nothing moves, nothing renders."""
        self.follower.step(0.0)
        self._sync()

    def _tick(self, dt: float) -> None:
        """The loop sleeps ``dt``: the world moves, then the leader sends its command for the next tick."""
        self.after_tick(dt)
        self.before_tick()

    def episode_status(self):
        """The task's status (``done``, ``success``, ``reason``) of the current episode."""
        return self.env.status()

    # ---- faults ---------------------------------------------------------------------------------------------
    def pause_feedback(self) -> None:
        self.follower.pause_feedback()

    def resume_feedback(self) -> None:
        self.follower.resume_feedback()

    def freeze_camera(self, frozen: bool = True) -> None:
        self.camera_frozen = bool(frozen)


class TeleopRigs:
    """The simulation as ``dssp-record``'s :class:`~hardware.cli.record.SimulatedRig`: its point-cloud
    settings and a :class:`TeleopRig` per session."""

    def default_cloud_config(self):
        return cloud_config_for()

    def open(self, task: str, seed: int, pace: float | None = None) -> TeleopRig:
        try:
            make_task(task)
        except (KeyError, ValueError):
            raise ConfigError(f"--task-name {task!r} is not a simulated task: use tap, swap or put2") from None
        return TeleopRig(task, seed=seed, pace=pace)


def record_main(argv: list[str] | None = None, stops=None) -> int:
    """``dssp-sim record``: ``dssp-record`` on the simulated rig (``--camera mujoco --can mujoco`` by default);
    ``stops``: the stop request :func:`dssp_sim.sim_cli.main` installed before importing this module."""

    return main(argv, sim=TeleopRigs(), prog="dssp-sim record", stops=stops)

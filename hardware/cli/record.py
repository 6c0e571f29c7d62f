"""``dssp-record``: record teleoperated demonstrations (Piper leader -> follower, RealSense scene) into a dataset.

    dssp-record --camera l515|d435|d405|file:PATH|sim --can can0[,can1]|sim --out PATH.zarr
                [--control-rate HZ] [--extrinsics FILE] [--task-name NAME] [--action leader|next-state]
                [--pointcloud FILE] [--thresholds FILE] [--max-steps N] [--episodes N] [--auto]
                [--no-depth] [--seed S] [--sim-speed X] [--interface socketcan] [--serial SERIAL] [--quiet]
                [--rerun [URL] | --rerun-save PATH.rrd]

Controls: on a terminal single keys, s start, k stop and keep, d stop and discard, q quit; otherwise one
command per line on stdin (s/start, k/keep, d/discard, q/quit). A live status line shows the episode, its
step, the measured rate and the age of every stream (``!`` past its threshold). Each kept episode is
appended to PATH.zarr crash-safely, with its raw CAN traffic in PATH.zarr.can/. Before anything is recorded or
written, the followers are asked for their firmware joint limits (0x472, the one frame the recorder sends) and one
that does not answer, or whose limits are empty, inverted or narrower than the Piper's, is refused with one line. ``dssp-sim record`` (same
flags, :mod:`dssp_sim.teleop`) records from the embedded simulation through this same code: ``--camera mujoco
--can mujoco`` (its defaults: the MuJoCo Piper's camera and arms), the task's scripted expert playing the leader arm on a virtual bus. The
simulation is handed in as a :class:`SimulatedRig` (this package never imports the simulation).
Every way the process is stopped — any signal whose default would end it (SIGINT, SIGTERM, SIGHUP, ...), or
stdout/stderr going away — ends the session like Ctrl-C (:mod:`hardware.cli.stops`): an unfinished episode is
discarded, every kept one stays in the dataset.
Exit codes: 0 done, 2 bad input, 128 + N stopped by signal N (130 SIGINT, 143 SIGTERM, 129 SIGHUP, ...), 141 stdout
or stderr went away.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import queue
import select
import socket
import sys
import threading
import time
from pathlib import Path
from typing import Protocol

from dssp_core.cli_runner import ArgumentParser, run_cli
from dssp_core.errors import ConfigError, DSSPError
from dssp_core.output_guard import NEW, OutputKind, check_append
from dssp_core.schema import DEFAULT_CONTROL_RATE_HZ, check_rate
from dssp_data.attributes import zarr_generator
from dssp_data.observation import ObservationContract, piper_layout
from hardware.cli.stops import Stops, run_stoppable
from hardware.clock import FakeClock
from hardware.piper.bus import interface_name

RECORDED_DATASET = OutputKind(
    "a recorded dataset", "dssp-record", marker=False, signature=lambda p: zarr_generator(p) == "dssp-record"
)
"""``dssp-record --out``: a zarr dataset whose ``generator`` attribute is ``dssp-record`` (appended to)."""

EPILOG = """\
Action convention (--action): "leader" (default) records the leader arm's command at each step, what the
follower was told to do and what dssp-run sends; "next-state" records the follower's next measured state
(RoboTwin's convention; each episode loses its last step). The dataset's attributes say which.
--auto starts and ends episodes by itself: after --max-steps, or on the simulation when the task is done
(kept only if it succeeded); --episodes N ends the session after N kept episodes.
"""

MUJOCO = "mujoco"  # the camera and arms of the simulated rig dssp-sim record hands in (SimulatedRig)
KEYS = {"s": "start", " ": "start", "k": "keep", "d": "discard", "q": "quit"}
WORDS = {
    "s": "start",
    "start": "start",
    "k": "keep",
    "keep": "keep",
    "d": "discard",
    "discard": "discard",
    "q": "quit",
    "quit": "quit",
    "exit": "quit",
}


class SimulatedRig(Protocol):
    """What ``--can sim`` needs from a simulation (``dssp-sim record`` passes :class:`dssp_sim.teleop.TeleopRigs`)."""

    def default_cloud_config(self): ...

    """The simulation's point-cloud settings (a :class:`~dssp_data.observation.PointCloudConfig`)."""

    def open(self, task: str, seed: int, pace: float | None = None): ...

    """A rig (``channel``, ``camera``, ``clock`` — whose sleep moves the simulation —, ``control_rate_hz``,
    ``start(monitor)``, ``answer()`` — its arms handle what they were sent, at the present time: nothing moves —,
    ``stop()``) for ``task`` from scene ``seed``, run at ``pace`` simulated seconds per wall second (None: as fast as
    possible); raises ConfigError naming the task when there is no such task."""


class _AnsweredInPlace(FakeClock):
    """The wait for the simulated followers' answers to the joint-limit query, in lockstep without moving the
    simulation: each sleep counts on this clock (for the timeout) and lets the rig's arms answer at the present time
    (``answer()``), so the recording is the same with the check as without."""

    def __init__(self, rig) -> None:
        super().__init__()
        self.rig = rig

    def sleep(self, dt: float) -> None:
        super().sleep(dt)
        self.rig.answer()


def parse_args(argv, sim: SimulatedRig | None = None, prog: str = "dssp-record"):
    """``argv`` → the arguments; ``sim``: the simulation ``--can sim`` records from (None: a robot only)."""
    p = ArgumentParser(
        prog=prog,
        description="Record teleoperated demonstrations into a DP3 zarr dataset.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    default = MUJOCO if sim is not None else None
    p.add_argument(
        "--camera",
        default=default,
        required=sim is None,
        help="l515 | d435 | d405 | file:PATH (.bag/.db3) | tabletop"
        + (" | mujoco (default: mujoco, the MuJoCo Piper's)" if sim else ""),
    )
    p.add_argument("--serial", help="RealSense serial number, when several are connected")
    p.add_argument(
        "--can",
        default=default,
        required=sim is None,
        help="can0[,can1] (one bus per leader/follower pair: left, right)"
        + (" | mujoco (default: mujoco, the MuJoCo Piper's arms)" if sim else ""),
    )
    p.add_argument(
        "--interface",
        default="socketcan",
        type=interface_name,
        help="python-can interface of real buses (default: socketcan)",
    )
    p.add_argument("--out", type=Path, required=True, help="dataset to create or append to (PATH.zarr)")
    p.add_argument(
        "--control-rate",
        type=float,
        help="recording rate in Hz (default: the dataset's, else the simulation's 10 Hz, else 10)",
    )
    p.add_argument("--extrinsics", type=Path, help="camera->robot-base calibration JSON (needed with a real camera)")
    p.add_argument(
        "--pointcloud", type=Path, help="point-cloud settings JSON (default: the dataset's, else the robot's defaults)"
    )
    p.add_argument(
        "--task-name",
        help="task name stored with the data; on the simulation also its task (tap, swap, put2; default tap)",
    )
    p.add_argument(
        "--action", choices=["leader", "next-state"], default="leader", help="what `action` holds (see below)"
    )
    p.add_argument("--thresholds", type=Path, help="stream thresholds JSON (hardware.recorder.RecordThresholds fields)")
    p.add_argument("--max-steps", type=int, help="end (and keep) an episode after N steps")
    p.add_argument("--episodes", type=int, help="end the session after N kept episodes")
    p.add_argument("--auto", action="store_true", help="start and end episodes without the operator (see below)")
    p.add_argument(
        "--no-depth", action="store_true", help="do not store the raw depth images (the clouds cannot be rebuilt then)"
    )
    p.add_argument(
        "--seed", type=int, help="simulation: scene seed of the first episode (default: after the dataset's last)"
    )
    p.add_argument(
        "--sim-speed",
        type=float,
        help="simulation: simulated seconds per second (default 1, with --auto as fast as possible)",
    )
    p.add_argument("--quiet", action="store_true", help="no live status line")
    from dssp_data.rerun_views import add_rerun_flags, check_views  # deferred: loads numpy

    add_rerun_flags(p, what="every recorded step")
    args = p.parse_args(argv)
    check_views(args.rerun, args.rerun_save)
    for name in ("max_steps", "episodes"):
        value = getattr(args, name)
        if value is not None and value < 1:
            raise ConfigError(f"--{name.replace('_', '-')} must be at least 1, got {value}")
    from hardware.camera import check_camera_spec  # deferred: loads numpy

    if args.control_rate is not None:
        check_rate(args.control_rate)

    if not (sim is not None and args.camera.strip().lower() == MUJOCO):
        check_camera_spec(args.camera, args.serial)
    if args.sim_speed is not None and not (args.sim_speed == 0 or 0.01 <= args.sim_speed <= 100):
        raise ConfigError(
            f"--sim-speed must be 0 (as fast as possible) or in [0.01, 100] simulated seconds per second, "
            f"got {args.sim_speed:g}"
        )
    if args.seed is not None and args.seed < 0:
        raise ConfigError(f"--seed must be >= 0, got {args.seed}")
    can = args.can.strip().lower()
    if sim is None and (can.startswith("sim") or can.startswith(MUJOCO)):
        raise ConfigError(
            f"--can {args.can}: dssp-record drives real buses; record the simulation with dssp-sim record (same flags)"
        )
    if sim is not None and can.startswith("sim"):  # the spelling before there were two simulators
        raise ConfigError(
            f"--can {args.can}: the simulated rig's arms are spelled mujoco (--camera mujoco --can mujoco, "
            "the defaults)"
        )
    args.sim_rig = sim
    return args


# ---- operator controls -----------------------------------------------------------------------------------
class KeyControls:
    """Single keys on a terminal (cbreak mode: no Enter needed, Ctrl-C still works)."""

    def __init__(self, stream=sys.stdin):
        import termios  # deferred: loads termios
        import tty  # deferred: loads termios

        self.stream, self.fd = stream, stream.fileno()
        self._saved = termios.tcgetattr(self.fd)
        tty.setcbreak(self.fd)

    def poll(self) -> str | None:
        ready, _, _ = select.select([self.fd], [], [], 0)
        if not ready:
            return None
        key = os.read(self.fd, 1).decode(errors="ignore").lower()
        return KEYS.get(key, f"key {key!r}" if key.strip() else None)

    def close(self) -> None:
        import termios  # deferred: loads termios

        termios.tcsetattr(self.fd, termios.TCSADRAIN, self._saved)


class LineControls:
    """One command per line (s/start, k/keep, d/discard, q/quit) read by a thread; the end of input is "eof"."""

    def __init__(self, stream=sys.stdin):
        self._queue: queue.Queue = queue.Queue()
        self._thread = threading.Thread(target=self._read, args=(stream,), name="record-controls", daemon=True)
        self._thread.start()

    def _read(self, stream) -> None:
        try:
            for line in stream:
                word = line.strip().lower()
                if word:
                    self._queue.put(WORDS.get(word, word))
        except (OSError, ValueError):
            pass
        self._queue.put("eof")

    def poll(self) -> str | None:
        try:
            return self._queue.get_nowait()
        except queue.Empty:
            return None

    def close(self) -> None:
        pass


class Console:
    """Event lines on stdout (one per event, at once) and the live status line on stderr."""

    def __init__(self, quiet: bool):
        from hardware.subscribers.status_line import StatusPrinter  # deferred: loads termios

        self.status = None if quiet else StatusPrinter()

    def event(self, line: str) -> None:
        if self.status is not None and self.status.tty:
            sys.stderr.write("\r\x1b[K")
            sys.stderr.flush()
        print(line, flush=True)

    def close(self) -> None:
        if self.status is not None:
            self.status.close()


# ---- devices -------------------------------------------------------------------------------------------------
def _next_sim_seed(out: Path) -> int:
    """One past the largest scene seed the dataset's simulated episodes used (0 for a new dataset)."""
    from dssp_data.replay_buffer import ReplayBufferReader  # deferred: loads msgpack, numcodecs, numpy, …

    if not out.exists():
        return 0
    reader = ReplayBufferReader(out, allow_incomplete_tail=True)  # a broken dataset: its one-line DatasetError
    from dssp_data.recording import episode_infos  # deferred: loads msgpack, numcodecs, numpy, …

    seeds = [
        info["sim"]["seed"]
        for info in episode_infos(reader.attrs, reader.n_episodes, out)
        if info and isinstance(info.get("sim"), dict) and isinstance(info["sim"].get("seed"), int)
    ]
    return max(seeds) + 1 if seeds else reader.n_episodes


def _check_no_orphan_can_logs(out: Path) -> None:
    """A new dataset's CAN-log folder must not hold another recording's logs (they would be overwritten)."""
    from dssp_data.recording import LOCK_NAME, can_log_dir  # deferred: loads msgpack, numcodecs, numpy, …

    logs = can_log_dir(out)
    if logs.is_symlink() or (logs.exists() and not logs.is_dir()):
        raise ConfigError(
            f"{logs} exists and is not a folder of CAN logs; move it away or choose another --out (nothing is deleted)"
        )
    if logs.is_dir() and any(p.name != LOCK_NAME for p in logs.iterdir()):
        raise ConfigError(
            f"{logs} holds CAN logs of a dataset that is not there ({out}); move them away or choose "
            "another --out (nothing is deleted)"
        )


def _existing_attrs(out: Path) -> dict:
    from dssp_data.replay_buffer import ReplayBufferReader  # deferred: loads msgpack, numcodecs, numpy, …

    if not out.exists():
        return {}
    return ReplayBufferReader(out, allow_incomplete_tail=True).attrs  # a broken dataset: its one-line DatasetError


def open_session(args, stack: contextlib.ExitStack, console: Console):
    """Open the devices and the dataset for ``args`` (closed by ``stack``); returns the RecordSession
    (its ``rig`` is the simulated rig, or None on a robot)."""
    # deferred: loads msgpack, numcodecs, numpy, …
    from dssp_data.pointcloud import PointCloudConfig, load_extrinsics  # deferred: loads numpy
    from dssp_data.recording import (
        ACTION_CONVENTIONS,
        DEPTH_KEY,
        RECORDED_KEYS,
        STATE_CONVENTION,
        RecordingDataset,
    )
    from dssp_data.replay_buffer_writer import dataset_lock  # deferred: loads msgpack, numcodecs, numpy, …
    from dssp_data.rerun_views import open_views  # deferred: loads numpy
    from hardware.bus_monitor import BusMonitor, ListeningArms  # deferred: loads numpy
    from hardware.clock import REAL_CLOCK  # deferred: loads numpy
    from hardware.record_session import RecordSession, SessionSettings  # deferred: loads numpy
    from hardware.recorder import Recorder, RecordThresholds, StampedCamera  # deferred: loads numpy
    from hardware.rig import Rig  # deferred: loads numpy

    sim_can = args.can.strip().lower().startswith(MUJOCO)
    sim_camera = args.camera.strip().lower() == MUJOCO
    if sim_can and args.can.strip().lower() != MUJOCO:
        raise ConfigError(f"--can {args.can}: the simulated rig has one leader/follower pair; use --can mujoco")
    if sim_can != sim_camera:
        raise ConfigError(
            "--can mujoco records the MuJoCo scene in lockstep with simulated time: it goes with --camera "
            "mujoco, and --camera mujoco with --can mujoco"
        )
    if args.auto and not sim_can and args.max_steps is None:
        raise ConfigError("--auto on a robot needs --max-steps: nothing else ends an episode")
    # one writer per dataset, before any device opens: a second session stops here, touching nothing
    lock = dataset_lock(args.out, flag="--out", doing="recorded into")
    stack.callback(lock.release)
    if check_append(args.out, kind=RECORDED_DATASET, flag="--out") == NEW:  # appends only to its own recordings
        _check_no_orphan_can_logs(args.out)
    convention = "leader_command" if args.action == "leader" else "next_state"
    thresholds = RecordThresholds.load(args.thresholds, "thresholds") if args.thresholds else RecordThresholds()
    existing = _existing_attrs(args.out)
    recorded_rate = None
    if existing.get("control_rate_hz") is not None:
        recorded_rate = check_rate(existing["control_rate_hz"], flag=f"{args.out}'s control_rate_hz attribute")
    recorded_task = existing.get("task")
    if recorded_task is not None and not isinstance(recorded_task, str):
        raise ConfigError(f"{args.out}'s task attribute is {recorded_task!r}, not a task name; fix the attribute")
    task = args.task_name or (recorded_task or ("tap" if sim_can else None))

    if args.pointcloud:
        cloud_config = PointCloudConfig.load(args.pointcloud, "point-cloud settings")
    elif existing.get("pointcloud") is not None:
        try:
            cloud_config = PointCloudConfig.from_dict(existing["pointcloud"])
        except ConfigError as exc:
            raise ConfigError(
                f"{args.out}'s pointcloud attribute: {exc} (give --pointcloud FILE, or fix the attribute)"
            ) from None
    elif sim_can:
        cloud_config = args.sim_rig.default_cloud_config()
    else:
        cloud_config = PointCloudConfig()

    views = open_views("dssp-record", args.rerun, args.rerun_save)  # before any device: a bad flag opens nothing
    if views is not None:
        stack.callback(lambda: console.event(views.close_line("steps")))
    rig = None
    if sim_can:
        seed = args.seed if args.seed is not None else _next_sim_seed(args.out)
        pace = args.sim_speed if args.sim_speed is not None else (0.0 if args.auto else 1.0)
        rig = args.sim_rig.open(task, seed, pace or None)
        stack.callback(rig.stop)
        clock = rig.clock
        rate = args.control_rate or recorded_rate or rig.control_rate_hz
        if abs(float(rate) - rig.control_rate_hz) > 1e-9:
            given = "--control-rate" if args.control_rate else f"{args.out}'s control_rate_hz attribute"
            raise ConfigError(
                f"the simulation runs at {rig.control_rate_hz:g} Hz, {given} says {rate:g}: record it at "
                f"{rig.control_rate_hz:g} Hz"
            )
        monitors = [BusMonitor(rig.channel, "virtual", clock=clock, name="sim")]
        monitors[0].start()
        stack.callback(monitors[0].stop)
        rig.start(monitors[0])
        camera = StampedCamera(rig.camera, clock=clock)
        camera_to_base = rig.camera.camera_to_base if args.extrinsics is None else load_extrinsics(args.extrinsics)
        frame = rig.camera.latest()
    else:
        from hardware.camera import TABLETOP, open_camera  # deferred: loads numpy

        if args.extrinsics is None and args.camera.strip().lower() != TABLETOP:
            raise ConfigError(
                "--extrinsics is needed with a real camera: the workspace crop is in the robot-base frame "
                '(a JSON file {"camera_to_base": 4x4})'
            )
        channels = [c.strip() for c in args.can.split(",")]
        if not 1 <= len(channels) <= 2 or any(not c for c in channels):
            raise ConfigError(f"--can {args.can!r} is invalid: give can0 or can0,can1 (left,right)")
        clock = REAL_CLOCK
        rate = args.control_rate or recorded_rate or DEFAULT_CONTROL_RATE_HZ
        raw_camera = open_camera(args.camera, serial=args.serial, color=cloud_config.use_color)
        stack.enter_context(raw_camera)
        camera_to_base = load_extrinsics(args.extrinsics) if args.extrinsics else raw_camera.camera_to_base
        monitors = [BusMonitor(ch, args.interface) for ch in channels]
        for monitor in monitors:
            stack.enter_context(monitor)
        frame = raw_camera.wait_for_frame(5.0)
        camera = StampedCamera(raw_camera)

    # Before anything is recorded or written: the followers' own joint limits, read with the one frame the recorder
    # sends (0x472), must hold the range the robot is used in (hardware.rig.Rig.check_firmware_limits).
    waiting = _AnsweredInPlace(rig) if sim_can else clock
    Rig(None, ListeningArms(monitors), camera_to_base, clock=waiting).check_firmware_limits()

    n_arms = 1 if sim_can else len(monitors)
    recorder = Recorder(
        camera,
        monitors,
        cloud_config,
        camera_to_base,
        float(rate),
        action_convention=convention,
        thresholds=thresholds,
        store_depth=not args.no_depth,
        views=views,
    )
    calibration = {
        "camera_to_base": [[float(v) for v in row] for row in camera_to_base],
        "camera_intrinsics": frame.intrinsics.to_dict(),
        "camera_depth_unit": float(frame.depth_unit),
    }
    dataset_attrs = {
        "control_rate_hz": float(rate),
        "action_convention": ACTION_CONVENTIONS[convention],
        "state_convention": STATE_CONVENTION,
        "pointcloud": cloud_config.to_dict(),
        **ObservationContract(state=piper_layout(n_arms), action=piper_layout(n_arms)).attrs(),
        **calibration,
        "generator": "dssp-record",
        "timestamps": "data/*timestamp: seconds since each episode's first step (recorder's clock)",
        **({"task": task} if task else {}),
    }
    session_tag = time.strftime("%Y%m%d-%H%M%S") + f"-{os.getpid()}"
    session = {
        "tag": session_tag,
        "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "host": socket.gethostname(),
        "camera": args.camera,
        "can": args.can,
        "interface": "virtual" if sim_can else args.interface,
        "rate_hz": float(rate),
        "clock": "simulated" if sim_can else "monotonic",
        "action_convention": convention,
        **calibration,
        "pointcloud": cloud_config.to_dict(),
        "thresholds": thresholds.to_dict(),
        "store_depth": not args.no_depth,
        "task": task,
    }
    extra_keys = RECORDED_KEYS + (() if args.no_depth else (DEPTH_KEY,))
    dataset = RecordingDataset(args.out, dataset_attrs, session, extra_keys, lock=lock)
    stack.callback(dataset.close)
    if dataset.repaired_steps:
        console.event(
            f"warning: {args.out} ended with {dataset.repaired_steps} steps of an episode whose write was "
            f"interrupted; they were cut off (every complete episode is intact)"
        )
    if dataset.calibration_changed:
        console.event("note: the camera calibration differs from the dataset's; it is stored with this session")

    settings = SessionSettings(max_steps=args.max_steps, auto=args.auto, episodes=args.episodes, task=task)
    console.event(
        f"recording into {args.out} ({dataset.n_episodes} episodes so far) at {float(rate):g} Hz, "
        f"action = {convention}" + ("" if args.auto else "; commands: s start, k keep, d discard, q quit")
    )
    return RecordSession(
        recorder,
        dataset,
        monitors,
        clock,
        settings,
        rig=rig,
        events=console.event,
        status=console.status,
        session_tag=session_tag,
    )


def record(args, stops: Stops | None = None) -> int:
    """``args`` → exit code; ``stops``: the stop request main() installed (None: installed here)."""
    return run_stoppable(_record, args, stops, "nothing was recorded")


def _record(args, stops: Stops) -> int:
    from dssp_data.recording import can_log_dir  # deferred: loads numpy

    console = Console(args.quiet)
    logs = can_log_dir(args.out)
    logs_existed = logs.exists() or logs.is_symlink()
    with contextlib.ExitStack() as stack:
        stack.callback(console.close)
        run = open_session(args, stack, console)
        controls = KeyControls() if sys.stdin.isatty() else LineControls()
        stack.callback(controls.close)
        stops.during(run.request_stop)  # a stop that came while the devices opened, or any later one
        stack.callback(stops.during, None)
        try:
            summary = run.run(controls)
        except OSError as exc:  # the disk, the dataset's directory: one line, like every other error
            raise DSSPError(f"writing {args.out} failed: {exc}") from exc

    problems = (
        f", {len(summary.kept_with_problems)} with problems (episodes {', '.join(map(str, summary.kept_with_problems))})"
        if summary.kept_with_problems
        else ""
    )
    failed = f", task failures: {summary.failed}" if summary.failed else ""
    print(
        f"kept {len(summary.kept)} episode(s) ({summary.steps} steps){problems}; discarded {summary.discarded}{failed}; "
        f"ended by: {summary.ended_by}"
    )
    if summary.n_episodes:
        print(f"dataset: {args.out} holds {summary.n_episodes} episodes; CAN logs in {logs}")
    else:  # a new dataset appears with its first kept episode; the log folder this session made holds nothing
        if not logs_existed:
            with contextlib.suppress(OSError):
                logs.rmdir()
        print(f"nothing was written: no episode was kept, so {args.out} was not created")
    return stops.code if stops.reason is not None and summary.ended_by == stops.reason else 0


def main(
    argv: list[str] | None = None,
    sim: SimulatedRig | None = None,
    prog: str = "dssp-record",
    stops: Stops | None = None,
) -> int:
    """``stops``: the stop request a caller installed before its own imports (``dssp-sim record``); None: installed
    here, first (from here every stop is a clean one), and restored at the end."""
    own = stops is None
    stops = stops or Stops()
    try:
        return run_cli(lambda: record(parse_args(argv, sim, prog), stops))
    finally:
        if own:
            stops.restore()


if __name__ == "__main__":
    sys.exit(main())

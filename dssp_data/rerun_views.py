"""Rerun views of what the robot sees and does, one control tick at a time (``--rerun``, ``--rerun-save``).

    views = open_views("dssp-run", connect=None, save=Path("run.rrd"))  # None, None: no views (returns None)
    views.camera(intrinsics, camera_to_base)                  # static: the camera's pose and pinhole
    views.tick(t, depth=..., depth_unit=..., cloud=..., state=..., command=..., chunk=..., held=..., events=[...],
               latency_ms={"cloud": 0.6, ...})              # never blocks: queued, or dropped and counted
    views.close()                                            # drains the queue; {"logged": n, "dropped": m}
    print(views.close_line())                                # the same, as the commands' one line

Everything is on the timeline ``tick`` (one step per control tick). Entities, in the robot's base frame
(metres, z up) unless said otherwise:

    world/camera             the camera's pose (camera_to_base (4, 4)), its pinhole (intrinsics, pixels)
    world/camera/depth       the depth image (H, W) uint16, ``depth_unit`` metres per unit
    world/cloud              the point cloud the policy saw (P, 3) (+ colour channels ignored), coloured by height
    world/arm{i}/gripper     the tool centre point of arm i from its joint state (forward kinematics of the Piper)
    world/arm{i}/chunk       the predicted action chunk as a ghost path of that point, (H, 3), logged on new chunks
    joints/arm{i}/state      joint state of arm i: 7 series (J1..J6 rad, gripper opening)
    joints/arm{i}/command    the command sent to arm i (7 series)
    safety/held              1 on a tick the safety layer held, else 0
    safety/events            the safety layer's events and hold reasons (text log)
    latency/{stage}          milliseconds per stage (cloud, observe, chunk, tick)
    episode                  text: the start of each episode (evaluations, recordings)

Logging never blocks the caller: :meth:`TickViews.tick` puts references to the arrays on a bounded queue (the
caller must not modify them afterwards; the control loop makes new ones every tick) and a worker thread does
the forward kinematics, colours and Rerun calls. A full queue drops the tick's views and counts it. A saved
recording is streamed to ``PATH.partial`` and put in place as ``PATH`` when closed (a crash leaves the partial file,
readable up to the last tick logged). The partial file is created new in its folder, never through a link, and
written through its own descriptor; neither it nor ``PATH`` ever replaces a file that is there.

The flags are checked once, here (:func:`check_views`, for ``dssp-run``, ``dssp-record``, ``dssp-sim eval`` and
``dssp-data view``), before the commands open anything: ``--rerun URL`` must parse as a Rerun address,
``--rerun-save`` must name a new ``.rrd`` file in an existing, writable folder, with no ``PATH.partial`` beside it.

rerun-sdk is optional (the ``viz`` extra); without it the flags fail with one line saying what to install.
"""

from __future__ import annotations

import os
import queue
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from dssp_core.errors import ConfigError
from dssp_data.arm_kinematics import ARM_VALUES, tool_points

QUEUE_SIZE = 256  # ticks of views waiting for the worker; beyond it they are dropped (and counted)
INSTALL_HINT = 'pip install -e ".[viz]" (or pip install rerun-sdk)'
JOINT_NAMES = ("J1", "J2", "J3", "J4", "J5", "J6", "gripper")
# Height colours of the point cloud: a blue → green → yellow ramp over the cloud's own height range.
_RAMP = np.array([[68, 1, 84], [33, 145, 140], [253, 231, 37]], np.float32)


def require_rerun(flag: str = "--rerun"):
    """The ``rerun`` module, or a one-line :class:`ConfigError` saying how to install it."""
    try:
        import rerun  # optional: rerun-sdk (the viz extra), only for --rerun and --rerun-save
    except ImportError:
        raise ConfigError(f"{flag} needs rerun-sdk, which is not installed: {INSTALL_HINT}") from None
    return rerun


def add_rerun_flags(parser, what: str = "each control tick") -> None:
    """``--rerun [URL]`` and ``--rerun-save PATH.rrd`` on an argparse parser."""
    parser.add_argument(
        "--rerun",
        nargs="?",
        const="spawn",
        default=None,
        metavar="URL",
        help=f"show {what} in Rerun: spawn a viewer, or connect to one at URL (e.g. rerun+http://HOST:9876/proxy)",
    )
    parser.add_argument(
        "--rerun-save",
        type=Path,
        default=None,
        metavar="PATH.rrd",
        help=f"save the Rerun views of {what} to a file (no viewer; open it later with `rerun PATH.rrd`)",
    )


def check_views(connect: str | None, save: Path | None) -> None:
    """Check ``--rerun`` / ``--rerun-save`` without opening anything: rerun-sdk is installed, ``connect`` is "spawn"
    or an address Rerun can parse, ``save`` is a new ``.rrd`` file in an existing, writable folder with no
    ``PATH.partial`` beside it (a recording is never replaced). One-line :class:`ConfigError` otherwise."""
    if connect is None and save is None:
        return
    rr = require_rerun("--rerun-save" if connect is None else "--rerun")
    if connect is not None and connect != "spawn":
        try:
            rr.GrpcSink(connect)  # parses the address; connects only once a recording is given it
        except Exception as exc:  # noqa: BLE001 - rerun's parse errors are RuntimeErrors of its own wording
            raise ConfigError(
                f"--rerun {connect!r} is not a Rerun viewer's address ({' '.join(str(exc).split())}); "
                "give e.g. rerun+http://127.0.0.1:9876/proxy, or --rerun alone to start a viewer"
            ) from None
    if save is not None:
        save = Path(save)
        if save.suffix != ".rrd" or not save.stem:
            raise ConfigError(
                f"--rerun-save {save}: a Rerun recording is a .rrd file; name it e.g. "
                f"{save.with_suffix('.rrd') if save.name else 'views.rrd'}"
            )
        if save.is_dir() and not save.is_symlink():
            raise ConfigError(f"--rerun-save {save} is a folder; give a new .rrd file name")
        if save.exists() or save.is_symlink():
            raise ConfigError(f"--rerun-save {save} exists; choose a new file name (a recording is never replaced)")
        if not save.parent.is_dir():
            what = "is not a folder" if save.parent.exists() else "does not exist; create it first"
            raise ConfigError(f"--rerun-save {save}: the folder {save.parent} {what}")
        if not os.access(save.parent, os.W_OK | os.X_OK):
            raise ConfigError(f"--rerun-save {save}: the folder {save.parent} is not writable; choose another one")
        partial = _partial(save)
        if partial.is_symlink():
            raise ConfigError(
                f"--rerun-save {save}: {partial} is a symbolic link; remove it (a recording is never "
                "written through a link)"
            )
        if partial.exists():
            raise ConfigError(
                f"--rerun-save {save}: {partial} exists (a recording that did not finish?); move it "
                "away or choose another name"
            )


def open_views(app: str, connect: str | None, save: Path | None, queue_size: int = QUEUE_SIZE) -> TickViews | None:
    """Views for ``--rerun`` (``connect``: "spawn" or a URL) and/or ``--rerun-save`` (``save``); None without either.
    Checks the flags (rerun-sdk installed, ``save`` a new ``.rrd`` file in an existing folder) before anything runs."""
    if connect is None and save is None:
        return None
    check_views(connect, save)
    rr = require_rerun()
    save = Path(save) if save is not None else None
    fd = _create_partial(save) if save is not None else None
    try:
        stream = rr.RecordingStream(app)
        sinks = []
        if save is not None:
            sinks.append(rr.FileSink(_written_path(fd, _partial(save))))
        if connect == "spawn":
            stream.spawn(connect=False)
            sinks.append(rr.GrpcSink())
        elif connect is not None:
            sinks.append(rr.GrpcSink(connect))
        stream.set_sinks(*sinks)
    except Exception as exc:  # noqa: BLE001 - a viewer that cannot start, a sink that cannot open: one line
        if fd is not None:
            _drop_partial(fd, _partial(save))
        flag = "--rerun" if connect is not None else "--rerun-save"
        raise ConfigError(f"{flag}: the Rerun views could not be opened ({' '.join(str(exc).split())})") from None
    return TickViews(stream, save=save, queue_size=queue_size, save_fd=fd)


def _partial(save: Path) -> Path:
    return save.with_name(save.name + ".partial")


def _create_partial(save: Path) -> int:
    """Create ``PATH.partial`` new, in ``PATH``'s folder, without following a link: its descriptor (a link or a
    file planted there meanwhile is refused with one line)."""
    partial = _partial(save)
    folder = os.open(save.parent, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    try:
        return os.open(
            partial.name,
            os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC | getattr(os, "O_NOFOLLOW", 0),
            0o644,
            dir_fd=folder,
        )
    except FileExistsError:
        raise ConfigError(
            f"--rerun-save {save}: {partial} appeared meanwhile (a link or another recording); move it "
            "away or choose another name"
        ) from None
    except OSError as exc:
        raise ConfigError(f"--rerun-save {save}: cannot create {partial} ({exc.strerror or exc})") from None
    finally:
        os.close(folder)


def _written_path(fd: int, partial: Path) -> str:
    """The path Rerun opens to write the recording: the descriptor's own file where the system names it
    (``/proc/self/fd/N``: whatever happens to the name meanwhile), else the partial file's name."""
    own = f"/proc/self/fd/{fd}"
    try:
        if os.path.samestat(os.stat(own), os.fstat(fd)):
            return own
    except OSError:
        pass
    return str(partial)


def _same_file(fd: int, path: Path) -> bool:
    """Whether ``path`` (not followed if a link) is still the file open as ``fd``."""
    try:
        return os.path.samestat(os.lstat(path), os.fstat(fd))
    except OSError:
        return False


def _drop_partial(fd: int, partial: Path) -> None:
    """Remove a partial file this process created (only if the name is still that file) and close it."""
    try:
        if _same_file(fd, partial):
            os.unlink(partial)
    except OSError:
        pass
    finally:
        os.close(fd)


def _publish(fd: int, save: Path) -> None:
    """Put the finished recording (the file open as ``fd``, named ``PATH.partial``) in place as ``PATH``: a new
    name for the same file, never over one that is there; then the partial name goes. Closes ``fd``."""
    partial = _partial(save)
    try:
        if not _same_file(fd, partial):
            raise ConfigError(f"{partial} was moved or replaced while the views were written; {save} was not made")
        try:
            os.link(partial, save, follow_symlinks=False)
        except FileExistsError:
            raise ConfigError(
                f"{save} appeared while the views were written; the recording stays at {partial}"
            ) from None
        os.unlink(partial)
    finally:
        os.close(fd)


def height_colors(z: np.ndarray) -> np.ndarray:
    """(P,) heights → (P, 3) uint8 colours on a blue → yellow ramp over their own range."""
    z = np.asarray(z, np.float32)
    lo, hi = (float(z.min()), float(z.max())) if z.size else (0.0, 1.0)
    u = (z - lo) / max(hi - lo, 1e-6) * (len(_RAMP) - 1)
    i = np.clip(u.astype(np.int32), 0, len(_RAMP) - 2)
    f = (u - i)[:, None]
    return ((1 - f) * _RAMP[i] + f * _RAMP[i + 1]).astype(np.uint8)


class TickViews:
    """Views of a run on the ``tick`` timeline, logged by a worker thread from a bounded queue."""

    def __init__(self, stream: Any, save: Path | None = None, queue_size: int = QUEUE_SIZE, save_fd: int | None = None):
        """``save``: the recording's final path, written as ``PATH.partial``; ``save_fd``: that partial file's
        descriptor (:func:`open_views`; None: the partial file is put in place by its name)."""
        import rerun as rr  # optional: rerun-sdk (the viz extra), only for --rerun and --rerun-save

        self._rr, self.stream, self.save, self._save_fd = rr, stream, save, save_fd
        self.logged = 0
        self.dropped = 0
        self.last_tick = -1  # the latest tick given to tick(): a next episode continues after it
        self._queue: queue.Queue = queue.Queue(maxsize=queue_size)
        self._error: BaseException | None = None
        self._closed = False
        self._named: set[str] = set()
        stream.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        self._worker = threading.Thread(target=self._work, name="rerun-views", daemon=True)
        self._worker.start()

    # ----------------------------------------------------------------------- the caller's side (cheap)
    def camera(self, intrinsics: dict, camera_to_base: np.ndarray) -> None:
        """The camera's pose (4, 4) in the base frame and its pinhole (``width, height, fx, fy, ppx, ppy`` pixels)."""
        self._put(
            ("camera", None, {"intrinsics": dict(intrinsics), "camera_to_base": np.asarray(camera_to_base, np.float64)})
        )

    def tick(self, tick: int, wait: bool = False, **views: Any) -> bool:
        """Queue one tick's views (keyword arguments, all optional): ``depth`` (H, W) uint16 with ``depth_unit`` m,
        ``cloud`` (P, C) in the base frame, ``state`` and ``command`` (7 * arms,) policy units, ``chunk``
        (H, 7 * arms) the new chunk's actions, ``held`` bool, ``events`` [str], ``latency_ms`` {stage: ms}.
        Returns False when the queue was full and the tick's views were dropped; ``wait`` (offline logging of a
        dataset, never in a control loop): wait for room instead."""
        self.last_tick = max(self.last_tick, int(tick))
        return self._put(("tick", int(tick), views), wait)

    def text(self, tick: int, entity: str, message: str) -> bool:
        """A line of text at ``entity`` (e.g. "episode") on tick ``tick``."""
        return self._put(("text", int(tick), {"entity": entity, "message": message}))

    def _put(self, item: tuple, wait: bool = False) -> bool:
        if self._closed:
            return False
        try:
            self._queue.put(item, block=wait)
            return True
        except queue.Full:
            self.dropped += 1
            return False

    def close(self, timeout: float = 30.0) -> dict[str, int]:
        """Log what is queued (waiting up to ``timeout`` s), flush, end the recording; a saved one is renamed from
        ``PATH.partial`` to ``PATH``. Returns {"logged": ticks logged, "dropped": ticks dropped}."""
        if not self._closed:
            self._closed = True
            self._queue.put(None)
            self._worker.join(timeout)
            self.stream.flush()
            self.stream.disconnect()
            if self._save_fd is not None:
                fd, self._save_fd = self._save_fd, None
                _publish(fd, self.save)
            elif self.save is not None and _partial(self.save).is_file() and not _partial(self.save).is_symlink():
                os.replace(_partial(self.save), self.save)
        if self._error is not None:
            raise ConfigError(f"the Rerun views stopped: {self._error}")
        return {"logged": self.logged, "dropped": self.dropped}

    def close_line(self, unit: str = "ticks") -> str:
        """:meth:`close`, then the one line the commands print: what was logged and dropped, and the file saved."""
        counts = self.close()
        return f"rerun views: {counts['logged']} {unit} logged, {counts['dropped']} dropped" + (
            f"; saved to {self.save}" if self.save is not None else ""
        )

    def __enter__(self) -> TickViews:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ----------------------------------------------------------------------- the worker's side
    def _work(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            if self._error is not None:
                continue  # a failed view stops logging, never the control loop; close() reports it
            kind, tick, payload = item
            try:
                if kind == "camera":
                    self._log_camera(**payload)
                elif kind == "text":
                    self.stream.set_time("tick", sequence=tick)
                    self.stream.log(payload["entity"], self._rr.TextLog(payload["message"]))
                else:
                    self._log_tick(tick, **payload)
                    self.logged += 1
            except Exception as exc:  # noqa: BLE001 - reported by close()
                self._error = exc

    def _log_camera(self, intrinsics: dict, camera_to_base: np.ndarray) -> None:
        rr, log = self._rr, self.stream.log
        log(
            "world/camera",
            rr.Transform3D(translation=camera_to_base[:3, 3], mat3x3=camera_to_base[:3, :3]),
            static=True,
        )
        log(
            "world/camera/depth",
            rr.Pinhole(
                focal_length=[intrinsics["fx"], intrinsics["fy"]],
                principal_point=[intrinsics["ppx"], intrinsics["ppy"]],
                resolution=[intrinsics["width"], intrinsics["height"]],
                camera_xyz=rr.ViewCoordinates.RDF,
            ),
            static=True,
        )

    def _log_tick(
        self,
        tick: int,
        depth=None,
        depth_unit: float | None = None,
        cloud=None,
        state=None,
        command=None,
        chunk=None,
        held: bool | None = None,
        events=(),
        latency_ms: dict | None = None,
    ) -> None:
        rr = self._rr

        def log(*args, **kwargs) -> None:  # each call, then the interpreter to a waiting control loop (sleep(0) yields)
            self.stream.log(*args, **kwargs)
            time.sleep(0)

        self.stream.set_time("tick", sequence=tick)
        if depth is not None:
            log("world/camera/depth", rr.DepthImage(depth, meter=1.0 / (depth_unit or 0.001)))
        if cloud is not None:
            xyz = np.asarray(cloud)[:, :3]
            log("world/cloud", rr.Points3D(xyz, colors=height_colors(xyz[:, 2]), radii=0.003))
        for name, value in (("state", state), ("command", command)):
            if value is not None:
                value = np.asarray(value, np.float64)
                for arm in range(value.shape[-1] // ARM_VALUES):
                    entity = f"joints/arm{arm}/{name}"
                    if entity not in self._named:  # the series' names, once
                        log(entity, rr.SeriesLines(names=[f"{name} {j}" for j in JOINT_NAMES]), static=True)
                        self._named.add(entity)
                    log(entity, rr.Scalars(value[arm * ARM_VALUES : (arm + 1) * ARM_VALUES]))
        if state is not None and np.asarray(state).shape[-1] % ARM_VALUES == 0:
            for arm, point in enumerate(tool_points(state)[0]):
                log(f"world/arm{arm}/gripper", rr.Points3D(point[None], radii=0.01))
        if chunk is not None and np.asarray(chunk).shape[-1] % ARM_VALUES == 0:
            paths = tool_points(chunk)  # (H, arms, 3)
            for arm in range(paths.shape[1]):
                log(f"world/arm{arm}/chunk", rr.LineStrips3D([paths[:, arm]], radii=0.002, colors=[[255, 140, 0, 160]]))
        if held is not None:
            log("safety/held", rr.Scalars(float(bool(held))))
        if events:
            log("safety/events", rr.TextLog("; ".join(map(str, events)), level=rr.TextLogLevel.WARN))
        for stage, ms in (latency_ms or {}).items():
            if ms is not None:
                log(f"latency/{stage}", rr.Scalars(float(ms)))

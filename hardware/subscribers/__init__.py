"""What happens on each tick of the control loop, besides control: subscribers.

    runner = Runner(source, rig, cloud_config, settings,
                    subscribers=[RunLog(log_dir, settings_dict), StatusLine(), RerunTicks(views)])

The loop (:class:`hardware.run_loop.Runner`) controls: it reads the camera and the arms, asks the policy source, passes
the action through the safety layer and sends the command. Everything else — the episode log, the live status
line, the Rerun views, a CSV of the ticks — is a :class:`Subscriber`: told when the loop has started
(:meth:`~Subscriber.on_start`), given every tick (:meth:`~Subscriber.on_tick`, a :class:`Tick`) and the summary at
the end (:meth:`~Subscriber.on_end`). A subscriber only reads: the loop has decided and sent before it is called.

``dssp-run --subscribe NAME`` adds the subscribers of :data:`REGISTRY` by name; a new one is one file in this
folder and one line in :data:`REGISTRY` (hardware/README.md, "Subscribers", has the worked example,
:mod:`hardware.subscribers.csv_log`).
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from dssp_core.errors import ConfigError

if TYPE_CHECKING:  # annotations only
    from dssp_data.pointcloud.depth_frame import DepthFrame
    from hardware.camera.base import Camera
    from hardware.robot import Robot
    from hardware.safety import SafetyConfig


class Loop(Protocol):
    """What a subscriber may use of the loop that tells it: its devices and settings, what it counts, a stop request."""

    robot: Robot
    camera: Camera | None
    camera_to_base: np.ndarray  # (4, 4)
    safety_config: SafetyConfig
    settings: Any  # the loop's settings (dry_run, max_steps, …)
    ticks: int
    holds: int
    event_counts: dict[str, int]
    latencies: dict[str, list[float]]  # "cloud", "observe", "chunk", "tick" (ms)

    def rate(self) -> float: ...
    def request_stop(self, why: str) -> None: ...


@dataclass(frozen=True)
class Tick:
    """One tick as the loop made it; the arrays are this tick's own (never changed afterwards).

    record: the tick's log record (``tick``, ``time``, ``state`` (dof,), ``action`` (dof,) or None, ``command``
        (dof,) or None, ``held``, the ages and latencies ``*_ms``, ``safety`` and ``events``);
    frame: the camera frame the tick read (None: none yet);
    cloud: the point cloud (P, C) float32 the policy saw, or None (no observation this tick);
    chunk: a new chunk's actions to come (H - offset, A) when the tick started one, else None;
    loop: the loop itself, for what it counts (``ticks``, ``holds``, ``latencies``, ``event_counts``, ``rate()``);
    scheduled: when the tick was due on the loop's clock (``record["time"]`` later than it: the tick started late).
    """

    record: dict[str, Any]
    frame: DepthFrame | None
    cloud: np.ndarray | None
    chunk: np.ndarray | None
    loop: Loop
    scheduled: float


class Subscriber:
    """Told of the loop's start, each tick and its end; every method does nothing unless overridden."""

    def on_start(self, loop: Loop) -> None:
        """The loop has its first frame and feedback and is about to tick (the arms enabled unless a dry run)."""

    def on_tick(self, tick: Tick) -> None:
        """One tick, after its command was sent (or held)."""

    def on_end(self, summary: dict[str, Any]) -> None:
        """The run ended (``summary``: :meth:`hardware.run_loop.Runner.summary`); called once, on every ending."""


REGISTRY: dict[str, str] = {
    "csv": "hardware.subscribers.csv_log:CsvLog",  # LOG_DIR/ticks.csv: one row per tick
}
"""``dssp-run --subscribe NAME``: the subscriber's class as ``module:Class``; the class is built with
``from_run(log_dir)``."""


def open_subscribers(names: list[str], log_dir: Path) -> list[Subscriber]:
    """The subscribers ``names`` of :data:`REGISTRY`, built for the run logged in ``log_dir``."""
    out = []
    for name in names:
        if name not in REGISTRY:
            raise ConfigError(f"--subscribe {name}: no such subscriber; choose from {', '.join(sorted(REGISTRY))}")
        module, _, cls = REGISTRY[name].partition(":")
        out.append(getattr(importlib.import_module(module), cls).from_run(Path(log_dir)))
    return out


def check_subscribers(names: list[str]) -> None:
    """Refuse an unknown ``--subscribe`` name before anything is opened."""
    unknown = [n for n in names if n not in REGISTRY]
    if unknown:
        raise ConfigError(f"--subscribe {unknown[0]}: no such subscriber; choose from {', '.join(sorted(REGISTRY))}")

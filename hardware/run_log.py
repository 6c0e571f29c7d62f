"""The episode log of a ``dssp-run``: what the robot saw, what was sent, how long it took, every event.

A run directory holds:
    run.json          settings at start (model, camera, intrinsics, extrinsics, safety), and the summary
                      at the end (both written atomically)
    ticks.jsonl       one JSON line per tick, flushed as it is written (survives a crash up to the last
                      tick): time, state (dof,), policy action (dof,), command sent (dof,) or null, held,
                      latencies in ms, safety events
    clouds/NNNNNN.npy the point clouds the policy saw, (n, P, C) float32 per part of ``part_size`` ticks,
                      each part written atomically (numeric .npy, no pickles)
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from dssp_core.files import atomic_save_npy, atomic_write_text
from hardware.subscribers import Subscriber, Tick


def _jsonable(value):
    if isinstance(value, np.ndarray):
        return [None if not np.isfinite(v) else float(v) for v in value.ravel()]
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


class RunLog(Subscriber):
    """The episode log (module docstring) as the control loop's subscriber: each tick appended, the summary
    written at the end."""

    def __init__(self, directory: Path, settings: dict[str, Any], part_size: int = 100):
        self.dir = Path(directory)
        (self.dir / "clouds").mkdir(parents=True, exist_ok=True)
        self.settings = settings
        self.part_size = part_size
        self._clouds: list[np.ndarray] = []
        self._parts = 0
        self.ticks = 0
        atomic_write_text(self.dir / "run.json", json.dumps({"settings": settings}, indent=2, default=_jsonable) + "\n")
        self._ticks = open(self.dir / "ticks.jsonl", "a")

    def tick(self, record: dict[str, Any], cloud: np.ndarray | None) -> None:
        """Append one tick (``cloud`` (P, C) float32, or None when no observation was taken)."""
        record = {**record, "cloud_index": None}
        if cloud is not None:
            record["cloud_index"] = self._parts * self.part_size + len(self._clouds)
            self._clouds.append(np.asarray(cloud, np.float32))
        self._ticks.write(json.dumps(record, default=_jsonable) + "\n")
        self._ticks.flush()
        self.ticks += 1
        if len(self._clouds) >= self.part_size:
            self._flush_clouds()

    def on_tick(self, tick: Tick) -> None:
        self.tick(tick.record, tick.cloud)

    def on_end(self, summary: dict[str, Any]) -> None:
        self.close(summary)

    def _flush_clouds(self) -> None:
        if self._clouds:
            atomic_save_npy(self.dir / "clouds" / f"{self._parts:06d}.npy", np.stack(self._clouds))
            self._parts += 1
            self._clouds = []

    def close(self, summary: dict[str, Any]) -> None:
        self._flush_clouds()
        self._ticks.close()
        text = json.dumps({"settings": self.settings, "summary": summary}, indent=2, default=_jsonable)
        atomic_write_text(self.dir / "run.json", text + "\n")


def read_ticks(directory: Path) -> list[dict[str, Any]]:
    """Every complete tick record of a run directory (a torn last line after a crash is ignored)."""
    records = []
    with open(Path(directory) / "ticks.jsonl") as f:
        for line in f:
            try:
                records.append(json.loads(line))
            except json.JSONDecodeError:
                break
    return records


def read_clouds(directory: Path) -> np.ndarray:
    """All logged point clouds in tick order, (n, P, C) float32."""
    parts = sorted((Path(directory) / "clouds").glob("*.npy"))
    return np.concatenate([np.load(p, allow_pickle=False) for p in parts]) if parts else np.zeros((0, 0, 3), np.float32)

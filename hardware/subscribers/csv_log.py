"""``dssp-run --subscribe csv``: one CSV row per tick in ``LOG_DIR/ticks.csv`` — the worked example of a subscriber.

Columns: tick, time (s, the loop's clock), held (0/1), the command sent (``command_0`` … one per value, empty
when nothing was sent) and the latencies in ms (cloud, observe, chunk, tick; empty when the tick had none).
Each row is flushed as it is written, so the file survives a crash up to the last tick, like ``ticks.jsonl``;
the log directory is the run's own (locked by ``dssp-run``).
"""

from __future__ import annotations

import csv
from pathlib import Path

from hardware.subscribers import Subscriber, Tick

LATENCIES = ("cloud", "observe", "chunk", "tick")


class CsvLog(Subscriber):
    def __init__(self, path: Path):
        self.path = Path(path)
        self._file = None
        self._writer = None

    @classmethod
    def from_run(cls, log_dir: Path) -> CsvLog:
        return cls(Path(log_dir) / "ticks.csv")

    def on_start(self, loop) -> None:
        dof = loop.robot.dof
        self._file = open(self.path, "x", newline="")  # a new file: never one that was there
        self._writer = csv.writer(self._file)
        self._writer.writerow(
            ["tick", "time", "held", *(f"command_{i}" for i in range(dof)), *(f"{k}_ms" for k in LATENCIES)]
        )
        self._dof = dof

    def on_tick(self, tick: Tick) -> None:
        r = tick.record
        command = r["command"]
        self._writer.writerow(
            [
                r["tick"],
                f"{r['time']:.6f}",
                int(bool(r["held"])),
                *([f"{v:.6f}" for v in command] if command is not None else [""] * self._dof),
                *("" if r.get(f"{k}_ms") is None else f"{r[f'{k}_ms']:.3f}" for k in LATENCIES),
            ]
        )
        self._file.flush()

    def on_end(self, summary) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None

"""The live one-line status of a loop: rewritten in place on a terminal, one line a second otherwise."""

from __future__ import annotations

import sys
import time

import numpy as np

from hardware.subscribers import Subscriber, Tick


class StatusPrinter:
    """Prints status lines to ``stream`` (stderr by default): in place on a terminal, else at most one a second."""

    def __init__(self, stream=None):
        stream = sys.stderr if stream is None else stream  # looked up now: the stream the stop request watches
        self.stream, self.tty, self.last = stream, stream.isatty(), 0.0

    def __call__(self, line: str) -> None:
        now = time.monotonic()  # how often a person is shown a line: wall time, whatever the loop's clock
        if self.tty:
            self.stream.write("\r" + line[:200] + "\x1b[K")
            self.stream.flush()
        elif now - self.last >= 1.0:
            self.stream.write(line + "\n")
            self.stream.flush()
            self.last = now

    def close(self) -> None:
        if self.tty:
            self.stream.write("\n")


def control_status(tick: Tick) -> str:
    """dssp-run's status line: tick, measured rate, the median latencies of the last 50 ticks, holds, events."""
    loop = tick.loop

    def p50(key):
        values = loop.latencies[key][-50:]
        return f"{np.median(values):.1f}" if values else "-"

    events = " ".join(f"{k}={v}" for k, v in sorted(loop.event_counts.items())) or "none"
    return (
        f"tick {loop.ticks:5d}  {loop.rate():5.1f} Hz  cloud {p50('cloud')} ms  observe {p50('observe')} ms  "
        f"chunk {p50('chunk')} ms  tick {p50('tick')} ms  holds {loop.holds}  events: {events}"
        + ("  [dry run]" if loop.settings.dry_run else "")
    )


class StatusLine(Subscriber):
    """The control loop's status line after every tick (:func:`control_status`), through ``printer``."""

    def __init__(self, printer=None):
        self.printer = StatusPrinter() if printer is None else printer

    def on_tick(self, tick: Tick) -> None:
        self.printer(control_status(tick))

    def on_end(self, summary) -> None:
        close = getattr(self.printer, "close", None)
        if close is not None:
            close()

"""The timing every fixed-rate loop shares: pacing to the next tick, the measured rate, latency statistics.

    pacer = Pacer(clock, period=0.1)            # resync=0: an overrun starts the schedule again from now
    pacer.start()
    while running:
        tick()
        pacer.wait()                             # sleeps on the clock to the next tick; counts overruns
    meter = RateMeter(); meter.mark(clock.now()); meter.rate()   # Hz over the last 50 ticks
    latency_stats([3.1, 2.9, 4.0])               # {"p50": 3.1, "p95": ..., "max": 4.0, "n": 3}

The control loop (:mod:`hardware.run_loop`: ``dssp-run``, ``dssp-record``, ``dssp-replay``, ``dssp-sim eval``) and
the recorder (:mod:`hardware.recorder`) pace and measure themselves with these, so a tick's deadline, an overrun and
a p95 mean the same thing in each.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterable

import numpy as np

from hardware.clock import Clock

RATE_WINDOW = 50
"""Ticks the measured rate is taken over (:class:`RateMeter`)."""


class Pacer:
    """Ticks every ``period`` seconds of ``clock``.

    :meth:`wait` sleeps until the next tick's time. A tick that ends after that time is an **overrun**
    (counted); when it ends more than ``resync`` seconds late, the schedule starts again from now, so the loop
    does not race to catch up. ``resync=0`` (the control loop) starts again after every overrun; the recorder
    allows up to one period of lag (``LoopSettings(resync=period)``), so that its samples stay on one grid through a short
    stall.
    """

    def __init__(self, clock: Clock, period: float, resync: float = 0.0) -> None:
        if not period > 0:
            raise ValueError(f"a tick period must be positive, got {period!r}")
        if not resync >= 0:
            raise ValueError(f"resync must be >= 0 s, got {resync!r}")
        self.clock, self.period, self.resync = clock, float(period), float(resync)
        self.next_tick = clock.now()
        self.overruns = 0

    def start(self) -> None:
        """The schedule starts now: the first :meth:`wait` returns one period from here."""
        self.next_tick = self.clock.now()

    def wait(self) -> bool:
        """Sleep to the next tick; False when the tick overran (then nothing was slept)."""
        self.next_tick += self.period
        delay = self.next_tick - self.clock.now()
        if delay > 0:
            self.clock.sleep(delay)
            return True
        self.overruns += 1
        if -delay > self.resync:  # (exactly on time, delay == 0, the schedule is now anyway)
            self.next_tick = self.clock.now()
        return False


class RateMeter:
    """The measured tick rate (Hz) over the last :data:`RATE_WINDOW` marked ticks."""

    def __init__(self, window: int = RATE_WINDOW) -> None:
        self._times: deque = deque(maxlen=window)

    def mark(self, t: float) -> None:
        self._times.append(float(t))

    def rate(self) -> float:
        """Ticks per second between the first and the last marked tick of the window; 0 before two ticks."""
        t = self._times
        return (len(t) - 1) / max(t[-1] - t[0], 1e-9) if len(t) >= 2 else 0.0


def latency_stats(values: Iterable[float], digits: int | None = None) -> dict | None:
    """``{"p50", "p95", "max", "n"}`` of the finite ``values`` (ms, say); None when there are none.
    ``digits``: round the three figures (a dataset's metadata keeps 3)."""
    v = np.asarray([x for x in values if math.isfinite(x)], dtype=np.float64)
    if v.size == 0:
        return None
    figures = {"p50": float(np.median(v)), "p95": float(np.percentile(v, 95)), "max": float(v.max())}
    if digits is not None:
        figures = {k: round(x, digits) for k, x in figures.items()}
    return {**figures, "n": int(v.size)}

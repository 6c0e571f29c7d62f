"""``CanReader``: one python-can bus and the daemon thread that receives from it.

    reader = CanReader("can0", "socketcan", name="piper-rx-can0", on_frame=handle, counts=decoder.counts)
    reader.start()      # open the bus (CanError), start the thread
    ...
    reader.close()      # stop the thread, shut the bus down

The thread calls ``bus.recv`` until stopped and hands every frame to ``on_frame(frame)``. A failed receive
(one bad udp_multicast datagram) is counted in ``counts["receive_error"]`` and skipped;
``MAX_RECEIVE_FAILURES`` failures in a row, or an exception from ``on_frame`` or ``tick``, end the thread:
the exception is kept in ``error`` (unless it came while stopping) and passed to ``on_error``.
``open()`` alone opens the bus without a thread (a node that only sends, or one stepped by hand).
"""

from __future__ import annotations

import collections
import threading
from collections.abc import Callable, MutableMapping

import can

from dssp_core.errors import CanError
from hardware.piper.bus import open_bus

MAX_RECEIVE_FAILURES = 10  # consecutive receive errors before the bus is taken as failed
RECEIVE_TIMEOUT = 0.05  # s: how long one recv waits, so that a stop is seen promptly


class CanReader:
    """``channel`` on ``interface`` (``bus_options`` go to ``can.Bus``), read by a thread called ``name``.

    ``tick()``, if given, is called before every receive and returns how long that receive may wait (s);
    without it each waits ``RECEIVE_TIMEOUT``. ``bus`` is the open bus (None when closed).
    """

    def __init__(
        self,
        channel: str,
        interface: str,
        bus_options: dict | None = None,
        *,
        name: str = "",
        on_frame: Callable[[can.Message], None] | None = None,
        counts: MutableMapping[str, int] | None = None,
        tick: Callable[[], float] | None = None,
        on_error: Callable[[BaseException], None] | None = None,
    ) -> None:
        self.channel, self.interface = channel, interface
        self.bus_options = dict(bus_options or {})
        self.name = name or f"can-rx-{channel}"
        self.on_frame, self.tick, self.on_error = on_frame, tick, on_error
        self.counts = collections.Counter() if counts is None else counts
        self.bus: can.BusABC | None = None
        self.error: BaseException | None = None
        """Why the thread ended early, or None."""
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def open(self) -> can.BusABC:
        """Open the bus unless it is open; returns it. Raises CanError."""
        if self.bus is None:
            self.bus = open_bus(self.channel, self.interface, **self.bus_options)
            self.error = None
        return self.bus

    def start(self) -> None:
        """Open the bus and start the receive thread (no-op while it runs). Raises CanError."""
        bus = self.open()
        if self.running:
            return
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, args=(bus,), name=self.name, daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop the receive thread (waits up to 2 s for it); the bus stays open."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None

    def close(self) -> None:
        """Stop the thread and shut the bus down (idempotent). Raises CanError if the shutdown fails."""
        self.stop()
        bus, self.bus = self.bus, None
        if bus is not None:
            try:
                bus.shutdown()
            except (can.CanError, OSError) as exc:
                raise CanError(f"closing CAN bus {self.channel!r} failed: {exc}") from exc

    @property
    def running(self) -> bool:
        """The receive thread is alive."""
        return self._thread is not None and self._thread.is_alive()

    def _run(self, bus: can.BusABC) -> None:
        failures = 0
        try:
            while not self._stop.is_set():
                timeout = RECEIVE_TIMEOUT if self.tick is None else self.tick()
                try:
                    frame = bus.recv(timeout=timeout)
                except (can.CanError, OSError, ValueError):
                    self.counts["receive_error"] += 1
                    failures += 1
                    if failures >= MAX_RECEIVE_FAILURES:
                        raise
                    continue
                failures = 0
                if frame is not None and self.on_frame is not None:
                    self.on_frame(frame)
        except Exception as exc:  # kept for the owner, who raises it on its next call
            if not self._stop.is_set():
                self.error = exc
                if self.on_error is not None:
                    self.on_error(exc)

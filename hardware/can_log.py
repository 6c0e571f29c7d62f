"""Raw CAN traffic to a log file, from a listener of its own on the same bus.

    with BusRecorder("can0", "socketcan", "runs/x/can0.blf"):
        ...   # every frame on can0 (commands and feedback) goes to the file

python-can's ``Logger`` picks the format from the suffix (``.blf``, ``.asc``, ``.csv``, ``.log``);
``can.LogReader`` reads it back. SocketCAN and python-can's ``virtual`` interface deliver every frame to
every bus opened on the channel, so a second bus sees both directions. (A ``udp_multicast`` sender does
not see its own frames on another socket of the same process: record those from another process.)
"""

from __future__ import annotations

import threading
from pathlib import Path

import can
from can.util import channel2int

from dssp_core.errors import CanError
from hardware.piper.bus import open_bus


class BusRecorder:
    def __init__(self, channel: str, interface: str, path: Path, **bus_options):
        self.channel, self.interface, self.path = channel, interface, Path(path)
        self.bus_options = bus_options
        self._bus = self._logger = None
        self._thread: threading.Thread | None = None
        # BLF/ASC store a channel number: python-can takes the name's trailing digits ("can0" → 0), which for a
        # generated name ("dssp-sim-b1996431") overflow the format's 16 bits; such frames are logged on the
        # file's own channel (one file per bus).
        number = channel2int(channel)
        self._renamed = number is not None and not 0 <= number < 0xFFFF
        self._stop = threading.Event()

    def start(self) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._bus = open_bus(self.channel, self.interface, **self.bus_options)
        try:
            self._logger = can.Logger(str(self.path))
        except (ValueError, OSError) as exc:
            self._bus.shutdown()
            raise CanError(f"cannot write the CAN log {self.path}: {exc}; use a .blf, .asc, .csv or .log path") from exc
        self._stop.clear()
        self._thread = threading.Thread(target=self._record, name=f"can-log-{self.channel}", daemon=True)
        self._thread.start()

    def _record(self) -> None:
        while not self._stop.is_set():
            frame = self._bus.recv(timeout=0.05)
            if frame is not None:
                self._write(frame)

    def _write(self, frame: can.Message) -> None:
        if self._renamed:
            frame.channel = None
        self._logger(frame)

    def stop(self) -> None:
        """Stop, after writing every frame that reached this listener (none is left in its queue)."""
        if self._thread is not None:
            self._stop.set()
            self._thread.join()
            while (frame := self._bus.recv(timeout=0.0)) is not None:
                self._write(frame)
        if self._logger is not None:
            self._logger.stop()
        if self._bus is not None:
            self._bus.shutdown()
        self._bus = self._logger = self._thread = None

    def __enter__(self) -> "BusRecorder":
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


def read_log(path: Path) -> list[can.Message]:
    """Every frame of a log file, in order."""
    with can.LogReader(str(path)) as reader:
        return list(reader)

"""``dssp-sim-arm``: run simulated AgileX Piper arms on CAN buses until stopped (or --duration).

Any signal whose default would end the process (SIGINT, SIGTERM, SIGHUP, ...; :mod:`hardware.cli.stops`) stops
the simulators cleanly, exit code 0: stopping is how this command ends.

Each channel gets one ``hardware.piper.can_simulator.SimulatedPiper``. Between processes use ``udp_multicast``: each
channel is a multicast group address; frames stay on this host (hop limit 0).
"""

from __future__ import annotations

import argparse
import ipaddress
import sys
import threading
import time

from dssp_core.cli_runner import ArgumentParser, run_cli
from dssp_core.errors import HardwareError
from hardware.cli.stops import Stops

EPILOG = """\
channels:
  udp_multicast  one IPv4/IPv6 multicast group address per arm, e.g. 239.74.163.2 (python-can's default)
                 or 239.74.163.2,239.74.163.3 for two arms; all processes of one setup use the same --port.
                 Frames never leave this host (hop limit 0). Clients you start yourself (e.g. piper-sdk)
                 need CAN_CONFIG='{"hop_limit": 0, "port": PORT}' in their environment.
  virtual        in-process channel names: only useful inside one Python process (tests).

example:
  dssp-sim-arm --channel 239.74.163.2,239.74.163.3
  then, in another process: hardware.piper.open_robot("239.74.163.2,239.74.163.3", interface="udp_multicast")
"""


def _channels(text: str, interface: str) -> list[str]:
    channels = [c.strip() for c in text.split(",")]
    if not text.strip() or any(not c for c in channels):
        raise argparse.ArgumentTypeError(f"--channel {text!r} is empty or has an empty name")
    if len(set(channels)) != len(channels):
        raise argparse.ArgumentTypeError(f"--channel {text!r} names a channel twice")
    if interface == "udp_multicast":
        for c in channels:
            try:
                ok = ipaddress.ip_address(c).is_multicast
            except ValueError:
                ok = False
            if not ok:
                raise argparse.ArgumentTypeError(
                    f"--channel {c!r} is not a multicast group address: use e.g. 239.74.163.2 with udp_multicast"
                )
    return channels


class _ArgumentError(Exception):
    pass


class _Parser(ArgumentParser):
    def error(self, message):  # ArgumentParser's one line, returned by main as exit code 2 (not a SystemExit)
        raise _ArgumentError(f"{self.prog}: {message} (see {self.prog} --help)")


def _parser() -> argparse.ArgumentParser:
    p = _Parser(
        prog="dssp-sim-arm",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=EPILOG,
        description="Simulated AgileX Piper arms speaking the Piper CAN protocol, one per channel.",
    )
    p.add_argument("--channel", required=True, help="channel per arm, comma-separated (see below)")
    p.add_argument(
        "--interface",
        default="udp_multicast",
        choices=("udp_multicast", "virtual"),
        help="python-can interface (default: udp_multicast)",
    )
    p.add_argument(
        "--port",
        type=int,
        default=None,
        help="UDP port for udp_multicast (default: python-can's 43113, or CAN_CONFIG's port)",
    )
    p.add_argument("--feedback-rate", type=float, default=200.0, help="feedback rate in Hz (default: 200)")
    p.add_argument(
        "--duration", type=float, default=None, help="stop after this many seconds (default: run until SIGINT/SIGTERM)"
    )
    return p


def main(argv: list[str] | None = None) -> int:
    """Run the simulators; exit code 0 after SIGINT/SIGTERM or --duration, 2 on bad input or a bus error."""
    try:
        args = _parser().parse_args(argv)
        channels = _channels(args.channel, args.interface)
        if not (args.feedback_rate > 0 and args.feedback_rate <= 2000):
            raise _ArgumentError(f"--feedback-rate {args.feedback_rate:g} is out of range: give 0 < rate <= 2000 Hz")
        if args.duration is not None and not args.duration > 0:
            raise _ArgumentError(f"--duration {args.duration:g} must be > 0 seconds")
        if args.port is not None and not 1 <= args.port <= 65535:
            raise _ArgumentError(f"--port {args.port} is out of range 1..65535")
    except (_ArgumentError, argparse.ArgumentTypeError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return run_cli(lambda: _run(args, channels))


def _run(args, channels: list[str]) -> int:
    from hardware.piper.can_simulator import SimulatedPiper  # deferred: loads can, numpy

    options = {"port": args.port} if args.port is not None and args.interface == "udp_multicast" else {}
    sims = [SimulatedPiper(c, args.interface, rate=args.feedback_rate, bus_options=options) for c in channels]
    stop = threading.Event()
    stops = Stops(streams=False)
    stops.during(lambda _why: stop.set())
    started = []
    start_time = time.monotonic()
    failure: HardwareError | None = None
    try:
        for sim in sims:
            sim.start()
            started.append(sim)
        port = f", port {args.port}" if options else ""
        print(
            f"dssp-sim-arm: {len(sims)} simulated Piper arm(s) on {args.interface} {','.join(channels)}"
            f"{port} at {args.feedback_rate:g} Hz; stop with Ctrl-C or SIGTERM",
            flush=True,
        )
        deadline = None if args.duration is None else start_time + args.duration
        while not stop.is_set():
            if deadline is not None and time.monotonic() >= deadline:
                break
            if any(not sim.running for sim in started):
                break  # a simulator stopped on an error: reported below
            stop.wait(0.05)
    finally:
        for sim in started:
            try:
                sim.stop()
            except HardwareError as exc:
                failure = failure or exc
        stops.restore()
    elapsed = time.monotonic() - start_time
    summary = "; ".join(
        f"{sim.channel}: {sim.ticks} ticks, {sim.frames_sent} frames sent, {sim.commands_received} commands received"
        for sim in started
    )
    print(f"dssp-sim-arm: stopped after {elapsed:.1f} s; {summary}", flush=True)
    if failure is not None:
        raise failure
    return 0


if __name__ == "__main__":
    sys.exit(main())

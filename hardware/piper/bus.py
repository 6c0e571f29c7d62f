"""Open a python-can bus for a Piper arm, with one-line ``CanError``s instead of python-can's exceptions.

Interfaces: ``socketcan`` (a real arm: channel ``can0``), ``virtual`` (in-process: buses with the same
channel name see each other's frames) and ``udp_multicast`` (between processes on this host: the channel
is a multicast group address such as python-can's default ``239.74.163.2``). For ``udp_multicast`` the
hop limit is always 0, so frames never leave this host, and the socket receives only its own group
(Linux otherwise delivers every group joined on the host to every socket bound to the same port).
"""

from __future__ import annotations

import socket
import sys
from typing import TYPE_CHECKING

from dssp_core.errors import CanError

if TYPE_CHECKING:
    import can

INTERFACES = ("socketcan", "virtual", "udp_multicast")
DEFAULT_UDP_PORT = 43113  # python-can's default port for udp_multicast

_IP_MULTICAST_ALL = getattr(socket, "IP_MULTICAST_ALL", 49)  # Linux values
_IPV6_MULTICAST_ALL = getattr(socket, "IPV6_MULTICAST_ALL", 29)


def interface_name(text: str) -> str:
    """``--interface``: a python-can interface name (argparse ``type=``: checked when the flags are parsed, before
    anything opens; python-can's own error would come only when the bus opens)."""
    import argparse

    import can  # deferred: python-can loads only when a command checks its flags or opens a bus

    valid = can.interfaces.VALID_INTERFACES
    if text not in valid:
        raise argparse.ArgumentTypeError(
            f"{text!r} is not a python-can interface; use one of {', '.join(sorted(valid))}"
        )
    return text


def _hint(channel: str, interface: str) -> str:
    if interface == "socketcan":
        return f"bring the interface up (sudo ip link set {channel} up type can bitrate 1000000) and check the cable"
    if interface == "udp_multicast":
        return "the channel must be a multicast group address such as 239.74.163.2 (and msgpack installed)"
    return "check the channel name and interface"


def _only_own_group(bus: can.BusABC, channel: str) -> None:
    """Make a udp_multicast socket receive only its own group (Linux; elsewhere groups already separate)."""
    if not sys.platform.startswith("linux"):
        return
    v6 = ":" in channel
    family = socket.AF_INET6 if v6 else socket.AF_INET
    sock = socket.fromfd(bus.fileno(), family, socket.SOCK_DGRAM)  # a duplicate of the bus's socket
    try:
        if v6:
            sock.setsockopt(socket.IPPROTO_IPV6, _IPV6_MULTICAST_ALL, 0)
        else:
            sock.setsockopt(socket.IPPROTO_IP, _IP_MULTICAST_ALL, 0)
    finally:
        sock.close()


def open_bus(channel: str, interface: str = "socketcan", **options) -> can.BusABC:
    """Open ``channel`` on ``interface``; ``options`` go to ``can.Bus`` (e.g. ``port`` for udp_multicast).

    Raises CanError (one line) if the bus cannot be opened. ``hop_limit`` is forced to 0 for udp_multicast.
    """
    import can  # deferred: python-can loads only when a command checks its flags or opens a bus

    if not channel:
        raise CanError("empty CAN channel name: give e.g. can0 (socketcan) or 239.74.163.2 (udp_multicast)")
    if interface == "udp_multicast":
        options["hop_limit"] = 0  # the port comes from options, CAN_CONFIG, or python-can's default 43113
    try:
        bus = can.Bus(channel=channel, interface=interface, **options)
    except (can.CanError, OSError, ValueError, ImportError, RuntimeError, NotImplementedError) as exc:
        reason = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise CanError(f"cannot open CAN bus {channel!r} ({interface}): {reason}; {_hint(channel, interface)}") from exc
    if interface == "udp_multicast":
        try:
            _only_own_group(bus, channel)
        except OSError as exc:
            bus.shutdown()
            raise CanError(f"cannot configure multicast group {channel!r}: {exc}; {_hint(channel, interface)}") from exc
    return bus

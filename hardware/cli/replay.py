"""``dssp-replay``: send a recorded episode's actions to the arms through the safety layer (a dry run unless --send).

    dssp-replay PATH --episode K [--can can0[,can1]|sim] [--send] [--control-rate HZ] [--safety FILE] [--interface IF]

It is ``dssp-run``'s control loop with the recorded episode as its policy source (:mod:`hardware.episode_replay`).
Without ``--can`` the episode runs against ideal tracking (no arm, a simulated clock: as fast as it computes); with
``--can`` but without ``--send`` the arms are read, never commanded, at the replay's rate. Every way the process is
stopped — any signal whose default would end it (Ctrl-C,
SIGTERM, SIGHUP, ...), or stdout/stderr going away (:mod:`hardware.cli.stops`) — stops between two commands and
holds; exit code 128 + N for signal N (130 SIGINT, 143 SIGTERM, ...), 141 when stdout or stderr went away.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from dssp_core.cli_runner import ArgumentParser, run_cli
from hardware.cli.stops import Stops
from hardware.piper.bus import interface_name


def build_parser() -> argparse.ArgumentParser:
    p = ArgumentParser(
        prog="dssp-replay", description="Send an episode's actions through the safety layer (dry run by default)."
    )
    p.add_argument("path", type=Path)
    p.add_argument("--episode", type=int, required=True)
    p.add_argument("--can", help="can0[,can1] (left, right) | sim | sim:2; without it: dry run without an arm")
    p.add_argument(
        "--interface", default="socketcan", type=interface_name, help="python-can interface (default: socketcan)"
    )
    p.add_argument("--send", action="store_true", help="enable the arms and command them (otherwise nothing is sent)")
    p.add_argument("--control-rate", type=float, help="replay rate in Hz (default: the dataset's control rate)")
    p.add_argument("--safety", type=Path, help="safety settings JSON (hardware.safety.SafetyConfig fields)")

    return p


def _replay(args, stops: Stops) -> int:
    from hardware.episode_replay import replay_episode  # deferred: loads msgpack, numcodecs, numpy, …
    from hardware.safety import SafetyConfig  # deferred: loads numpy

    safety = SafetyConfig.load(args.safety, "safety") if args.safety else SafetyConfig()
    if stops.reason is not None:
        print(f"stopped by {stops.reason} before the replay started; nothing was sent", file=sys.stderr)
        return stops.code
    result = replay_episode(
        args.path,
        args.episode,
        args.can,
        send=args.send,
        interface=args.interface,
        control_rate_hz=args.control_rate,
        safety_config=safety,
        attach_stop=stops.during,
    )
    stopped = stops.reason is not None and result["ended_by"] == stops.reason
    mode = (
        f"sent {result['sent']} commands to {args.can}"
        if args.send
        else (f"dry run on {args.can} (nothing sent)" if args.can else "dry run without an arm (ideal tracking)")
    )
    print(f"episode {result['episode']}: {result['steps']} actions at {result['rate_hz']:g} Hz, {mode}")
    print(
        f"safety: {result['clips']} clips, {result['holds']} holds, {result['refused']} refused; largest change to a "
        f"recorded action {result['max_change']:.4f}; first action {result['start_distance']:.3f} from the start"
    )
    if result["tracking_error"] is not None:
        print(f"final tracking error {result['tracking_error']:.4f} (policy units)")
    print(f"ended by: {result['ended_by']}")
    if result["fault"]:
        return 1
    return stops.code if stopped else 0


def main(argv: list[str] | None = None) -> int:
    stops = Stops()  # first: from here every stop is a clean one
    try:
        args = build_parser().parse_args(argv)
        return run_cli(lambda: _replay(args, stops))
    finally:
        stops.restore()


if __name__ == "__main__":
    sys.exit(main())

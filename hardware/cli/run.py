"""``dssp-run``: run an exported DSSP model on the robot (or on the embedded simulated one).

    dssp-run --model MODEL_DIR --camera l515|d435|d405|file:PATH|sim --can can0[,can1]|sim[:2]
             [--rate HZ] [--extrinsics FILE] [--pointcloud FILE] [--safety FILE] [--max-steps N] [--dry-run]
             [--log-dir DIR] [--prefetch] [--threads N] [--precision fp32|int8] [--seed S] [--serial SERIAL] [--interface socketcan]

Opens the camera and the arm(s), warms the model up, then runs the control loop (``hardware.run_loop``):
the history every tick, a new chunk every H_a ticks, every command through the safety layer. Prints a
live one-line status, writes the episode log (``hardware.run_log``) and ends with a summary.
Exit codes: 0 done, 1 ended by a fault (arm error, e-stop, send failure), 2 bad input, 130 stopped by a signal.
"""

from __future__ import annotations

import argparse
import contextlib
import signal
import sys
import time
from pathlib import Path

import numpy as np

from dssp_deploy.manifest import PRECISIONS
from dssp_train.cli.common import read_json_object
from dssp_train.errors import ConfigError

EPILOG = """\
--camera sim --can sim runs everything against the embedded simulation (no hardware). Real arms:
--can can0 (one Piper) or can0,can1 (two: left, right; 14 values). --dry-run computes the actions and
logs them without enabling or commanding the arms (feedback is still read).
"""


def parse_args(argv):
    p = argparse.ArgumentParser(prog="dssp-run", description="Run a DSSP model on the robot.", epilog=EPILOG,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model", type=Path, required=True, help="model directory (python -m export.to_onnx)")
    p.add_argument("--camera", default="sim", help="l515 | d435 | d405 | file:PATH (.bag/.db3) | sim (default: sim)")
    p.add_argument("--serial", help="RealSense serial number, when several are connected")
    p.add_argument("--can", default="sim", help="can0[,can1] (one bus per arm: left, right) | sim | sim:2 (default: sim)")
    p.add_argument("--interface", default="socketcan", help="python-can interface of real buses (default: socketcan)")
    p.add_argument("--rate", type=float, help="control rate in Hz (default: the model's training rate)")
    p.add_argument("--extrinsics", type=Path, help="camera→robot-base calibration JSON (default: identity)")
    p.add_argument("--pointcloud", type=Path, help="point-cloud pipeline settings JSON (crop box, voxel, clip)")
    p.add_argument("--safety", type=Path, help="safety settings JSON (hardware.safety.SafetyConfig fields)")
    p.add_argument("--max-steps", type=int, help="stop after N ticks (default: until Ctrl-C)")
    p.add_argument("--dry-run", action="store_true", help="compute and log actions, send nothing")
    p.add_argument("--prefetch", action="store_true", help="compute each chunk early in a background thread")
    p.add_argument("--threads", type=int, help="ONNX Runtime threads (default: all CPUs)")
    p.add_argument("--precision", choices=sorted(PRECISIONS), default="fp32",
                   help="the model's fp32 graphs, or its int8 graphs (export --quantize int8)")
    p.add_argument("--seed", type=int, help="diffusion noise seed (default: random)")
    p.add_argument("--log-dir", type=Path, help="episode log directory (default: runs/dssp-run/YYYYmmdd-HHMMSS)")
    p.add_argument("--no-can-log", action="store_true", help="do not write the raw CAN traffic (.blf per bus) into the log")
    p.add_argument("--quiet", action="store_true", help="no live status line")
    return p.parse_args(argv)


class StatusPrinter:
    """The live one-line status: rewritten in place on a terminal, one line a second otherwise."""

    def __init__(self, stream=sys.stderr):
        self.stream, self.tty, self.last = stream, stream.isatty(), 0.0

    def __call__(self, line: str) -> None:
        now = time.monotonic()
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


def run(args) -> int:
    from dssp_deploy.policy import OnnxPolicy
    from hardware.camera import open_camera
    from hardware.can_log import BusRecorder
    from hardware.piper.limits import JointLimits
    from hardware.piper.robot import open_robot
    from hardware.pointcloud import PointCloudConfig, load_extrinsics
    from hardware.run_log import RunLog
    from hardware.run_loop import LoopSettings, Runner, check_fits
    from hardware.safety import SafetyConfig

    safety_config = SafetyConfig.from_dict(read_json_object(args.safety, "safety")) if args.safety else SafetyConfig()
    simulated_camera = args.camera.strip().lower() == "sim"
    if args.extrinsics:
        camera_to_base = load_extrinsics(args.extrinsics)
    elif not simulated_camera:
        raise ConfigError(
            "--extrinsics is needed with a real camera or a recording: the workspace crop is in the robot-base frame "
            "(a JSON file {\"camera_to_base\": 4x4}; see the README's calibration section)"
        )
    print(f"loading {args.model} (warm-up included)", file=sys.stderr)
    policy = OnnxPolicy(args.model, threads=args.threads, precision=args.precision)
    n_points = policy.manifest["model_config"]["n_points"]
    if args.pointcloud:
        cloud_config = PointCloudConfig.from_dict(read_json_object(args.pointcloud, "point-cloud settings"))
    else:
        cloud_config = PointCloudConfig(n_points=n_points)
    rate = args.rate or policy.control_rate_hz or 10.0
    settings = LoopSettings(rate_hz=rate, max_steps=args.max_steps, dry_run=args.dry_run, prefetch=args.prefetch, seed=args.seed)
    log_dir = args.log_dir or Path("runs/dssp-run") / time.strftime("%Y%m%d-%H%M%S")

    robot = open_robot(args.can, interface=args.interface)
    check_fits(policy, robot, cloud_config)  # before any device is opened
    n_arms = robot.dof // 7
    limits = JointLimits.piper()
    lower, upper = np.tile(limits.lower, n_arms), np.tile(limits.upper, n_arms)
    gripper = np.tile(np.arange(7) == 6, n_arms)

    camera = open_camera(args.camera, serial=args.serial)
    if simulated_camera and not args.extrinsics:
        camera_to_base = camera.camera_to_base  # the simulated camera's own mounting
    recorders = [] if args.no_can_log else [
        BusRecorder(arm.channel, arm.interface, log_dir / f"can_{arm.channel}.blf", **arm.bus_options) for arm in robot.arms
    ]
    status = None if args.quiet else StatusPrinter()
    with contextlib.ExitStack() as stack:
        stack.enter_context(camera)
        stack.enter_context(robot)  # connect: simulators start first, so the recorders find their channels
        for recorder in recorders:
            stack.enter_context(recorder)
        log = RunLog(log_dir, {
            "model": str(args.model), "camera": args.camera, "can": args.can, "rate_hz": rate, "dry_run": args.dry_run,
            "camera_to_base": camera_to_base, "pointcloud": cloud_config.to_dict(), "safety": safety_config.to_dict(),
            "manifest": {k: policy.manifest[k] for k in ("denoise_steps", "control_rate_hz") if k in policy.manifest},
        })
        runner = Runner(policy, camera, robot, cloud_config, camera_to_base, safety_config, settings,
                        (lower, upper, gripper), log=log, status=status)
        handlers = {}
        for sig in (signal.SIGINT, signal.SIGTERM):
            handlers[sig] = signal.signal(sig, lambda signum, _frame: runner.request_stop(signal.Signals(signum).name))
        try:
            summary = runner.run()
        finally:
            for sig, handler in handlers.items():
                signal.signal(sig, handler)
            if status is not None:
                status.close()
            log.close(runner.summary())
    print_summary(summary, log_dir)
    if summary["fault"]:
        return 1
    return 130 if runner.stop_reason in ("SIGINT", "SIGTERM") else 0


def print_summary(summary: dict, log_dir: Path) -> None:
    lat = summary["latency_ms"]

    def fmt(key):
        s = lat.get(key)
        return f"{s['p50']:.1f} / {s['p95']:.1f} / {s['max']:.1f}" if s else "-"

    print(f"ticks {summary['ticks']} ({summary['policy_ticks']} with the policy), {summary['rate_hz']:.1f} Hz "
          f"(target {summary['target_rate_hz']:g}), commands sent {summary['commands_sent']}, holds {summary['holds']}"
          + (" [dry run]" if summary["dry_run"] else ""))
    print(f"latency p50 / p95 / max ms: cloud {fmt('cloud')}, observe {fmt('observe')}, chunk {fmt('chunk')}, tick {fmt('tick')}")
    print(f"safety events: {summary['events'] or 'none'}; ended by: {summary['ended_by']}")
    print(f"episode log: {log_dir}")


def main(argv: list[str] | None = None) -> int:
    from dssp_train.cli.common import run_cli

    args = parse_args(argv)
    return run_cli(lambda: run(args))


if __name__ == "__main__":
    sys.exit(main())

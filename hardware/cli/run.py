"""``dssp-run``: run an exported DSSP model on the robot (or on the embedded simulated one).

    dssp-run --model MODEL_DIR | --policy NAME[:ARG]  --camera l515|d435|d405|file:PATH|tabletop --can can0[,can1]|sim[:2]
             [--control-rate HZ] [--extrinsics FILE] [--pointcloud FILE] [--safety FILE] [--max-steps N] [--dry-run]
             [--log-dir DIR] [--prefetch | --smoothing none|ensemble|rtc [--ensemble-every N] [--ensemble-decay M]]
             [--threads N] [--precision fp32|int8|int4] [--kernel auto|fused|standard] [--seed S] [--serial SERIAL] [--interface socketcan]
             [--allow-mismatch FIELD ...] [--rerun [URL]] [--rerun-save PATH.rrd]

Opens the camera and the arm(s), warms the model up, then runs the control loop (``hardware.run_loop``):
the history every tick, a new chunk every H_a ticks (``--smoothing ensemble``: a chunk every ``--ensemble-every``
ticks, the action the weighted mean of the kept chunks' predictions for the tick,
:mod:`dssp_deploy.schedules`), every command through the safety layer. ``--policy NAME[:ARG]``
runs another policy source of :data:`hardware.policies.REGISTRY` in the same loop instead of a model (``hold``: the
arm held where it starts, a check of the rig; ``episode:PATH.zarr@K``: a recorded episode's actions). Prints a
live one-line status, writes the episode log (``hardware.run_log``) and ends with a summary; ``--rerun`` /
``--rerun-save`` also show each tick in Rerun (:mod:`dssp_data.rerun_views`).
The model carries its observation contract (``dssp_model.json`` ``observation`` and ``control_rate_hz``: the
point-cloud settings, the state/action layout per arm, the control rate); its point-cloud settings are the
default, and a setup that contradicts it (``--pointcloud``, ``--can`` with another number of arms, ``--control-rate``)
is refused before anything is opened, one line naming the field, both values and ``--allow-mismatch FIELD``.
Every way the process is stopped — any signal whose default would end it (SIGINT, SIGTERM, SIGHUP, SIGQUIT, ...),
or stdout/stderr going away — is one stop request (:mod:`hardware.cli.stops`): the loop ends in its final hold (and
disables the motors if the safety settings say so), the log and the summary name the true reason.
Exit codes: 0 done, 1 ended by a fault (arm error, e-stop, send failure), 2 bad input, 128 + N stopped by signal N
(130 SIGINT, 143 SIGTERM, 129 SIGHUP, ...), 141 stdout or stderr went away.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import sys
import time
from pathlib import Path

from dssp_core.cli_runner import ArgumentParser, run_cli
from dssp_core.errors import ConfigError, OutputError
from dssp_core.output_guard import OutputKind, check_output, claim_dir

# Only the standard library and the core (dssp_core, no numpy) load before main() installs the stop request
# (hardware.cli.stops): a Ctrl-C during the heavier imports (numpy, the runtime) is then a clean stop.
from dssp_core.schema import DEFAULT_CONTROL_RATE_HZ, check_rate
from dssp_core.staging import writer_lock, writer_lock_path
from hardware.cli.stops import Stops, run_stoppable
from hardware.piper.bus import interface_name

RUN_LOG = OutputKind("an episode log", "dssp-run")
"""``dssp-run --log-dir``: a new directory for one run's log (marked); an existing log is never reused."""

EPILOG = """\
--camera tabletop --can sim runs everything against the simulated tabletop camera and the CAN simulator of
the Piper (no hardware; the defaults). Real arms:
--can can0 (one Piper) or can0,can1 (two: left, right; 14 values). --dry-run computes the actions and
logs them without enabling or commanding the arms (feedback is still read).
"""


def parse_args(argv):
    p = ArgumentParser(
        prog="dssp-run",
        description="Run a DSSP model on the robot.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    source = p.add_mutually_exclusive_group(required=True)
    source.add_argument("--model", type=Path, help="model directory (python -m export.to_onnx)")
    source.add_argument(
        "--policy",
        metavar="NAME[:ARG]",
        help="another policy source instead of a model (hardware.policies.REGISTRY): hold (the arm held "
        "where it starts: the rig checked end to end), episode:PATH.zarr@K (a recorded episode's actions)",
    )
    p.add_argument(
        "--camera",
        default="tabletop",
        help="l515 | d435 | d405 | file:PATH (.bag/.db3) | tabletop (default: tabletop, the simulated one)",
    )
    p.add_argument("--serial", help="RealSense serial number, when several are connected")
    p.add_argument(
        "--can", default="sim", help="can0[,can1] (one bus per arm: left, right) | sim | sim:2 (default: sim)"
    )
    p.add_argument(
        "--interface",
        default="socketcan",
        type=interface_name,
        help="python-can interface of real buses (default: socketcan)",
    )
    p.add_argument("--control-rate", type=float, help="control rate in Hz (default: the model's training rate)")
    p.add_argument(
        "--extrinsics", type=Path, help="camera→robot-base calibration JSON (needed with a real camera or a recording)"
    )
    p.add_argument("--pointcloud", type=Path, help="point-cloud pipeline settings JSON (crop box, voxel, clip)")
    p.add_argument("--safety", type=Path, help="safety settings JSON (hardware.safety.SafetyConfig fields)")
    p.add_argument("--max-steps", type=int, help="stop after N ticks (default: until Ctrl-C)")
    p.add_argument("--dry-run", action="store_true", help="compute and log actions, send nothing")
    p.add_argument("--prefetch", action="store_true", help="compute each chunk early in a background thread")
    from hardware.cli.schedule_flags import add_schedule_arguments  # deferred: loads numpy

    add_schedule_arguments(p, also="not with --prefetch")
    p.add_argument("--threads", type=int, help="ONNX Runtime threads (default: all CPUs)")
    from dssp_deploy.onnx_policy import add_runtime_arguments  # deferred: loads numpy

    add_runtime_arguments(p)
    p.add_argument("--seed", type=int, help="diffusion noise seed (default: random)")
    p.add_argument("--log-dir", type=Path, help="episode log directory (default: runs/dssp-run/YYYYmmdd-HHMMSS[-N])")
    p.add_argument(
        "--no-can-log", action="store_true", help="do not write the raw CAN traffic (.blf per bus) into the log"
    )
    p.add_argument(
        "--allow-mismatch",
        action="append",
        default=[],
        metavar="FIELD",
        help="run although FIELD of the setup differs from the model's training data (e.g. pointcloud.crop_min, "
        "control_rate_hz); written to the log; repeatable",
    )
    p.add_argument("--quiet", action="store_true", help="no live status line")
    p.add_argument(
        "--subscribe",
        action="append",
        default=[],
        metavar="NAME",
        help="also hand every tick to the subscriber NAME (hardware.subscribers.REGISTRY: csv = "
        "LOG_DIR/ticks.csv); repeatable",
    )
    from dssp_data.rerun_views import add_rerun_flags  # deferred: loads numpy

    add_rerun_flags(p)
    return p.parse_args(argv)


def check_args(args):
    """Flags judged without opening anything (one line each, before any device or model is touched): (the schedule,
    the loop's settings; their rate --control-rate's, else the default until the source gives its own)."""
    from dssp_deploy.sessions import check_threads  # deferred: loads numpy
    from hardware.camera import check_camera_spec  # deferred: loads numpy
    from hardware.cli.schedule_flags import model_flags_given, schedule_of  # deferred: loads numpy

    check_camera_spec(args.camera, args.serial)
    if args.policy is not None:
        from hardware.policies import split_spec  # deferred: loads numpy

        split_spec(args.policy)
        given = model_flags_given(
            args,
            ("--prefetch", args.prefetch),
            ("--allow-mismatch", bool(args.allow_mismatch)),
            ("--threads", args.threads is not None),
            ("--seed", args.seed is not None),
        )
        if given:
            raise ConfigError(f"{given[0]} is a model's setting: it goes with --model, not --policy {args.policy}")
    schedule = schedule_of(args)
    from hardware.subscribers import check_subscribers  # deferred: loads numpy

    check_subscribers(args.subscribe)
    from hardware.run_loop import LoopSettings  # deferred: loads numpy

    rate = DEFAULT_CONTROL_RATE_HZ if args.control_rate is None else args.control_rate  # None: the source's, later
    settings = LoopSettings(control_rate_hz=rate, max_steps=args.max_steps, dry_run=args.dry_run)
    check_threads(args.threads)
    if args.seed is not None and args.seed < 0:
        raise ConfigError(f"--seed must be >= 0, got {args.seed}")
    from dssp_data.observation import contract_fields  # deferred: loads numpy

    known = [*contract_fields(), "control_rate_hz"]
    for field in args.allow_mismatch:
        if field not in known:
            raise ConfigError(
                f"--allow-mismatch {field}: not a field of the observation contract; one of {', '.join(known)}"
            )
    return schedule, settings


def control_rate(args, policy) -> float:
    """--control-rate, else the rate the model's training data was recorded at; a model without one needs --control-rate.
    (A --control-rate that contradicts the model's is refused with the rest of the contract, in _run.)"""
    if args.control_rate is not None:
        return args.control_rate
    if policy.contract.control_rate_hz is None:
        raise ConfigError(
            f"{args.model} records no control rate (its dataset had none): pass --control-rate HZ, the rate "
            "the demonstrations were recorded at"
        )
    return policy.contract.control_rate_hz  # in range: the contract checked it


def log_stamp() -> str:
    """The default log directory's name: the local time to the second (runs in the same second get -2, -3, ...)."""
    return time.strftime("%Y%m%d-%H%M%S")


def lock_log_dir(log_dir: Path | None, stack: contextlib.ExitStack) -> Path:
    """The run's log directory, locked for this run until ``stack`` closes (one writer per log directory, a second
    one gets one line before anything is opened): ``--log-dir``, or ``runs/dssp-run/<log_stamp()>``, with a suffix
    -2, -3, ... when that name is taken — chosen under its lock, so two runs never pick the same one. The folders
    made for the lock are removed again if the run leaves nothing in them."""

    if log_dir is not None:
        stack.enter_context(writer_lock(log_dir, what="log directory", flag="--log-dir"))
        return log_dir
    chosen = Path("runs/dssp-run") / log_stamp()
    for n in range(1, 1000):
        candidate = chosen if n == 1 else chosen.with_name(f"{chosen.name}-{n}")
        if candidate.exists() or candidate.is_symlink():
            continue
        attempt = contextlib.ExitStack()
        try:
            attempt.enter_context(writer_lock(candidate, what="log directory", flag="--log-dir"))
        except OutputError:
            if writer_lock_path(candidate).exists():  # another run holds this name
                continue
            raise
        if candidate.exists() or candidate.is_symlink():  # taken meanwhile by a run that has ended
            attempt.close()
            continue
        stack.enter_context(attempt)
        return candidate
    raise ConfigError(f"{chosen.parent} holds 999 logs named {chosen.name}[-N]; pass --log-dir DIR")


def model_source(args, schedule, described, cloud_config, safety_config, stops: Stops):
    """``--model``: (the model's policy source, the point-cloud settings, the control rate, what the log says of it),
    the model loaded and warmed up, the setup checked against its observation contract and ``schedule`` against the
    model — one line for what contradicts them, before any device opens."""
    from dssp_data.observation import FRAME_ROBOT_BASE, ObservationContract, check_contract  # deferred: loads numpy
    from dssp_data.pointcloud import PointCloudConfig  # deferred: loads numpy
    from dssp_deploy.onnx_policy import OnnxPolicy  # deferred: loads numpy
    from hardware.cli.schedule_flags import refusal  # deferred: loads numpy
    from hardware.policies.exported_model import ModelPolicy  # deferred: loads numpy

    if not args.quiet and sys.stderr.isatty():  # a progress note for a person; logs and scripts get only the result
        print(f"loading {args.model} (warm-up included)", file=sys.stderr)
    policy = OnnxPolicy(
        args.model,
        threads=args.threads,
        precision=args.precision,
        kernel=args.kernel,
        background_chunks=args.prefetch or args.smoothing == "rtc",
        spinning=False if args.no_spin else None,
    )
    stops.check()
    trained = policy.contract.observation
    if cloud_config is None:  # the model's own settings; a model from data that recorded none: the defaults
        cloud_config = trained.pointcloud or PointCloudConfig(n_points=policy.contract.n_points)
    rate = control_rate(args, policy)
    safety_config.check_speed(rate, described.max_joint_speed)  # before the prefetch lead is measured at this rate
    given = ObservationContract(
        pointcloud=cloud_config, frame=FRAME_ROBOT_BASE, state=described.layout, action=described.layout
    )
    pointcloud_by = f"--pointcloud {args.pointcloud}" if args.pointcloud else "the default point-cloud settings"
    overrides = check_contract(
        trained,
        given,
        trained_by=f"the model {args.model}",
        allow=args.allow_mismatch,
        given_by={
            "pointcloud": pointcloud_by,
            "frame": "the point-cloud pipeline",
            "state": f"--can {args.can}",
            "action": f"--can {args.can}",
            "control_rate_hz": "--control-rate",
        },
        extra=[("control_rate_hz", policy.contract.control_rate_hz, args.control_rate)],
    )
    for o in overrides:
        print(
            f"warning: running with {o['field']} = {o['given']} although the model was trained with {o['trained']} "
            "(--allow-mismatch)",
            file=sys.stderr,
        )
    try:  # the prefetch lead or real-time chunking's delay measured once, here: a model or rate it cannot serve refused
        source = ModelPolicy(policy, rate, seed=args.seed, schedule=schedule)  # the schedule is in the log: describe()
    except ValueError as exc:
        raise refusal(exc, f"--prefetch at {rate:g} Hz" if args.prefetch else f"--smoothing {args.smoothing}") from None
    about = {
        "model": str(args.model),
        "policy": source.describe(),
        "manifest": {
            "denoise_steps": policy.contract.denoise_steps,
            "control_rate_hz": policy.contract.control_rate_hz,
        },
        "observation": trained.to_manifest(),
        "allowed_mismatches": overrides,
    }
    return source, cloud_config, rate, about


def other_source_rate(args, source) -> float:
    """``--policy``: --control-rate, else the rate the source was made for (a recording's), else
    :data:`~dssp_core.schema.DEFAULT_CONTROL_RATE_HZ` (a source made for no rate, ``hold``: a rate that holds nothing
    it could spoil; a model's rate is never guessed: a model without one needs --control-rate)."""
    if args.control_rate is not None:
        return args.control_rate
    if source.control_rate_hz is not None:
        return check_rate(source.control_rate_hz, flag=f"--policy {args.policy}: the recording's control_rate_hz")
    return DEFAULT_CONTROL_RATE_HZ


def run(args, stops: Stops | None = None) -> int:
    """``args`` → exit code; ``stops``: the stop request main() installed (None: installed here)."""
    return run_stoppable(_run, args, stops, "no arm was enabled, nothing was sent")


def _run(args, stops: Stops) -> int:
    stops.check()
    schedule, settings = check_args(args)
    from dssp_data.pointcloud import PointCloudConfig, load_extrinsics  # deferred: loads can
    from dssp_data.rerun_views import check_views, open_views  # deferred: loads numpy
    from hardware.camera import TABLETOP, open_camera  # deferred: loads numpy
    from hardware.can_log import BusRecorder  # deferred: loads can
    from hardware.piper.piper_robot import open_robot  # deferred: loads can
    from hardware.rig import Rig  # deferred: loads numpy
    from hardware.run_log import RunLog  # deferred: loads numpy
    from hardware.run_loop import Runner, describe_ending  # deferred: loads numpy
    from hardware.safety import SafetyConfig  # deferred: loads numpy
    from hardware.subscribers import open_subscribers  # deferred: loads numpy
    from hardware.subscribers.rerun_ticks import RerunTicks  # deferred: loads numpy
    from hardware.subscribers.status_line import StatusLine  # deferred: loads numpy

    check_views(args.rerun, args.rerun_save)
    with contextlib.ExitStack() as stack:  # the log directory's lock, the views: released and closed on every exit
        log_dir = lock_log_dir(args.log_dir, stack)
        check_output(log_dir, force=None, kind=RUN_LOG, flag="--log-dir")  # a log is never replaced
        stops.check()
        safety_config = SafetyConfig.load(args.safety, "safety") if args.safety else SafetyConfig()
        robot = open_robot(args.can, interface=args.interface)  # not connected yet: what it is, from itself
        described = robot.description
        if args.control_rate is not None:
            safety_config.check_speed(settings.control_rate_hz, described.max_joint_speed)
        simulated_camera = args.camera.strip().lower() == TABLETOP
        if args.extrinsics:
            camera_to_base = load_extrinsics(args.extrinsics)
        elif not simulated_camera:
            raise ConfigError(
                "--extrinsics is needed with a real camera or a recording: the workspace crop is in the robot-base frame "
                '(a JSON file {"camera_to_base": 4x4}; see the README\'s calibration section)'
            )
        cloud_config = PointCloudConfig.load(args.pointcloud, "point-cloud settings") if args.pointcloud else None
        if args.model is not None:
            source, cloud_config, rate, about = model_source(
                args, schedule, described, cloud_config, safety_config, stops
            )
        else:
            from hardware.policies import open_policy  # deferred: loads numpy

            source = open_policy(args.policy)
            rate = other_source_rate(args, source)
            safety_config.check_speed(rate, described.max_joint_speed)
            cloud_config = cloud_config or PointCloudConfig()
            about = {"policy": source.describe()}
        source.check(described, cloud_config)  # before any device is opened
        stops.check()
        if rate != settings.control_rate_hz:  # the source's rate, checked where it was read
            settings = dataclasses.replace(settings, control_rate_hz=rate)
        if args.model is not None:
            print(
                f"graphs: {source.policy.kernel_note}", file=sys.stderr
            )  # which graphs run: the one start-up line about them
        views = open_views(
            "dssp-run", args.rerun, args.rerun_save
        )  # flags checked (and a viewer started) before any device
        if views is not None:
            stack.callback(lambda: print(views.close_line()))
        stops.check()  # the last moment a stop raises; from here it is the runner's, and the log records it
        claim_dir(log_dir, kind=RUN_LOG, flag="--log-dir")
        camera = open_camera(args.camera, serial=args.serial)  # not started yet
        if simulated_camera and not args.extrinsics:
            camera_to_base = camera.camera_to_base  # the simulated camera's own mounting
        recorders = (
            []
            if args.no_can_log
            else [
                BusRecorder(arm.channel, arm.interface, log_dir / f"can_{arm.channel}.blf", **arm.bus_options)
                for arm in robot.arms
            ]
        )
        log = RunLog(
            log_dir,
            {
                **about,
                "camera": args.camera,
                "can": args.can,
                "robot": described.to_dict(),
                "rate_hz": rate,
                "dry_run": args.dry_run,
                "camera_to_base": camera_to_base,
                "pointcloud": cloud_config.to_dict(),
                "safety": safety_config.to_dict(),
            },
        )
        subscribers = [
            log,
            *([] if args.quiet else [StatusLine()]),
            *([RerunTicks(views)] if views is not None else []),
            *open_subscribers(args.subscribe, log_dir),
        ]
        rig = Rig(camera, robot, camera_to_base, safety_config, recorders=recorders)  # the limits: the robot's own
        runner = Runner(source, rig, cloud_config, settings, subscribers=subscribers)
        stops.during(runner.request_stop)  # a stop that came meanwhile, or any later: the runner's final hold
        try:
            with (
                rig
            ):  # the camera, the arms (simulators start first, so the recorders find their channels), the recorders
                summary = runner.run()
        except BaseException as exc:
            if runner.ended_by is None:  # a device failed to open: the run never started, its reason is this error
                runner.finish(describe_ending(exc))
            raise
        finally:
            stops.during(None)
            runner.close()  # every ending gives the subscribers the summary (the log's), with what ended the run
    print_summary(summary, log_dir)
    if runner.safety is None and summary["ended_by"] == stops.reason:
        print(f"stopped by {stops.reason} during start-up; no arm was enabled, nothing was sent", file=sys.stderr)
    if summary["fault"]:
        return 1
    return stops.code if stops.reason is not None and summary["ended_by"] == stops.reason else 0


def print_summary(summary: dict, log_dir: Path) -> None:
    lat = summary["latency_ms"]

    def fmt(key):
        s = lat.get(key)
        return f"{s['p50']:.1f} / {s['p95']:.1f} / {s['max']:.1f}" if s else "-"

    print(
        f"ticks {summary['ticks']} ({summary['policy_ticks']} with the policy), {summary['rate_hz']:.1f} Hz "
        f"(target {summary['target_rate_hz']:g}), commands sent {summary['commands_sent']}, holds {summary['holds']}"
        + (" [dry run]" if summary["dry_run"] else "")
    )
    print(
        f"latency p50 / p95 / max ms: cloud {fmt('cloud')}, observe {fmt('observe')}, chunk {fmt('chunk')}, tick {fmt('tick')}"
    )
    print(
        f"safety events: {summary['events'] or 'none'}; ended by: {summary['ended_by']}"
        + ("; motors disabled" if summary.get("disabled") else "")
    )
    print(f"episode log: {log_dir}")


def main(argv: list[str] | None = None) -> int:
    stops = Stops()  # first: from here every stop is a clean one, even during the imports below
    try:
        args = parse_args(argv)
        return run_cli(lambda: run(args, stops))
    finally:
        stops.restore()


if __name__ == "__main__":
    sys.exit(main())

"""``dssp-sim``: expert demonstrations and closed-loop evaluation in the MuJoCo simulation.

    dssp-sim collect --task tap|swap|put2|metaworld/NAME|metaworld-cue/NAME --episodes N --out PATH.zarr [--seed S] [--points P]
    dssp-sim record --out PATH.zarr [dssp-record's flags; --camera mujoco --can mujoco by default]
    dssp-sim calibrate --mode eye-to-hand|eye-in-hand --auto N --out calib.json [dssp-calibrate's flags]
    dssp-sim eval --model MODEL_DIR | --expert  --task NAME --episodes N [--seed S] [--noise SIGMA] [--strips DIR] [--json PATH] [--force]
                  [--smoothing none|ensemble|rtc [--ensemble-every N] [--ensemble-decay M]] [--rerun [URL] | --rerun-save PATH.rrd]

``record`` is ``dssp-record`` on the simulated rig (the task's scripted expert plays the leader arm); ``calibrate`` is
``dssp-calibrate`` on the calibration twin (:mod:`dssp_sim.calibration_twin`: a ChArUco board and a camera at known poses).
``collect`` keeps only successful expert episodes and says how many it tried. ``eval`` drives the model
through the real chain (simulated camera → point-cloud pipeline → runtime → safety → CAN → simulated arm)
and prints the success rate with its 95 % Wilson interval and each episode's outcome (``--smoothing ensemble``: the
loop's temporal ensembling, as ``dssp-run``'s, on the Piper's and MetaWorld's tasks); ``eval --expert`` drives the
task's scripted expert through the same chain (the task's ceiling through the loop and its safety layer).
Outputs (:mod:`dssp_core.output_guard`): ``collect`` appends only to a dataset ``dssp-sim collect`` wrote;
``eval --strips`` replaces a previous output of its own only with ``--force``, and
never a folder with anything else in it; ``eval --json`` replaces an existing file only with ``--force``.
Exit codes: 0 done, 2 bad input (an output path that may not be written included).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import sys
from pathlib import Path

from dssp_core.cli_runner import ArgumentParser, run_cli
from dssp_core.errors import ConfigError
from dssp_core.output_guard import OutputDir, check_output, check_output_file, write_output_text
from dssp_data.rerun_views import add_rerun_flags, check_views, open_views
from dssp_deploy.onnx_policy import add_runtime_arguments
from hardware.cli.schedule_flags import add_schedule_arguments, model_flags_given, schedule_of
from hardware.cli.stops import Stops

TASKS = ("tap", "swap", "put2")


TASK_HELP = (
    " | ".join(TASKS) + " | metaworld/NAME (a MetaWorld v3 task) | metaworld-cue/NAME (reach, push, "
    "pick-place with the goal shown for 10 steps, then hidden)"
)


def _task(name: str) -> str:
    from dssp_sim.metaworld_env import is_metaworld, task_id  # deferred: loads mujoco

    if is_metaworld(name):
        try:
            return task_id(name)
        except ConfigError as e:
            raise argparse.ArgumentTypeError(str(e)) from None
    if name not in TASKS:
        raise argparse.ArgumentTypeError(
            f"unknown task {name!r}; choose one of {', '.join(TASKS)}, metaworld/NAME or metaworld-cue/NAME"
        )
    return name


def positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def _non_negative(text: str) -> int:
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {value}")
    return value


def parse_args(argv):
    p = ArgumentParser(prog="dssp-sim", description="Memory tasks in a MuJoCo simulation of the AgileX Piper.")
    sub = p.add_subparsers(dest="command", required=True)
    sub.add_parser("record", help="dssp-record on the simulated rig (same flags; see dssp-sim record --help)")
    sub.add_parser("calibrate", help="dssp-calibrate on the MuJoCo twin (same flags; see dssp-sim calibrate --help)")
    c = sub.add_parser("collect", help="expert demonstrations → a DP3 zarr dataset")
    c.add_argument("--task", type=_task, required=True, help=TASK_HELP)
    c.add_argument("--episodes", type=positive_int, required=True, help="successful episodes to keep")
    c.add_argument(
        "--out", type=Path, required=True, help="dataset path (.zarr; a dataset dssp-sim collect wrote is appended to)"
    )
    c.add_argument(
        "--seed",
        type=_non_negative,
        help="first scene seed (default: 0, or after the last one of the dataset appended to)",
    )
    c.add_argument(
        "--points",
        type=positive_int,
        help="points per cloud (default 256, the sim preset's; 512 for metaworld/NAME, DP3's)",
    )
    c.add_argument("--no-progress", action="store_true")
    e = sub.add_parser("eval", help="closed-loop evaluation of a model directory (or of the task's scripted expert)")
    who = e.add_mutually_exclusive_group(required=True)
    who.add_argument("--model", type=Path, help="model directory (python -m export.to_onnx)")
    who.add_argument(
        "--expert",
        action="store_true",
        help="the task's scripted expert as the control loop's policy source, through the same camera, "
        "safety layer and CAN bus (Piper tasks)",
    )
    e.add_argument("--task", type=_task, required=True, help=TASK_HELP)
    e.add_argument("--episodes", type=positive_int, default=20)
    e.add_argument(
        "--seed", type=_non_negative, default=1000, help="first episode seed (default 1000: unseen in collection)"
    )
    e.add_argument(
        "--noise", type=float, default=0.0, help="σ of Gaussian noise on the recent state tokens (robustness test)"
    )
    e.add_argument("--threads", type=int, help="ONNX Runtime threads")
    add_runtime_arguments(e)
    e.add_argument(
        "--prefetch",
        action="store_true",
        help="start each chunk early, by the delay (--inject-delay), and drop its passed actions (dssp-run's)",
    )
    add_schedule_arguments(e, also="not with --prefetch")
    e.add_argument(
        "--limit-excludes-holds",
        action="store_true",
        help="a tick the loop holds (waiting for a chunk) does not count toward the task's step limit: success "
        "scored on the task, not on the wait (Piper tasks)",
    )
    e.add_argument(
        "--inject-delay",
        type=float,
        default=0.0,
        metavar="MS",
        help="simulate an inference delay: each chunk usable MS ms after its observation (whole ticks, rounded "
        "up); the loop holds until then (compare --smoothing none|ensemble|rtc under delay)",
    )
    e.add_argument("--strips", type=Path, help="write a PNG strip of each episode here")
    e.add_argument("--json", type=Path, help="write the result here")
    e.add_argument("--force", action="store_true", help="replace an existing --json file and previous --strips")
    e.add_argument("--no-progress", action="store_true")

    add_rerun_flags(e, what="every tick of every episode")
    return p.parse_args(argv)


def run(args) -> int:
    if args.command == "collect":
        from dssp_sim.collect import collect  # deferred: loads hardware.camera, dssp_data.pointcloud

        result = collect(
            args.task, args.episodes, args.out, seed=args.seed, n_points=args.points, progress=not args.no_progress
        )
        failed = sum(result.failures.values())
        print(
            f"{args.out}: kept {result.kept} successful {args.task} episodes of {result.attempted} tried"
            + (f" ({failed} failed: {dict(result.failures)})" if failed else "")
            + (
                f"; {sum(result.steps)} steps, {min(result.steps)}–{max(result.steps)} per episode"
                if result.steps
                else ""
            )
        )
        if result.kept < args.episodes:
            raise ConfigError(
                f"only {result.kept} of {args.episodes} expert episodes succeeded in {result.attempted} tries; "
                "the dataset holds the successful ones — check the task's expert"
            )
        return 0
    from dssp_sim.evaluate import STRIPS_DIR, prepare_evaluation, print_eval  # deferred: loads can

    if not (math.isfinite(args.noise) and 0 <= args.noise <= 10):
        raise ConfigError(f"--noise must be a number in [0, 10] (σ in the tokens' units), got {args.noise}")
    check_views(args.rerun, args.rerun_save)  # every flag checked before anything is opened or written
    if args.expert:
        given = model_flags_given(
            args,
            ("--noise", args.noise != 0.0),
            ("--threads", args.threads is not None),
            ("--inject-delay", args.inject_delay != 0.0),
            ("--prefetch", args.prefetch),
            ("--limit-excludes-holds", args.limit_excludes_holds),
        )
        if given:
            raise ConfigError(f"{given[0]} is a model's setting: it goes with --model, not --expert")
    schedule = schedule_of(args)
    if args.json:
        check_output_file(args.json, force=args.force, flag="--json")
    if args.strips:
        check_output(args.strips, force=args.force, kind=STRIPS_DIR, flag="--strips")  # made only once all is checked

    # the model and the task loaded and every setting checked against them before an output is opened
    evaluation = prepare_evaluation(
        args.model,
        args.task,
        args.episodes,
        seed=args.seed,
        threads=args.threads,
        precision=args.precision,
        kernel=args.kernel,
        spinning=False if args.no_spin else None,
        state_token_noise=args.noise,
        views=bool(args.rerun or args.rerun_save),
        inject_delay_ms=args.inject_delay,
        schedule=schedule,
        limit_excludes_holds=args.limit_excludes_holds,
    )
    with contextlib.ExitStack() as stack:
        stack.callback(evaluation.env.close)
        strips = (
            stack.enter_context(OutputDir(args.strips, STRIPS_DIR, force=args.force, flag="--strips"))
            if args.strips
            else None
        )
        views = open_views("dssp-sim eval", args.rerun, args.rerun_save)  # after --strips: a refused one saves no views
        if views is not None:
            stack.callback(lambda: print(views.close_line()))
        result = evaluation.run(strips.path if strips else None, progress=not args.no_progress, views=views)
        if strips is not None:
            strips.commit()
    print_eval(result)
    if args.json:
        write_output_text(args.json, json.dumps(result.to_dict(), indent=2) + "\n", force=args.force, flag="--json")
    return 0


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["record"]:  # dssp-record's own flags, on the simulated rig
        stops = Stops()  # before the simulation's imports: a stop while they load ends in one line, not silently
        try:
            from dssp_sim.teleop import record_main  # deferred: loads can, mujoco, OpenGL, …

            return record_main(argv[1:], stops)
        finally:
            stops.restore()
    if argv[:1] == ["calibrate"]:  # dssp-calibrate's own flags, on the twin
        from dssp_sim.calibration_twin import calibrate_main  # deferred: loads can, cv2, mujoco, …

        return calibrate_main(argv[1:])
    args = parse_args(argv)
    return run_cli(lambda: run(args))


if __name__ == "__main__":
    sys.exit(main())

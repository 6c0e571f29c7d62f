"""``dssp-data``: look at, check, combine, convert and export demonstration datasets (DP3 / RoboTwin zarr).

    dssp-data info PATH [--json]
    dssp-data view PATH --episode K [--out DIR] [--steps N] [--video] [--rerun [URL] | --rerun-save PATH.rrd]
    dssp-data merge OUT IN IN... [--drop-marked] [--force]
    dssp-data split PATH --train OUT --val OUT (--val-ratio R | --val-episodes 1,5) [--seed S] [--drop-marked]
                    [--drop-episodes 3,7-9] [--force]
    dssp-data convert ROBOTWIN_DIR --out OUT.zarr [--episodes N] [--xyz] [--control-rate HZ] [--task NAME] [--force]
    dssp-data convert BAGS --out OUT.zarr --extrinsics FILE [--pointcloud FILE] [--control-rate HZ] [--state-topic T]
                      [--action-topic T] [--depth-topic T] [--info-topic T] [--joints J1,..,J7] [--gripper-open V]
                      [--tolerance S] [--depth-unit M] [--episodes N] [--task NAME] [--force]
    dssp-data convert LEROBOT_ROOT --out OUT.zarr --extrinsics FILE [--pointcloud FILE] [--depth-key K]
                      [--state-key observation.state] [--action-key action] [--episodes N] [--task NAME] [--force]
    dssp-data export PATH --to lerobot --out DIR [--repo-id local/NAME] [--force]
    dssp-data repair PATH

Every problem with the input is one ``error: ...`` line and exit code 2: among them a chunk of the dataset that
is missing or corrupt (the line names the key, the chunk, its steps and episodes). ``info`` exits with 1 when it
lists problems with the data, 0 when it finds none; ``repair`` exits with 2 when the dataset has lost data it
cannot restore, and changes nothing then.

Replaying an episode on the arms is ``dssp-replay`` (:mod:`hardware.cli.replay`).

Outputs: merge, split and convert write a new dataset, or replace one that dssp-data made (``--force``, with
its ``.can`` CAN logs); a recorded, synthetic or any other dataset or folder there is refused and nothing is
deleted. ``export`` writes a new LeRobot dataset folder, or replaces one that ``dssp-data export`` made (``--force``).
An output may not be an input or lie inside one. Ctrl-C stops with exit code 130 and leaves no
temporary behind (``.OUT.tmp-*``); a killed command's temporaries are removed by the next one writing OUT.
Output that a reader stops reading (``dssp-data info PATH | head``) ends the command quietly (exit code 141).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from dssp_core.cli_runner import ArgumentParser, run_cli
from dssp_core.errors import ConfigError, DSSPError
from dssp_core.schema import DEFAULT_CONTROL_RATE_HZ

EPILOG = """\
info      episodes, lengths, rates, arrays, value ranges, attributes, recording metadata, problems found
          (exit 1 when it lists problems, 2 when the dataset cannot be read, e.g. a missing or corrupt chunk)
view      PNG pictures of one episode: point clouds over time from three viewpoints, state/action trajectories;
          with --rerun / --rerun-save PATH.rrd the episode in Rerun instead (cloud, depth, joints, ghost chunk)
merge     concatenate datasets (episodes, per-episode metadata and CAN logs travel along)
split     train/validation datasets by whole episodes (--drop-episodes leaves episodes out, e.g. lost ones)
convert   RoboTwin raw HDF5 episodes (<task>/<config>/data/episode*.hdf5), or ROS 2 bags (a bag folder with
          metadata.yaml, or a folder of them: one episode per bag; joint states + depth + camera_info, aligned to
          --control-rate, clouds by the robot's point-cloud pipeline), or a LeRobot v3 dataset (a folder with
          meta/info.json: one episode per LeRobot episode; a uint16 depth feature with info.camera_intrinsics,
          state and action features, clouds by the robot's point-cloud pipeline), to a DP3 zarr dataset
export    a DP3 zarr dataset to a LeRobot v3 dataset (--to lerobot): state, action, point clouds and, when
          recorded with its camera, depth; fps = control_rate_hz
repair    cut off the steps of an interrupted write (every complete episode stays); lost data (a missing or
          corrupt chunk of a complete episode) cannot be repaired: exit 2, nothing changed
"""


def build_parser() -> argparse.ArgumentParser:
    p = ArgumentParser(
        prog="dssp-data",
        description="Look at, check, combine, convert and export datasets.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    info = sub.add_parser("info", help="what a dataset holds and the problems found")
    info.add_argument("path", type=Path)
    info.add_argument("--json", action="store_true", help="print the report as JSON")

    view = sub.add_parser("view", help="pictures of one episode (PNG; --video adds a GIF)")
    view.add_argument("path", type=Path)
    view.add_argument("--episode", type=int, required=True)
    view.add_argument("--out", type=Path, default=Path("."), help="directory for the pictures (default: .)")
    view.add_argument("--steps", type=int, default=5, help="steps shown in the point-cloud picture (default 5)")
    view.add_argument("--video", action="store_true", help="also an animated GIF of the point clouds")
    view.add_argument("--force", action="store_true", help="replace pictures of the same name in --out")
    from dssp_data.rerun_views import add_rerun_flags  # deferred: loads numpy

    add_rerun_flags(view, what="the episode (instead of the pictures)")

    merge = sub.add_parser("merge", help="concatenate datasets")
    merge.add_argument("out", type=Path)
    merge.add_argument("inputs", type=Path, nargs="+")
    merge.add_argument("--force", action="store_true", help="replace a dataset dssp-data made before at OUT")
    merge.add_argument("--drop-marked", action="store_true", help="leave out episodes recorded with problems")

    split = sub.add_parser("split", help="train/validation datasets by episode")
    split.add_argument("path", type=Path)
    split.add_argument("--train", type=Path, required=True)
    split.add_argument("--val", type=Path, required=True)
    group = split.add_mutually_exclusive_group(required=True)
    group.add_argument("--val-ratio", type=float, help="fraction of episodes for validation, drawn with --seed")
    group.add_argument("--val-episodes", help="comma-separated episode indices for validation")
    split.add_argument("--seed", type=int, default=0, help="seed of the --val-ratio draw (>= 0)")
    split.add_argument("--force", action="store_true", help="replace datasets dssp-data made before at --train/--val")
    split.add_argument("--drop-marked", action="store_true", help="leave out episodes recorded with problems")
    split.add_argument("--drop-episodes", help="leave out these episodes, e.g. 3,7-9 (those whose data is lost)")

    convert = sub.add_parser(
        "convert", help="RoboTwin raw HDF5 episodes, ROS 2 bags or a LeRobot v3 dataset -> DP3 zarr"
    )
    convert.add_argument(
        "source",
        type=Path,
        help="RoboTwin <task>/<config> directory, its data/ directory or one .hdf5; "
        "or a ROS 2 bag folder (metadata.yaml), or a folder of bags; or a LeRobot v3 dataset's root "
        "(meta/info.json)",
    )
    convert.add_argument("--out", type=Path, required=True)
    convert.add_argument("--episodes", type=int, help="convert only the first N episodes")
    convert.add_argument("--xyz", action="store_true", help="RoboTwin: keep xyz only (drop the points' rgb)")
    convert.add_argument(
        "--control-rate",
        type=float,
        help="control rate in Hz, stored as control_rate_hz (ROS 2 bags: "
        "the rate the streams are aligned to, default 10)",
    )
    convert.add_argument("--task", help="task name stored with the data")
    convert.add_argument("--force", action="store_true", help="replace a dataset dssp-data made before at --out")
    bag = convert.add_argument_group("ROS 2 bags (the rosbags library: pip install 'dssp[ros]')")
    bag.add_argument("--extrinsics", type=Path, help="camera->robot-base calibration JSON (dssp-calibrate's; needed)")
    bag.add_argument("--pointcloud", type=Path, help="point-cloud settings JSON (default: the robot's defaults)")
    bag.add_argument(
        "--state-topic", default="/joint_states", help="the arm's sensor_msgs/JointState (default: %(default)s)"
    )
    bag.add_argument(
        "--action-topic",
        help="the leader's JointState: the action is its command (default: none, the action is the next tick's state)",
    )
    bag.add_argument(
        "--depth-topic", default="/camera/camera/depth/image_rect_raw", help="16UC1 depth (default: %(default)s)"
    )
    bag.add_argument(
        "--info-topic",
        default="/camera/camera/depth/camera_info",
        help="the depth camera's CameraInfo (default: %(default)s)",
    )
    bag.add_argument(
        "--joints",
        default="joint1,joint2,joint3,joint4,joint5,joint6,joint7",
        help="the 7 joint names, J1..J6 then the gripper (default: piper_ros's, %(default)s)",
    )
    bag.add_argument(
        "--gripper-open",
        type=float,
        default=0.07,
        help="the gripper value that is fully open (default: 0.07, the Piper's stroke in metres)",
    )
    bag.add_argument(
        "--tolerance",
        type=float,
        default=0.05,
        help="s: the oldest a stream's newest message may be at a "
        "tick before the bag is refused as unsynchronised (default: %(default)s)",
    )
    bag.add_argument(
        "--depth-unit", type=float, default=0.001, help="metres per depth count (default: %(default)s, mm)"
    )
    lerobot = convert.add_argument_group(
        "LeRobot v3 datasets (pyarrow: pip install 'dssp[lerobot]'; --extrinsics needed, --pointcloud as for bags)"
    )
    lerobot.add_argument(
        "--depth-key",
        help="the depth feature: uint16 (H, W) counts or float32 metres, with "
        "info.camera_intrinsics (default: the one feature named *depth* or holding intrinsics)",
    )
    lerobot.add_argument("--state-key", default="observation.state", help="the state feature (default: %(default)s)")
    lerobot.add_argument("--action-key", default="action", help="the action feature (default: %(default)s)")

    export = sub.add_parser("export", help="a DP3 zarr dataset -> a LeRobot v3 dataset")
    export.add_argument("path", type=Path)
    export.add_argument("--to", required=True, choices=["lerobot"], help="the format: lerobot (LeRobot v3)")
    export.add_argument("--out", type=Path, required=True, help="the dataset's folder (its root)")
    export.add_argument("--repo-id", help="the name to load it by, OWNER/NAME (default: local/<name of --out>)")
    export.add_argument(
        "--force", action="store_true", help="replace a LeRobot dataset dssp-data exported before at --out"
    )

    repair = sub.add_parser("repair", help="cut off the steps of an interrupted write")
    repair.add_argument("path", type=Path)
    return p


def _info(args) -> int:
    from dssp_data.inspect import format_report, inspect_dataset  # deferred: loads numpy

    report = inspect_dataset(args.path)
    print(json.dumps(report, indent=2) if args.json else format_report(report))
    return 1 if report["problems"] else 0


def _view(args) -> int:
    from dssp_data.view import render_episode, rerun_episode  # deferred: loads msgpack, numcodecs, numpy, …

    if args.steps < 1:
        raise DSSPError(f"--steps must be at least 1, got {args.steps}")
    if args.rerun is not None or args.rerun_save is not None:
        print(rerun_episode(args.path, args.episode, args.rerun, args.rerun_save))
        return 0
    for path in render_episode(
        args.path, args.episode, args.out, columns=args.steps, video=args.video, force=args.force
    ):
        print(f"wrote {path}")
    return 0


def _merge(args) -> int:
    from dssp_data.edit import merge  # deferred: loads numpy

    summary = merge(args.out, args.inputs, force=args.force, drop_marked=args.drop_marked, flag="OUT")
    for line in summary["warnings"]:
        print(f"warning: {line}", file=sys.stderr)
    for path, episodes in summary["dropped"].items():
        print(f"left out episodes {episodes} of {path} (recorded with problems)")
    print(f"wrote {args.out}: {summary['episodes']} episodes, {summary['steps']} steps, {summary['can_logs']} CAN logs")
    return 0


def _split(args) -> int:
    from dssp_data.edit import split  # deferred: loads numpy

    episodes = None
    if args.val_episodes is not None:
        try:
            episodes = [int(x) for x in args.val_episodes.split(",") if x.strip()]
        except ValueError:
            raise DSSPError(f"--val-episodes must be comma-separated integers, got {args.val_episodes!r}") from None
    if args.seed < 0:
        raise DSSPError(f"--seed must be a non-negative integer, got {args.seed}")
    drop = _episode_list(args.drop_episodes, "--drop-episodes") if args.drop_episodes is not None else []
    result = split(
        args.path,
        args.train,
        args.val,
        val_ratio=args.val_ratio,
        val_episodes=episodes,
        seed=args.seed,
        force=args.force,
        drop_marked=args.drop_marked,
        drop_episodes=drop,
    )
    if result["dropped"]:
        print(f"left out episodes {result['dropped']} (recorded with problems)")
    if result["left_out"]:
        print(f"left out episodes {result['left_out']} (--drop-episodes)")
    for part, target in (("train", args.train), ("val", args.val)):
        s = result[f"{part}_summary"]
        print(f"wrote {target}: {s['episodes']} episodes, {s['steps']} steps (source episodes {result[part]})")
    return 0


def _episode_list(text: str, option: str) -> list[int]:
    """Episode indices from ``3,7-9`` (ranges inclusive)."""
    episodes = []
    try:
        for part in (p.strip() for p in text.split(",")):
            if not part:
                continue
            first, _, last = part.partition("-")
            a, b = int(first), int(last) if last else int(first)
            if b < a:
                raise ValueError(part)
            episodes += range(a, b + 1)
    except ValueError:
        raise DSSPError(f"{option} must be comma-separated episode indices or ranges (3,7-9), got {text!r}") from None
    return episodes


def _convert(args) -> int:
    tty = sys.stderr.isatty()

    def progress(i, n, path):
        if tty:
            print(f"\rconverting {i + 1}/{n}: {path.name}\x1b[K", end="", file=sys.stderr, flush=True)

    from dssp_data.lerobot import is_lerobot_root  # deferred: loads msgpack, numcodecs, numpy, …
    from dssp_data.rosbag2 import looks_like_bag  # deferred: loads msgpack, numcodecs, numpy, …

    lerobot = is_lerobot_root(args.source)
    bags = not lerobot and (
        looks_like_bag(args.source) or (args.source.is_dir() and any(looks_like_bag(p) for p in args.source.iterdir()))
    )
    try:
        if lerobot:
            summary = _convert_lerobot(args, progress)
        elif bags:
            summary = _convert_bags(args, progress)
        else:
            from dssp_data.robotwin_hdf5 import convert  # deferred: loads msgpack, numcodecs, numpy, …

            summary = convert(
                args.source,
                args.out,
                max_episodes=args.episodes,
                xyz_only=args.xyz,
                control_rate_hz=args.control_rate,
                task=args.task,
                force=args.force,
                progress=progress,
            )
    finally:
        if tty:
            print("\r\x1b[K", end="", file=sys.stderr, flush=True)
    if lerobot:
        print(
            f"wrote {args.out}: {summary['episodes']} episodes (one per LeRobot episode), {summary['steps']} steps at "
            f"{summary['fps']:g} Hz (clouds from {summary['depth_key']}, state = {summary['state_key']}, action = "
            f"{summary['action_key']})"
        )
        return 0
    if bags:
        action = (
            "the leader's command (" + args.action_topic + ")"
            if summary["action_convention"] == "leader_command"
            else "the state at the next tick"
        )
        print(
            f"wrote {args.out}: {summary['episodes']} episodes (one per bag), {summary['steps']} steps at "
            f"{args.control_rate or DEFAULT_CONTROL_RATE_HZ:g} Hz (action = {action})"
        )
        return 0
    print(
        f"wrote {args.out}: {summary['episodes']} episodes, {summary['steps']} steps "
        f"(state = joint vector at t, action = joint vector at t + 1)"
    )
    if args.control_rate is None:
        print(
            "note: the control rate is not stored; pass --control-rate HZ (or give dssp-train --control-rate)",
            file=sys.stderr,
        )
    return 0


def _convert_bags(args, progress) -> dict:
    """``dssp-data convert BAGS``: the flags -> :func:`dssp_data.rosbag2.convert`."""
    from dssp_data.observation import PointCloudConfig  # deferred: loads numpy
    from dssp_data.pointcloud import load_extrinsics  # deferred: loads numpy
    from dssp_data.rosbag2 import Rosbag2Settings, convert  # deferred: loads msgpack, numcodecs, numpy, …

    if args.xyz:
        raise ConfigError("--xyz is for RoboTwin files; a bag's clouds follow --pointcloud (use_color false: xyz)")
    if args.extrinsics is None:
        raise ConfigError(
            "--extrinsics is needed to convert ROS 2 bags: the workspace crop is in the robot-base frame "
            "(dssp-calibrate writes the file)"
        )
    cloud_config = (
        PointCloudConfig.load(args.pointcloud, "point-cloud settings") if args.pointcloud else PointCloudConfig()
    )
    if cloud_config.use_color:
        raise ConfigError(
            "--pointcloud asks for colour (use_color): the ROS 2 converter builds xyz clouds from the depth "
            "topic only; set use_color false"
        )
    settings = Rosbag2Settings(
        **({} if args.control_rate is None else {"control_rate_hz": args.control_rate}),
        state_topic=args.state_topic,
        action_topic=args.action_topic,
        depth_topic=args.depth_topic,
        info_topic=args.info_topic,
        joints=tuple(j.strip() for j in args.joints.split(",")),
        gripper_open=args.gripper_open,
        tolerance=args.tolerance,
        depth_unit=args.depth_unit,
    )
    return convert(
        args.source,
        args.out,
        settings,
        cloud_config,
        load_extrinsics(args.extrinsics),
        max_episodes=args.episodes,
        task=args.task,
        force=args.force,
        progress=progress,
    )


def _convert_lerobot(args, progress) -> dict:
    """``dssp-data convert LEROBOT_ROOT``: the flags -> :func:`dssp_data.lerobot.read.convert`."""
    from dssp_data.lerobot import convert  # deferred: loads msgpack, numcodecs, numpy, …
    from dssp_data.observation import PointCloudConfig  # deferred: loads numpy
    from dssp_data.pointcloud import load_extrinsics  # deferred: loads numpy

    if args.xyz:
        raise ConfigError(
            "--xyz is for RoboTwin files; a LeRobot dataset's clouds follow --pointcloud (use_color false: xyz)"
        )
    if args.control_rate is not None:
        raise ConfigError(
            "--control-rate is for RoboTwin files and ROS 2 bags; a LeRobot dataset's control rate is its "
            "fps (meta/info.json)"
        )
    if args.extrinsics is None:
        raise ConfigError(
            "--extrinsics is needed to convert a LeRobot dataset: the workspace crop is in the robot-base "
            "frame (dssp-calibrate writes the file)"
        )
    cloud_config = (
        PointCloudConfig.load(args.pointcloud, "point-cloud settings") if args.pointcloud else PointCloudConfig()
    )
    return convert(
        args.source,
        args.out,
        cloud_config,
        load_extrinsics(args.extrinsics),
        depth_key=args.depth_key,
        state_key=args.state_key,
        action_key=args.action_key,
        max_episodes=args.episodes,
        task=args.task,
        force=args.force,
        progress=progress,
    )


def _export(args) -> int:
    from dssp_data.lerobot import export  # deferred: loads msgpack, numcodecs, numpy, …

    summary = export(args.path, args.out, repo_id=args.repo_id, force=args.force)
    for note in summary["notes"]:
        print(f"note: {note}", file=sys.stderr)
    print(
        f"wrote {args.out}: a LeRobot v3 dataset of {summary['episodes']} episodes, {summary['frames']} frames at "
        f"{summary['fps']} fps ({', '.join(summary['features'])}); load it with "
        f"LeRobotDataset({summary['repo_id']!r}, root={str(args.out)!r})"
    )
    return 0


def _repair(args) -> int:
    from dssp_data.edit import repair  # deferred: loads msgpack, numcodecs, numpy, …

    result = repair(args.path)
    if result["dropped_steps"] or result["dropped_infos"]:
        print(
            f"repaired {args.path}: cut off {result['dropped_steps']} steps and {result['dropped_infos']} "
            f"metadata entries of an interrupted write"
        )
    for key, (start, length) in result["reset_shapes"].items():
        print(
            f"repaired {args.path}: set {key} back to the last episode end (its metadata gave {length} steps, with "
            f"no chunk stored for steps {start}..{length - 1}; nothing stored was lost)"
        )
    if not (result["dropped_steps"] or result["dropped_infos"] or result["reset_shapes"]):
        print(f"{args.path} needed no repair")
    return 0


COMMANDS = {
    "info": _info,
    "view": _view,
    "merge": _merge,
    "split": _split,
    "convert": _convert,
    "export": _export,
    "repair": _repair,
}


def _run(args) -> int:
    return COMMANDS[args.command](args)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return run_cli(lambda: _run(args))


if __name__ == "__main__":
    sys.exit(main())

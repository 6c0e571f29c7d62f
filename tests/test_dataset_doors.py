"""The dataset doors: every way a dataset is written or converted (``dssp-data convert``, ``merge``, ``split``,
``repair``, ``export``, the writers) holds the one dataset lock from its first step; every reader (zarr, RoboTwin
HDF5, ROS 2 bags, LeRobot v3) stays within the read budget, reads its metadata files bounded and without blocking,
refuses what it cannot convert faithfully, and never writes into its input. Every refusal is one ``error: …`` line
(exit code 2, no traceback, no warning, no staging folder named) and writes nothing."""

from __future__ import annotations

import importlib
import io
import json
import math
import os
import pkgutil
import shutil
import signal
import sqlite3
import subprocess
import sys
import warnings
from contextlib import contextmanager, redirect_stdout
from pathlib import Path

import h5py
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from conftest import CAMERA, CLOUD, ROOT, calibration_flags, episodes, one_error_line, refusal, snapshot
from hypothesis import example, given, settings
from hypothesis import strategies as st
from ros_bags import write_bag

import dssp_data
from dssp_core.errors import ConfigError, DatasetError
from dssp_core.staging import writer_lock_path
from dssp_data.data_cli import main as data_main
from dssp_data.dataset_layout import Episode
from dssp_data.lerobot.layout import data_file
from dssp_data.pointcloud.depth_frame import MAX_FOCAL_PX, MAX_IMAGE_SIDE, Intrinsics
from dssp_data.replay_buffer import ReplayBuffer
from dssp_data.replay_buffer_writer import (
    DATASET_WRITERS,
    ReplayBufferWriter,
    _write_store,
    dataset_lock,
    write_replay_buffer,
)

HYPOTHESIS = {"deadline": None, "derandomize": True, "database": None, "max_examples": 60}


# ------------------------------------------------------------------------------------------- inputs
def zarr_dataset(path: Path, n: int = 2, seed: int = 0) -> Path:
    write_replay_buffer(path, episodes(n, seed), attrs={"control_rate_hz": 10.0, "task": "t"})
    return path


def robotwin(folder: Path, vector=None) -> Path:
    """A RoboTwin task folder with one episode file (``vector``: its joint vector, (4, 14))."""
    (folder / "data").mkdir(parents=True)
    with h5py.File(folder / "data" / "episode0.hdf5", "w") as f:
        f["joint_action/vector"] = np.zeros((4, 14)) if vector is None else vector
        f["pointcloud"] = np.full((4, 8, 6), 0.5, np.float32)
    return folder


BAG_FLAGS = ["--depth-unit", "0.00025"]


def lerobot_dataset(root: Path, tmp: Path, frames: int = 4) -> Path:
    """A LeRobot v3 dataset (dssp-data export of a dataset with depth and its camera) at ``root``."""
    depth = np.stack([CAMERA.render(k / 10)[0] for k in range(frames)])
    ep = Episode(
        np.zeros((frames, 8, 3), np.float32),
        np.zeros((frames, 7), np.float32),
        np.zeros((frames, 7), np.float32),
        extras={"depth": depth},
    )
    intr = CAMERA.intrinsics
    source = tmp / f"{root.name}_source.zarr"
    write_replay_buffer(
        source,
        [ep],
        attrs={"control_rate_hz": 10.0, "camera_depth_unit": CAMERA.depth_unit, "camera_intrinsics": intr.to_dict()},
    )
    with redirect_stdout(io.StringIO()):
        assert data_main(["export", str(source), "--to", "lerobot", "--out", str(root)]) == 0
    shutil.rmtree(source)
    (root / ".dssp-output.json").unlink()  # as if downloaded: no export's marker
    return root


def edit_info(root: Path, edit) -> Path:
    info = json.loads((root / "meta/info.json").read_text())
    edit(info)
    (root / "meta/info.json").write_text(json.dumps(info))
    return root


def rewrite_column(path: Path, name: str, values: np.ndarray) -> None:
    """Replace column ``name`` of the parquet file by lists of ``values`` (rows, n), in their dtype."""
    table = pq.ParquetFile(path).read()
    rows, n = values.shape
    flat = pa.Array.from_buffers(pa.from_numpy_dtype(values.dtype), values.size, [None, pa.py_buffer(values.ravel())])
    offsets = pa.Array.from_buffers(
        pa.int32(), rows + 1, [None, pa.py_buffer(np.arange(0, rows * n + 1, n, dtype=np.int32))]
    )
    column = pa.ListArray.from_arrays(offsets, flat)
    pq.write_table(table.set_column(table.schema.get_field_index(name), name, column), path)


# ------------------------------------------------------------------------------------------- checks
def cli(capsys, *argv) -> tuple[int, str, str]:
    """dssp-data in-process, numpy's and Python's warnings recorded: (exit code, stdout, stderr + warnings)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            code = data_main([str(a) for a in argv])
        except SystemExit as exc:  # argparse's own one-line errors
            code = exc.code
    out, err = capsys.readouterr()
    return code, out, err + "".join(f"warning: {w.message}\n" for w in caught)


def refused(result: tuple[int, str, str], *fragments: str) -> str:
    """The :func:`conftest.refusal` line of a ``cli`` result (exit 2, nothing on stdout, one ``error: …`` line holding
    ``fragments``, so no warning either), naming no internal staging path, and short."""
    line = refusal(result, *fragments)
    assert ".tmp-" not in line and ".partial-" not in line, line
    assert len(line) < 1000, line
    return line


@contextmanager
def never_blocks(seconds: float = 20.0):
    """Fail instead of hanging when something inside blocks (a FIFO opened for reading)."""

    def stop(signum, frame):
        raise TimeoutError("blocked")

    previous = signal.signal(signal.SIGALRM, stop)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def all_dataset_writers() -> dict[str, object]:
    """Every registered dataset writer, once every module of dssp_data is imported (a writer anywhere is found)."""
    for module in pkgutil.walk_packages(dssp_data.__path__, "dssp_data."):
        if module.name != "dssp_data.rerun_views":  # imports rerun; writes no dataset
            importlib.import_module(module.name)
    return {w.name: w for w in DATASET_WRITERS}


# ------------------------------------------------------------------------------------------- 1. one writer
def _writer_calls(tmp: Path) -> dict[str, tuple]:
    """For each dataset writer: (call, the datasets it writes)."""
    from dssp_data import edit, lerobot, robotwin_hdf5, rosbag2
    from dssp_data.observation import PointCloudConfig
    from dssp_data.recording import RecordingDataset

    a, b = zarr_dataset(tmp / "a.zarr"), zarr_dataset(tmp / "b.zarr", seed=1)
    raw, bag, root = robotwin(tmp / "raw"), write_bag(tmp / "bag", seconds=0.5), lerobot_dataset(tmp / "lerobot", tmp)
    out, val = tmp / "out.zarr", tmp / "val.zarr"
    cloud = PointCloudConfig.from_dict(CLOUD.to_dict())
    return {
        "dssp_data.replay_buffer_writer.write_replay_buffer": (lambda: write_replay_buffer(out, episodes(1)), [out]),
        "dssp_data.replay_buffer_writer.ReplayBufferWriter": (lambda: ReplayBufferWriter(out), [out]),
        "dssp_data.recording.RecordingDataset": (lambda: RecordingDataset(out, {}, {}, ()), [out]),
        "dssp_data.edit.merge": (lambda: edit.merge(out, [a, b], force=True), [out]),
        "dssp_data.edit.split": (lambda: edit.split(a, out, val, val_episodes=[0]), [val]),
        "dssp_data.edit.repair": (lambda: edit.repair(a), [a]),
        "dssp_data.robotwin_hdf5.convert": (lambda: robotwin_hdf5.convert(raw, out), [out]),
        "dssp_data.rosbag2.convert": (
            lambda: rosbag2.convert(
                bag, out, rosbag2.Rosbag2Settings(depth_unit=0.00025), cloud, CAMERA.camera_to_base
            ),
            [out],
        ),
        "dssp_data.lerobot.read.convert": (lambda: lerobot.convert(root, out, cloud, CAMERA.camera_to_base), [out]),
        "dssp_data.lerobot.write.export": (lambda: lerobot.export(a, tmp / "exported"), [tmp / "exported"]),
    }


HOLDER = r"""
import sys
from dssp_core.staging import WriterLock
locks = [WriterLock(path, what="dataset") for path in sys.argv[1:]]
print("held", flush=True)
sys.stdin.read()
for lock in locks:
    lock.release()
"""


@contextmanager
def held_by_another_process(paths: list[Path]):
    """The dataset locks of ``paths`` held by a child process (the one writer whose work is under way); its pid."""
    targets = [str(Path(os.path.realpath(p.parent)) / p.name) for p in paths]
    child = subprocess.Popen(
        [sys.executable, "-c", HOLDER, *targets], cwd=ROOT, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    try:
        assert child.stdout.readline() == "held\n"
        yield child.pid
    finally:
        child.stdin.close()
        child.wait(timeout=60)


def test_every_dataset_writer_is_refused_while_another_holds_its_dataset(tmp_path):
    """Enumerated from the writers' registry: a new writer without a case here fails this test."""
    calls = _writer_calls(tmp_path)
    assert set(all_dataset_writers()) == set(calls)
    for name, (call, held) in calls.items():
        before = snapshot(tmp_path)
        with held_by_another_process(held) as pid, pytest.raises(DatasetError) as info:
            call()
        line = str(info.value)
        assert "\n" not in line and f"is being written by pid {pid} on {os.uname().nodename}" in line, (name, line)
        assert "one writer per dataset" in line, (name, line)
        assert snapshot(tmp_path) == before, name  # nothing read into an output, no staging folder, no lock left
        assert not any(writer_lock_path(p).exists() for p in held), name


def test_a_dataset_written_without_its_lock_is_a_bug_not_data(tmp_path):
    """The writes themselves check the lock: a writer that forgets it fails every time, not only in a race."""
    path = tmp_path / "d.zarr"
    with pytest.raises(RuntimeError, match="written without its writer lock"):
        ReplayBufferWriter(path, lock=False)
    staged = tmp_path / ".d.zarr.tmp-0123abcd"
    staged.mkdir()
    with pytest.raises(RuntimeError, match=f"{path} is written without its writer lock"):
        _write_store(staged, episodes(1), {}, 2)
    assert os.listdir(staged) == [] and not path.exists()
    with dataset_lock(path):  # with it, the same write goes through
        _write_store(staged, episodes(1), {}, 2)


def test_a_second_command_is_refused_while_the_first_writes_and_the_first_completes(tmp_path, capsys, monkeypatch):
    """While `merge OUT --force` writes its first episode, a second merge, split and convert into OUT are each
    refused with one line naming the first; the first then completes with exactly its own episodes."""
    src = tmp_path / "src"
    a, b = zarr_dataset(src / "a.zarr", 2), zarr_dataset(src / "b.zarr", 3, seed=1)
    c = zarr_dataset(src / "c.zarr", 4, seed=2)
    raw = robotwin(src / "raw")
    out = tmp_path / "out.zarr"
    assert data_main(["merge", str(out), str(b), str(c)]) == 0  # an earlier output there, that --force replaces
    capsys.readouterr()
    seconds = {
        "merge": ["merge", out, c, b, "--force"],
        "split": ["split", c, "--train", out, "--val", tmp_path / "v.zarr", "--val-ratio", "0.5", "--force"],
        "convert": ["convert", raw, "--out", out, "--force"],
    }
    real, results = ReplayBufferWriter.add_episode, {}

    def add_episode(writer, episode, attrs=None):
        if not results:
            for name, argv in seconds.items():
                results[name] = cli(capsys, *argv)
        return real(writer, episode, attrs)

    monkeypatch.setattr(ReplayBufferWriter, "add_episode", add_episode)
    code, stdout, _ = cli(capsys, "merge", out, a, b, "--force")
    assert code == 0 and "5 episodes" in stdout
    for name, result in results.items():
        line = refused(result, f"{out} is being written by pid {os.getpid()}", "one writer per dataset")
        assert name and line
    merged = ReplayBuffer.load(out)
    expected = [ReplayBuffer.load(p) for p in (a, b)]
    np.testing.assert_array_equal(merged.state, np.concatenate([e.state for e in expected]))
    assert not (tmp_path / "v.zarr").exists() and not writer_lock_path(out).exists()


# ------------------------------------------------------------------------------------------- 2. bounded memory
def zstd_bomb(size: int, declare: bool = True) -> bytes:
    """A zstd frame of 128 KiB RLE blocks of zeros decoding to ``size`` bytes (4 bytes per block on disk); ``declare``:
    its header says so, else it gives no size."""
    block = 128 << 10
    count = size // block
    head = b"\x28\xb5\x2f\xfd" + (bytes([0xC0, 0x38]) + size.to_bytes(8, "little") if declare else bytes([0x00, 0x38]))
    return head + b"".join(((i == count - 1) | 1 << 1 | block << 3).to_bytes(3, "little") + b"\0" for i in range(count))


def replace_message(bag: Path, topic: str, data: bytes) -> None:
    """The first message of ``topic`` in the bag's sqlite3 file becomes ``data`` (as stored)."""
    [db] = bag.glob("*.db3")
    with sqlite3.connect(db) as con:
        con.execute(
            "UPDATE messages SET data = ? WHERE id = (SELECT min(messages.id) FROM messages JOIN topics ON "
            "messages.topic_id = topics.id WHERE topics.name = ?)",
            (data, topic),
        )


READERS = r"""
import contextlib, io, json, os, resource, sys
from dssp_data.data_cli import main
job = json.load(open(sys.argv[1]))
results, base = [], resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
for case in job:
    os.environ["DSSP_READ_BUDGET"] = case["budget"]
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        code = main(case["argv"])
    results.append({"code": code, "err": err.getvalue(), "rss_kb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss})
json.dump({"base_kb": base, "results": results}, open(sys.argv[2], "w"))
"""


def test_every_reader_refuses_an_input_over_the_read_budget_before_allocating_it(tmp_path):
    """zarr, RoboTwin HDF5, ROS 2 bags (sqlite3 and mcap, compressed or not) and LeRobot v3, each under a small
    DSSP_READ_BUDGET with an input over it: one line naming the budget, and the process's peak memory stays far
    below what the input declares (two bags' messages declare 1 GiB each, from 32 KiB on disk)."""
    src, outs = tmp_path / "src", tmp_path / "outs"
    cal = calibration_flags(src)
    big_chunks = tmp_path / "z.zarr"
    write_replay_buffer(big_chunks, episodes(1, points=4000))  # a chunk of 100 x 4000 points: 4.6 MiB
    raw = src / "raw"
    (raw / "data").mkdir(parents=True)
    with h5py.File(raw / "data" / "episode0.hdf5", "w") as f:
        f["joint_action/vector"] = np.zeros((4, 14))
        f.create_dataset("pointcloud", shape=(4, 10**6, 10**4), dtype="f4", chunks=(1, 1000, 100))  # 160 GB declared
    declared, undeclared = (
        write_bag(src / name, seconds=0.5, compression="message") for name in ("declared", "undeclared")
    )
    replace_message(declared, "/camera/camera/depth/image_rect_raw", zstd_bomb(1 << 30))
    replace_message(undeclared, "/camera/camera/depth/image_rect_raw", zstd_bomb(1 << 30, declare=False))
    plain, chunked = (
        write_bag(src / "plain", seconds=0.5),
        write_bag(src / "chunked", seconds=0.5, storage="mcap", compression="storage"),
    )
    root = lerobot_dataset(src / "lerobot", tmp_path, frames=40)  # 40 frames of 160 x 120 depth: 1.5 MiB decoded
    cases = [
        (["info", big_chunks], "1M", "one chunk of data/point_cloud"),
        (["convert", raw, "--out", outs / "raw.zarr"], "1M", "/pointcloud (shape (4, 1000000, 10000))"),
        (
            ["convert", declared, "--out", outs / "d.zarr", *cal, *BAG_FLAGS],
            "64M",
            "a compressed message (1.0 GiB declared)",
        ),
        (
            ["convert", undeclared, "--out", outs / "u.zarr", *cal, *BAG_FLAGS],
            "64M",
            "a compressed message decodes to more",
        ),
        (["convert", plain, "--out", outs / "p.zarr", *cal, *BAG_FLAGS], "256K", "a message of /camera/camera/depth"),
        (["convert", chunked, "--out", outs / "c.zarr", *cal, *BAG_FLAGS], "256K", "an mcap chunk"),
        (["convert", root, "--out", outs / "l.zarr", *cal], "1M", "file-000.parquet: the columns"),
    ]
    job = [{"argv": [str(a) for a in argv], "budget": budget} for argv, budget, _ in cases]
    (tmp_path / "job.json").write_text(json.dumps(job))
    before = snapshot(tmp_path)
    proc = subprocess.run(
        [sys.executable, "-c", READERS, str(tmp_path / "job.json"), str(tmp_path / "result.json")],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads((tmp_path / "result.json").read_text())
    for (argv, budget, fragment), got in zip(cases, result["results"]):
        line = refused(
            (got["code"], "", got["err"]),
            fragment,
            "over the read budget" if "decodes" not in fragment else "read budget",
            "DSSP_READ_BUDGET",
        )
        assert line, argv
    peak = max(r["rss_kb"] for r in result["results"]) - result["base_kb"]
    assert peak < 300 << 10, f"the readers grew by {peak >> 10} MiB"  # the bombs declare 1 GiB each
    (tmp_path / "result.json").unlink()
    assert snapshot(tmp_path) == before  # nothing written, no output folder created


@settings(**HYPOTHESIS)
@given(
    spec=st.one_of(
        st.from_regex(r"[<>^=]?[+ -]?#?0?[0-9]{0,7}[,_]?(\.[0-9]{0,3})?[dxXsfe%]?", fullmatch=True),
        st.text(alphabet="<>^=+- #_,.0123456789dxXsrfe%{}!", max_size=14),
    ),
    field=st.sampled_from(["chunk_index", "file_index", "0", "", "chunk_index.real", "chunk_index[0]"]),
)
@example(spec=">2000000", field="chunk_index")
@example(spec="09999999d", field="file_index")
@example(spec="03d", field="chunk_index")
@example(spec="", field="chunk_index.real")
def test_a_data_path_template_is_formatted_only_with_small_integer_fields(tmp_path_factory, spec, field):
    """Whatever format a dataset's data_path asks for, it is formatted only as {chunk_index}/{file_index} integers of
    at most 9 digits; anything else is one short line before anything is formatted."""
    root = tmp_path_factory.getbasetemp() / "template_root"
    (root / "data").mkdir(parents=True, exist_ok=True)
    template = "data/c{" + field + (":" + spec if spec else "") + "}-{file_index:03d}.parquet"
    try:
        path = data_file(root, template, 7, 3)
    except DatasetError as exc:
        message = str(exc)
        assert "\n" not in message and len(message) < 600, message
        return
    name = path.name
    assert name.endswith("-003.parquet") and len(name) <= len("c-003.parquet") + 9, name
    assert int(name[1:-12]) == 7


def test_a_huge_format_width_in_info_json_is_one_short_line(tmp_path, capsys):
    root = lerobot_dataset(tmp_path / "lerobot", tmp_path)
    edit_info(
        root, lambda info: info.update(data_path="data/chunk-{chunk_index:>2000000000}/file-{file_index:03d}.parquet")
    )
    before = snapshot(tmp_path)
    line = refused(
        cli(capsys, "convert", root, "--out", tmp_path / "o.zarr", *calibration_flags(tmp_path / "cal")),
        "data_path",
        "is not a template whose fields are {chunk_index} and {file_index}",
    )
    assert len(line) < 400
    assert {k: v for k, v in snapshot(tmp_path).items() if not k.startswith("cal")} == before


# ------------------------------------------------------------------------------------------- 3. files that are not files
def test_metadata_files_that_are_not_files_are_refused_without_blocking(tmp_path, capsys):
    """A FIFO never blocks, a device never fills memory, deep nesting and a key given twice are one line: ROS 2
    metadata.yaml, LeRobot meta/info.json, --pointcloud and --extrinsics."""
    cal = calibration_flags(tmp_path / "cal")
    bag, root = write_bag(tmp_path / "bag", seconds=0.5), lerobot_dataset(tmp_path / "lerobot", tmp_path)
    out = tmp_path / "o.zarr"
    metadata, info = bag / "metadata.yaml", root / "meta" / "info.json"
    good_metadata, good_info = metadata.read_text(), info.read_text()
    deep_json = '{"a": ' + "[" * 10000 + "]" * 10000 + "}"

    def restore():
        for path, text in ((metadata, good_metadata), (info, good_info)):
            path.unlink()
            path.write_text(text)

    cases = [
        (metadata, "fifo", [bag, *cal, *BAG_FLAGS], "metadata.yaml is not a regular file"),
        (metadata, "a: " + "[" * 5000 + "]" * 5000, [bag, *cal, *BAG_FLAGS], "nests more than 64 levels deep"),
        (metadata, "a: &x [1]\nb: *x\n", [bag, *cal, *BAG_FLAGS], "YAML alias"),
        (metadata, good_metadata[: len(good_metadata) // 3], [bag, *cal, *BAG_FLAGS], "metadata.yaml is not a"),
        (metadata, "\0\xff" * 100, [bag, *cal, *BAG_FLAGS], "metadata.yaml is not a"),
        (info, "fifo", [root, *cal], "meta/info.json is not a file"),
        (info, deep_json, [root, *cal], "info.json is not a usable JSON object (nested more than 64 levels deep)"),
        (info, good_info[:-1] + ', "fps": 10}', [root, *cal], "gives the key fps twice"),
    ]
    for path, content, argv, fragment in cases:
        path.unlink()
        if content == "fifo":
            os.mkfifo(path)
        else:
            path.write_text(content)
        before = snapshot(tmp_path)
        with never_blocks():
            refused(cli(capsys, "convert", *argv[:1], "--out", out, *argv[1:]), fragment)
        assert snapshot(tmp_path) == before, fragment
        restore()
    fifo = tmp_path / "settings.json"
    os.mkfifo(fifo)
    for flag, fragment in (("--pointcloud", "is a FIFO"), ("--extrinsics", "is a FIFO")):
        with never_blocks():
            argv = [bag, "--out", out, *cal, *BAG_FLAGS, flag, fifo]
            refused(cli(capsys, "convert", *argv), fragment)
        with never_blocks():
            refused(cli(capsys, "convert", bag, "--out", out, *cal, *BAG_FLAGS, flag, "/dev/zero"), "is a device")
    assert not out.exists()


# ------------------------------------------------------------------------------------------- 4. no tracebacks
def test_damaged_bags_and_frames_are_one_line(tmp_path, capsys):
    """What a crash of `ros2 bag record` leaves (a cut sqlite3 or mcap file, a cut metadata.yaml), a depth image
    whose bytes do not make its rows, a message that does not decode as its type, a topic of another type."""
    cal = [*calibration_flags(tmp_path / "cal"), *BAG_FLAGS]

    def cut(path: Path, keep: float = 0.5) -> None:
        data = path.read_bytes()
        path.write_bytes(data[: int(len(data) * keep)])

    cases = {}
    bag = write_bag(tmp_path / "cut_sqlite", seconds=0.5)
    cut(next(bag.glob("*.db3")))
    cases[bag] = ([], "not a readable sqlite3 bag file")
    bag = write_bag(tmp_path / "cut_mcap", seconds=0.5, storage="mcap", compression="storage")
    cut(next(bag.glob("*.mcap")))
    cases[bag] = ([], "not a readable ROS 2 bag")
    bag = write_bag(tmp_path / "cut_metadata", seconds=0.5)
    cut(bag / "metadata.yaml", 0.3)
    cases[bag] = ([], "metadata.yaml is not a")
    bag = write_bag(tmp_path / "no_storage", seconds=0.5)
    next(bag.glob("*.db3")).unlink()
    cases[bag] = ([], "which is missing")
    bag = write_bag(tmp_path / "odd_bytes", seconds=0.5, image_bytes=lambda data: data + b"\0")
    cases[bag] = ([], "holds 38401 bytes for 120 rows of 320")
    bag = write_bag(tmp_path / "garbage", seconds=0.5)
    replace_message(bag, "/joint_states", b"\x00\x01\x00\x00\xff\xff\xff\x7f")
    cases[bag] = ([], "a message of /joint_states does not decode as sensor_msgs/msg/JointState")
    bag = write_bag(tmp_path / "other_type", seconds=0.5)
    cases[bag] = (
        ["--state-topic", "/camera/camera/depth/camera_info"],
        "/camera/camera/depth/camera_info carries sensor_msgs/msg/CameraInfo, not the sensor_msgs/msg/JointState "
        "--state-topic names",
    )
    for bag, (extra, fragment) in cases.items():
        before = snapshot(tmp_path)
        refused(cli(capsys, "convert", bag, "--out", tmp_path / "o.zarr", *cal, *extra), str(bag), fragment)
        assert snapshot(tmp_path) == before, bag


@pytest.mark.parametrize(
    "argv",
    [
        ["view", "{dataset}", "--episode", "²"],
        ["split", "{dataset}", "--train", "{tmp}/t.zarr", "--val", "{tmp}/v.zarr", "--val-episodes", "²"],
        [
            "split",
            "{dataset}",
            "--train",
            "{tmp}/t.zarr",
            "--val",
            "{tmp}/v.zarr",
            "--val-ratio",
            "0.5",
            "--drop-episodes",
            "1-²",
        ],
    ],
)
def test_an_episode_index_that_is_a_digit_but_no_number_is_one_line(tmp_path, capsys, argv):
    dataset = zarr_dataset(tmp_path / "d.zarr", 3)
    before = snapshot(tmp_path)
    code, out, err = cli(capsys, *(a.format(dataset=dataset, tmp=tmp_path) for a in argv))
    assert code == 2 and out == "" and "²" in one_error_line(err)
    assert snapshot(tmp_path) == before


# ------------------------------------------------------------------------------------------- 5. refused, not accepted
def test_a_folder_of_bags_never_skips_a_bag(tmp_path, capsys):
    """A folder without metadata.yaml (a recording cut short) and a linked bag are refused by name, not skipped."""
    cal = [*calibration_flags(tmp_path / "cal"), *BAG_FLAGS]
    bags = tmp_path / "bags"
    write_bag(bags / "a", seconds=0.5)
    cut = write_bag(bags / "b", seconds=0.5)
    (cut / "metadata.yaml").unlink()
    out = tmp_path / "o.zarr"
    refused(
        cli(capsys, "convert", bags, "--out", out, *cal), f"{cut} is a folder without metadata.yaml", "ros2 bag reindex"
    )
    refused(cli(capsys, "convert", cut, "--out", out, *cal), f"{cut} holds a bag's storage files but no metadata.yaml")
    shutil.rmtree(cut)
    elsewhere = write_bag(tmp_path / "elsewhere", seconds=0.5)
    (bags / "c").symlink_to(elsewhere)
    refused(cli(capsys, "convert", bags, "--out", out, *cal), f"{bags / 'c'} is a link")
    (bags / "c").unlink()
    (bags / "notes.txt").write_text("not a bag")
    refused(cli(capsys, "convert", bags, "--out", out, *cal), "notes.txt is not a bag folder")
    (bags / "notes.txt").unlink()
    code, stdout, err = cli(capsys, "convert", bags, "--out", out, *cal)
    assert code == 0 and "1 episodes (one per bag)" in stdout, err


FIELDS = ("width", "height", "fx", "fy", "ppx", "ppy")
GOOD = (160, 120, 114.25, 114.25, 79.5, 59.5)


@settings(**HYPOTHESIS)
@given(
    field=st.sampled_from(FIELDS),
    value=st.one_of(
        st.floats(allow_nan=True, allow_infinity=True),
        st.integers(-(10**12), 10**12),
        st.booleans(),
        st.none(),
        st.text(max_size=3),
    ),
)
def test_intrinsics_are_checked_once_every_field_finite_and_in_range(field, value):
    values = dict(zip(FIELDS, GOOD), **{field: value})
    ok = {
        "width": lambda v: isinstance(v, int) and not isinstance(v, bool) and 1 <= v <= MAX_IMAGE_SIDE,
        "height": lambda v: isinstance(v, int) and not isinstance(v, bool) and 1 <= v <= MAX_IMAGE_SIDE,
        "fx": lambda v: _number(v) and 0 < v <= MAX_FOCAL_PX,
        "fy": lambda v: _number(v) and 0 < v <= MAX_FOCAL_PX,
        "ppx": lambda v: _number(v) and 0 <= v <= values["width"],
        "ppy": lambda v: _number(v) and 0 <= v <= values["height"],
    }
    expected = all(ok[k](values[k]) for k in FIELDS)
    try:
        Intrinsics(**values)
    except ConfigError as exc:
        assert not expected, exc
        first = next(k for k in FIELDS if not ok[k](values[k]))  # the line names the first field out of range
        assert f"camera intrinsics: {first} is {values[first]!r}; it must be" in str(exc), str(exc)
        assert "\n" not in str(exc)
        return
    assert expected, values


def _number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


@pytest.mark.parametrize(
    "k, distortion, fragment",
    [
        (lambda k: np.array([np.inf, 0, 79.5, 0, 114.25, 59.5, 0, 0, 1]), (0.0,) * 5, "fx is inf"),
        (lambda k: np.array([114.25, 0, np.nan, 0, 114.25, 59.5, 0, 0, 1]), (0.0,) * 5, "ppx is nan"),
        (None, (0.0, float("nan"), 0.0, 0.0, 0.0), "lens distortion D[1] is nan"),
    ],
)
def test_a_bags_camera_info_is_checked_field_by_field(tmp_path, capsys, k, distortion, fragment):
    bag = write_bag(tmp_path / "bag", seconds=0.5, k_of=k, distortion=distortion)
    refused(
        cli(capsys, "convert", bag, "--out", tmp_path / "o.zarr", *calibration_flags(tmp_path / "cal"), *BAG_FLAGS),
        "/camera/camera/depth/camera_info: camera intrinsics: " + fragment,
    )


@pytest.mark.parametrize("fps", [1e-300, 0.05, 2000, float("nan"), "10", True])
def test_a_lerobot_fps_outside_the_control_rates_is_refused(tmp_path, capsys, fps):
    root = edit_info(lerobot_dataset(tmp_path / "lerobot", tmp_path), lambda info: info.update(fps=fps))
    refused(
        cli(capsys, "convert", root, "--out", tmp_path / "o.zarr", *calibration_flags(tmp_path / "cal")),
        "meta/info.json: fps must be in [0.1, 1000] Hz",
    )
    assert not (tmp_path / "o.zarr").exists()


def test_robotwin_and_bag_rates_share_the_control_rate_bounds(tmp_path, capsys):
    raw, bag = robotwin(tmp_path / "raw"), write_bag(tmp_path / "bag", seconds=0.5)
    refused(
        cli(capsys, "convert", raw, "--out", tmp_path / "o.zarr", "--control-rate", "1e-300"),
        "--control-rate must be in [0.1, 1000] Hz",
    )
    refused(
        cli(
            capsys,
            "convert",
            bag,
            "--out",
            tmp_path / "o.zarr",
            "--control-rate",
            "2000",
            *calibration_flags(tmp_path / "cal"),
        ),
        "--control-rate must be in [0.1, 1000] Hz",
    )


# ------------------------------------------------------------------------------------------- 6. never into the input
def test_convert_never_writes_into_its_input(tmp_path, capsys, monkeypatch):
    """An output equal to, inside or holding the source is refused before the source is read."""
    from dssp_data import robotwin_hdf5, rosbag2
    from dssp_data.lerobot import read as lerobot_read

    for module, name in ((robotwin_hdf5, "read_episode"), (rosbag2, "read_bag"), (lerobot_read, "read_info")):
        monkeypatch.setattr(module, name, lambda *a, **k: pytest.fail("the input was read"))
    cal = calibration_flags(tmp_path / "cal")
    src = tmp_path / "src"
    sources = {
        "robotwin": (robotwin(src / "raw"), []),
        "bag": (write_bag(src / "bag", seconds=0.5), [*cal, *BAG_FLAGS]),
        "lerobot": (lerobot_dataset(src / "lerobot", tmp_path), cal),
    }
    before = snapshot(tmp_path)
    for kind, (source, flags) in sources.items():
        for out, fragment in (
            (source, "is also an input"),
            (source / "x.zarr", "lies inside the input"),
            (source / "data" / "x.zarr", "lies inside the input"),
            (src, "holds the input"),
        ):
            refused(cli(capsys, "convert", source, "--out", out, *flags), fragment, "choose another --out")
        assert snapshot(tmp_path) == before, kind


# ------------------------------------------------------------------------------------------- 7. words
def test_a_value_beyond_float32_names_the_input_and_warns_of_nothing(tmp_path, capsys):
    """1e300 in a bag's joint state, a LeRobot state and a RoboTwin joint vector: one line naming the input, the key,
    the value; no numpy warning, no staging folder in the line."""
    cal = calibration_flags(tmp_path / "cal")
    bag = write_bag(tmp_path / "bag", seconds=0.5, joints_of=lambda t: np.array([0.1, 1e300, 0, 0, 0, 0, 0.01]))
    vector = np.zeros((4, 14))
    vector[2, 5] = 1e300
    raw = robotwin(tmp_path / "raw", vector)
    root = lerobot_dataset(tmp_path / "lerobot", tmp_path)
    state = np.zeros((4, 7))
    state[3, 4] = -1e300
    rewrite_column(root / "data/chunk-000/file-000.parquet", "observation.state", state)
    edit_info(root, lambda info: info["features"]["observation.state"].update(dtype="float64"))
    cases = [
        ([bag, *cal, *BAG_FLAGS], f"{bag}: /joint_states's message at", "joint2 = 1e+300"),
        ([raw], "raw/data/episode0.hdf5: /joint_action/vector holds 1e+300 at step 2, index 5", "float32"),
        ([root, *cal], "file-000.parquet (episode 0): observation.state holds -1e+300 at frame 3, index 4", "float32"),
    ]
    for argv, *fragments in cases:
        before = snapshot(tmp_path)
        refused(cli(capsys, "convert", argv[0], "--out", tmp_path / "o.zarr", *argv[1:]), *fragments)
        assert snapshot(tmp_path) == before, argv[0]


def test_the_writer_names_the_output_never_its_staging_folder(tmp_path):
    from dssp_data.edit import ConvertedEpisode, write_converted
    from dssp_data.replay_buffer_writer import dataset_writer

    bad = episodes(1)[0]
    bad.state[1, 2] = np.nan
    out = tmp_path / "out.zarr"

    @dataset_writer(out="--out")
    def convert_two(out):
        return write_converted(out, {}, [ConvertedEpisode("ep_a.h5", episodes(1)[0]), ConvertedEpisode(None, bad)])

    try:
        with pytest.raises(DatasetError) as info:
            convert_two(out)
    finally:
        DATASET_WRITERS.pop()
    assert (
        str(info.value) == f"{out}: episode 1: state holds NaN or inf (first at step 1, index 2: nan): fix the episode"
    )
    assert os.listdir(tmp_path) == []

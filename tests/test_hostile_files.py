"""Files that are not what they seem: links planted in datasets, CAN-log folders and lock files; HDF5
episodes that pull in other files; two writers of one dataset. Each is refused with one line before
anything is written, and whatever the link or the other file points at is neither read into an output nor
changed."""

from __future__ import annotations

import os
import shutil
import stat
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
from conftest import ONE_THREAD_ENV, ROOT, episodes, one_line_message, recorded, refusal, run_data_cli, snapshot
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dssp_core.errors import DatasetError
from dssp_core.files import copy_regular_file
from dssp_core.staging import writer_lock_path
from dssp_data.attributes import zarr_attrs
from dssp_data.data_cli import main as data_main
from dssp_data.recording import RECORDED_KEYS, RecordingDataset, can_log_dir
from dssp_data.replay_buffer import ReplayBuffer
from dssp_data.replay_buffer_writer import ReplayBufferWriter, dataset_lock, write_replay_buffer

SECRET = b"secret: not part of any dataset\n"
SETTINGS = {
    "deadline": None,
    "derandomize": True,
    "database": None,
    "max_examples": 12,
    "suppress_health_check": [HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
}


def secret_file(folder: Path) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "secret.txt"
    path.write_bytes(SECRET)
    return path


def holds_secret(root: Path, outside: Path) -> list[str]:
    """Files under ``root`` but not under ``outside`` (no link followed) that hold the secret."""
    found = []
    for folder, _, files in os.walk(root):
        for name in files:
            path = Path(folder, name)
            if outside in path.parents or not stat.S_ISREG(path.lstat().st_mode):
                continue
            if SECRET in path.read_bytes():
                found.append(str(path))
    return found


# ------------------------------------------------------------------------------------------------ lock files
@pytest.mark.parametrize("where", ["beside", "old name in the CAN-log folder"])
def test_a_lock_file_planted_as_a_link_is_refused_and_its_target_untouched(tmp_path, capsys, where):
    victim = secret_file(tmp_path / "elsewhere")
    path = recorded(tmp_path / "d.zarr", n=2)
    link = writer_lock_path(path) if where == "beside" else can_log_dir(path) / ".recording.lock"
    os.symlink(victim, link)
    before = snapshot(tmp_path)
    with pytest.raises(DatasetError) as info:
        RecordingDataset(path, {"control_rate_hz": 10.0}, {}, RECORDED_KEYS)
    one_line_message(info, str(link.name))
    if where == "beside":
        with pytest.raises(DatasetError) as info:
            ReplayBufferWriter(path)
        one_line_message(info, "not a link")
        refusal(run_data_cli(capsys, "repair", path), "not a link")
    assert victim.read_bytes() == SECRET  # never truncated, never written
    assert snapshot(tmp_path) == before


# ------------------------------------------------------------------------------------------------ copies of CAN logs
def _plant(kind: str, path: Path, outside: Path) -> None:
    """Make the CAN logs of ``path`` not what they seem."""
    logs = can_log_dir(path)
    if kind == "linked folder":  # the whole .can folder is a link to another folder holding "logs"
        shutil.rmtree(logs)
        fake = outside / "fake.can"
        fake.mkdir()
        os.symlink(outside / "secret.txt", fake / "episode_000000.can0.blf")
        (fake / "episode_000001.can0.blf").write_bytes(SECRET)
        os.symlink(fake, logs)
    elif kind == "linked log inside":  # a log that is a link to another file of the folder
        (logs / "episode_000001.can0.blf").unlink()
        os.symlink(logs / "episode_000000.can0.blf", logs / "episode_000001.can0.blf")
    elif kind == "fifo":
        (logs / "episode_000001.can0.blf").unlink()
        os.mkfifo(logs / "episode_000001.can0.blf")
    elif kind == "linked subfolder":
        sub = outside / "sub"
        sub.mkdir()
        (sub / "x.blf").write_bytes(SECRET)
        os.symlink(sub, logs / "sub")
        import zarr

        root = zarr.open_group(str(path), mode="r+", use_consolidated=False)
        infos = list(root.attrs["episode_info"])
        infos[1] = dict(infos[1], can_logs={"can0": "sub/x.blf"})
        root.attrs["episode_info"] = infos


@pytest.mark.parametrize("kind", ["linked folder", "linked log inside", "fifo", "linked subfolder"])
def test_merge_and_split_copy_only_the_inputs_own_regular_files(tmp_path, capsys, kind):
    outside = tmp_path / "outside"
    secret_file(outside)
    a, b = recorded(tmp_path / "a.zarr", n=2), recorded(tmp_path / "b.zarr", n=2, seed=1)
    _plant(kind, b, outside)
    before = snapshot(tmp_path)
    started = time.monotonic()
    refusal(run_data_cli(capsys, "merge", tmp_path / "m.zarr", a, b), str(b.name))
    refusal(
        run_data_cli(
            capsys, "split", b, "--train", tmp_path / "t.zarr", "--val", tmp_path / "v.zarr", "--val-episodes", "1"
        ),
        str(b.name),
    )
    assert time.monotonic() - started < 30  # a FIFO is refused, never waited on
    assert snapshot(tmp_path) == before  # nothing written, no temporary left
    assert holds_secret(tmp_path, outside) == []


def test_copy_regular_file_copies_a_regular_file_with_its_times(tmp_path):
    src = tmp_path / "in" / "a" / "log.blf"
    src.parent.mkdir(parents=True)
    src.write_bytes(b"x" * 3000)
    os.utime(src, ns=(1_000_000_000, 2_000_000_000))
    dst = copy_regular_file(src, tmp_path / "copy.blf", inside=tmp_path / "in", error=DatasetError)
    assert dst.read_bytes() == src.read_bytes() and dst.stat().st_mtime_ns == 2_000_000_000
    with pytest.raises(DatasetError, match="File exists"):  # never over an existing file (or a link there)
        copy_regular_file(src, dst, inside=tmp_path / "in", error=DatasetError)


@settings(**SETTINGS)
@given(depth=st.integers(0, 3), where=st.integers(0, 5), kind=st.sampled_from(["link", "fifo", "link to a fifo"]))
def test_copy_regular_file_refuses_every_link_on_the_way_and_anything_not_regular(tmp_path_factory, depth, where, kind):
    """A folder tree ``in/d0/d1/.../log.blf``; one of its folders (or the file itself) is replaced by a link to
    a copy outside, or the file by a FIFO: the copy is refused with one line, nothing is created."""
    tmp = tmp_path_factory.mktemp("copy")
    inside = tmp / "in"
    folders = [inside] + [inside.joinpath(*[f"d{k}" for k in range(i + 1)]) for i in range(depth)]
    src = folders[-1] / "log.blf"
    src.parent.mkdir(parents=True)
    src.write_bytes(SECRET)
    targets = folders + [src]
    victim = targets[min(where, len(targets) - 1)]
    if kind == "link":
        real = tmp / "real"
        (shutil.copytree if victim.is_dir() else shutil.copy2)(victim, real)
        shutil.rmtree(victim) if victim.is_dir() else victim.unlink()
        os.symlink(real, victim)
    else:
        src.unlink()
        if kind == "fifo":
            os.mkfifo(src)
        else:
            os.mkfifo(tmp / "fifo")
            os.symlink(tmp / "fifo", src)
    with pytest.raises(DatasetError) as info:
        copy_regular_file(src, tmp / "out.blf", inside=inside, error=DatasetError)
    one_line_message(info)
    assert not (tmp / "out.blf").exists()


# ------------------------------------------------------------------------------------------------ appending through links
@settings(**SETTINGS)
@given(data=st.data())
def test_appending_refuses_a_link_anywhere_in_the_dataset(tmp_path_factory, data):
    """Any entry of the dataset's folder (an array folder such as data/state, a chunk, a metadata file, the
    dataset itself) replaced by a link to a copy elsewhere: the writer, a recording session and repair refuse
    with one line, and neither the dataset nor what the link points at changes."""
    tmp = tmp_path_factory.mktemp("append")
    path = tmp / "d.zarr"
    write_replay_buffer(path, episodes(2), attrs={"control_rate_hz": 10.0})
    entries = sorted(str(p.relative_to(path)) for p in path.rglob("*")) + ["."]
    chosen = data.draw(st.sampled_from(entries), label="linked entry")
    victim = (path / chosen) if chosen != "." else path
    elsewhere = tmp / "elsewhere"
    (shutil.copytree if victim.is_dir() else shutil.copy2)(victim, elsewhere)
    shutil.rmtree(victim) if victim.is_dir() else victim.unlink()
    os.symlink(elsewhere, victim)
    before = snapshot(tmp), snapshot(elsewhere) if elsewhere.is_dir() else elsewhere.read_bytes()
    for attempt in (
        lambda: ReplayBufferWriter(path).add_episode(episodes(1, seed=5)[0]),
        lambda: ReplayBufferWriter(path, repair_incomplete_tail=True),
        lambda: RecordingDataset(path, {"control_rate_hz": 10.0}, {}, ()),
    ):
        with pytest.raises(DatasetError) as info:
            attempt()
        one_line_message(info, "symbolic link")
    assert data_main(["repair", str(path)]) == 2
    assert (snapshot(tmp), snapshot(elsewhere) if elsewhere.is_dir() else elsewhere.read_bytes()) == before
    assert not writer_lock_path(path).exists()  # every refused writer let go of the lock


@pytest.mark.parametrize("what", ["link to /dev/zero", "fifo", "linked array folder"])
def test_readers_refuse_links_and_special_files_inside_a_dataset(tmp_path, capsys, what):
    path = tmp_path / "d.zarr"
    write_replay_buffer(path, episodes(2), attrs={"control_rate_hz": 10.0})
    chunk = path / "data" / "state" / "0.0"
    if what == "link to /dev/zero":
        chunk.unlink()
        os.symlink("/dev/zero", chunk)
    elif what == "fifo":
        chunk.unlink()
        os.mkfifo(chunk)
    else:
        other = tmp_path / "other.zarr"
        write_replay_buffer(other, episodes(2, seed=3))
        shutil.rmtree(path / "data" / "state")
        os.symlink(other / "data" / "state", path / "data" / "state")
    started = time.monotonic()
    with pytest.raises(DatasetError) as info:
        ReplayBuffer.load(path)
    one_line_message(info, "data/state")
    refusal(run_data_cli(capsys, "info", path), "data/state")
    assert time.monotonic() - started < 30  # neither /dev/zero nor the FIFO is read


def test_metadata_files_are_not_read_through_links(tmp_path):
    path = tmp_path / "d.zarr"
    write_replay_buffer(path, episodes(1), attrs={"generator": "dssp_sim.collect", "task": "tap"})
    assert zarr_attrs(path)["task"] == "tap"
    (path / ".zattrs").unlink()
    os.symlink("/dev/zero", path / ".zattrs")  # followed, this would never end
    assert zarr_attrs(path) == {}


# ------------------------------------------------------------------------------------------------ HDF5 pulling in other files
def _robotwin(path: Path, without: str = "") -> h5py.File:
    """A RoboTwin episode file open for writing, without its ``"vector"`` or ``"cloud"`` (the caller adds it)."""
    f = h5py.File(path, "w")
    if without != "vector":
        f["joint_action/vector"] = np.zeros((4, 14))
    if without != "cloud":
        f["pointcloud"] = np.zeros((4, 16, 6), np.float32)
    return f


def _crafted(kind: str, folder: Path) -> tuple[Path, str]:
    """An episode file that pulls values from ``other.h5`` / ``secret.bin``; (its path, the object named)."""
    folder.mkdir(parents=True)
    other = folder / "other.h5"
    with h5py.File(other, "w") as f:
        f["pc"] = np.full((4, 16, 6), 7.0, np.float32)
    secret = folder / "secret.bin"
    np.full((4, 14), 9.0).tofile(secret)
    path = folder / "data" / "episode0.hdf5"
    path.parent.mkdir()
    if kind == "external link":
        with _robotwin(path, without="cloud") as f:
            f["pointcloud"] = h5py.ExternalLink(str(other), "/pc")
        return path, "/pointcloud"
    if kind == "external link to a group":
        with _robotwin(path) as f:
            f["observation"] = h5py.ExternalLink(str(other), "/")
        return path, "/observation"
    if kind == "soft link through an external link":
        with _robotwin(path, without="cloud") as f:
            f["cache/other"] = h5py.ExternalLink(str(other), "/")
            f["pointcloud"] = h5py.SoftLink("/cache/other/pc")
        return path, "/cache/other"
    if kind == "external storage":
        with _robotwin(path, without="vector") as f:
            f.create_dataset("joint_action/vector", shape=(4, 14), dtype="f8", external=[(str(secret), 0, 4 * 14 * 8)])
        return path, "/joint_action/vector"
    with _robotwin(path, without="cloud") as f:
        layout = h5py.VirtualLayout(shape=(4, 16, 6), dtype="f4")
        layout[...] = h5py.VirtualSource(str(other), "pc", shape=(4, 16, 6))
        f.create_virtual_dataset("pointcloud", layout)
    return path, "/pointcloud"


@pytest.mark.parametrize(
    "kind",
    [
        "external link",
        "external link to a group",
        "soft link through an external link",
        "external storage",
        "virtual dataset",
    ],
)
def test_convert_refuses_hdf5_files_that_pull_in_other_files(tmp_path, capsys, kind):
    path, name = _crafted(kind, tmp_path / "task")
    with h5py.File(path, "r") as f:  # h5py itself reads the other file's values through it
        read = {"external link to a group": "observation/pc", "soft link through an external link": "pointcloud"}
        assert (f[read.get(kind, name)][()] == (9.0 if kind == "external storage" else 7.0)).all()
    before = snapshot(tmp_path)
    refusal(
        run_data_cli(capsys, "convert", tmp_path / "task", "--out", tmp_path / "o.zarr"),
        f"{path}: {name}",
        "self-contained",
    )
    assert snapshot(tmp_path) == before


@pytest.mark.parametrize("kind", ["deflate bomb", "lzf", "declared too large"])
def test_convert_reads_hdf5_data_within_bounds(tmp_path, capsys, kind, monkeypatch):
    import zlib

    path = tmp_path / "task" / "data" / "episode0.hdf5"
    path.parent.mkdir(parents=True)
    with _robotwin(path, without="cloud") as f:
        if kind == "deflate bomb":  # 20 kB on disk, 20 MiB decoded, in a chunk of 1.5 KiB
            d = f.create_dataset("pointcloud", shape=(4, 16, 6), dtype="f4", chunks=(4, 16, 6), compression="gzip")
            d.id.write_direct_chunk((0, 0, 0), zlib.compress(b"\0" * (20 << 20), 9))
            fragment = "decompression bomb"
        elif kind == "lzf":
            f.create_dataset("pointcloud", data=np.ones((4, 16, 6), np.float32), compression="lzf")
            fragment = "HDF5 filter 32000"
        else:
            f.create_dataset("pointcloud", shape=(4, 10**6, 10**4), dtype="f4", chunks=(1, 1000, 100))
            fragment = "over the read budget of 4.0 GiB (DSSP_READ_BUDGET)"
    monkeypatch.delenv("DSSP_READ_BUDGET", raising=False)
    before = snapshot(tmp_path)
    refusal(run_data_cli(capsys, "convert", tmp_path / "task", "--out", tmp_path / "o.zarr"), "/pointcloud", fragment)
    assert snapshot(tmp_path) == before


# ------------------------------------------------------------------------------------------------ one writer per dataset
def test_a_second_writer_of_a_dataset_is_refused_and_the_first_untouched(tmp_path, capsys):
    path = tmp_path / "d.zarr"
    write_replay_buffer(path, episodes(2), attrs={"control_rate_hz": 10.0})
    first = ReplayBufferWriter(path)
    first.add_episode(episodes(1, seed=1)[0])
    before = snapshot(path)
    pid = f"pid {os.getpid()}"
    for attempt, doing in (
        (lambda: ReplayBufferWriter(path), "is being written by"),
        (lambda: RecordingDataset(path, {"control_rate_hz": 10.0}, {}, ()), "is being written by"),
    ):
        with pytest.raises(DatasetError) as info:
            attempt()
        one_line_message(info, doing, pid, "one writer per dataset")
    refusal(run_data_cli(capsys, "repair", path), pid)
    first.add_episode(episodes(1, seed=2)[0])  # the first goes on as if nothing happened
    first.close()
    assert snapshot(path) != before and ReplayBuffer.load(path).n_episodes == 4
    with ReplayBufferWriter(path) as again:  # once let go, the next writer gets it
        again.add_episode(episodes(1, seed=3)[0])
    assert ReplayBuffer.load(path).n_episodes == 5


def test_a_recording_session_holds_the_dataset_against_other_writers(tmp_path):
    path = tmp_path / "d.zarr"
    session = RecordingDataset(path, {"control_rate_hz": 10.0}, {}, ())
    try:
        with pytest.raises(DatasetError) as info:
            ReplayBufferWriter(path)
        one_line_message(info, "is being recorded into by", f"pid {os.getpid()}")
    finally:
        session.close()
    ReplayBufferWriter(path).close()


def test_a_second_collect_into_one_dataset_is_refused(tmp_path):
    """A collect (here: a lock held by this process) writes into out.zarr; dssp-sim collect into the same
    dataset, in another process, exits 2 with one line before its simulation starts, changing nothing."""
    out = tmp_path / "out.zarr"
    write_replay_buffer(out, episodes(2), attrs={"generator": "dssp_sim.collect", "task": "tap", "next_seed": 2})
    lock = dataset_lock(out, flag="--out")
    try:
        before = snapshot(tmp_path)
        proc = subprocess.run(
            [
                sys.executable,
                "-m",
                "dssp_sim.sim_cli",
                "collect",
                "--task",
                "tap",
                "--episodes",
                "1",
                "--out",
                str(out),
                "--no-progress",
            ],
            cwd=ROOT,
            env=ONE_THREAD_ENV,
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert proc.returncode == 2, proc.stderr
        lines = proc.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("error: ") and f"pid {os.getpid()}" in lines[0], proc.stderr
        assert "one writer per dataset" in lines[0]
        assert snapshot(tmp_path) == before
    finally:
        lock.release()
    assert not writer_lock_path(out).exists()

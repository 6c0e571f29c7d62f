"""Where ``dssp-data`` writes: merge, split and convert replace only datasets they made (with their ``.can``
CAN logs), never an input or anything inside one; outputs under a file or in a folder that cannot be written
are one line; Ctrl-C leaves no temporary behind and a killed command's temporaries are swept by the next
one; ``info | head`` ends quietly; a negative seed is refused."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import DP3_DATASET, ONE_THREAD_ENV, ROOT, episodes, recorded, refusal, run_data_cli, snapshot
from waiting import wait_for

from dssp_data.recording import can_log_dir
from dssp_data.replay_buffer import ReplayBuffer
from dssp_data.replay_buffer_writer import write_replay_buffer
from dssp_train.data.synthetic import write_tap_count_dataset


def plain(path: Path, n: int = 3, seed: int = 1, **attrs) -> Path:
    write_replay_buffer(path, episodes(n, seed), attrs={"control_rate_hz": 10.0, **attrs})
    return path


def write_robotwin(folder: Path, n: int = 2) -> Path:
    import h5py

    rng = np.random.default_rng(0)
    (folder / "data").mkdir(parents=True)
    for k in range(n):
        with h5py.File(folder / "data" / f"episode{k}.hdf5", "w") as f:
            f["joint_action/vector"] = rng.uniform(-1, 1, (4, 14))
            f["pointcloud"] = rng.uniform(0, 1, (4, 8, 6)).astype(np.float32)
    return folder


def leftovers(folder: Path) -> list[str]:
    return sorted(n for n in os.listdir(folder) if ".tmp-" in n or ".partial-" in n or ".old-" in n)


@pytest.fixture
def inputs(tmp_path):
    """Two datasets to merge or split (one recorded, with CAN logs), a RoboTwin folder to convert."""
    src = tmp_path / "src"
    src.mkdir()
    return recorded(src / "a.zarr"), plain(src / "b.zarr"), write_robotwin(src / "robotwin")


def commands(inputs, out, force):
    a, b, raw = inputs
    flag = ["--force"] if force else []
    other = out.parent / "other.zarr"
    return {
        "merge OUT": ["merge", out, a, b, *flag],
        "split --train": ["split", a, "--train", out, "--val", other, "--val-episodes", "0", *flag],
        "split --val": ["split", a, "--train", other, "--val", out, "--val-episodes", "0", *flag],
        "convert --out": ["convert", raw, "--out", out, *flag],
    }


# ------------------------------------------------------------------ 1. only their own datasets are replaced
FOREIGN = {
    "a recorded dataset and its CAN logs": lambda p: recorded(p, n=5, seed=7),
    "a synthetic dataset": lambda p: write_tap_count_dataset(p, 2, n_points=24),
    "an older merge output": lambda p: plain(
        p, merged_from=[{"path": "x.zarr", "episodes": 3}], generator="dssp-record"
    ),
    "a folder with a file": lambda p: (p.mkdir(), (p / "notes.txt").write_text("keep me")),
    "a file": lambda p: p.write_text("not a dataset"),
}


@pytest.mark.parametrize("what", FOREIGN)
def test_merge_split_convert_never_replace_what_they_did_not_make(tmp_path, capsys, inputs, what):
    work = tmp_path / "work"
    work.mkdir()
    out = work / "X.zarr"
    FOREIGN[what](out)
    before = snapshot(tmp_path)
    for force in (False, True):
        for name, argv in commands(inputs, out, force).items():
            line = refusal(run_data_cli(capsys, *argv), str(out))
            assert "is not a dataset made by dssp-data merge, split or convert" in line, (name, line)
            assert "nothing is deleted" in line and "pass --force" not in line, (name, line)
            assert snapshot(tmp_path) == before, (name, force)


def test_can_logs_without_their_dataset_are_never_replaced(tmp_path, capsys, inputs):
    out = tmp_path / "X.zarr"
    can_log_dir(out).mkdir()
    (can_log_dir(out) / "episode_000000.can0.blf").write_bytes(b"someone's log")
    before = snapshot(tmp_path)
    for force in (False, True):
        for name, argv in commands(inputs, out, force).items():
            refusal(run_data_cli(capsys, *argv), f"{can_log_dir(out)} exists without X.zarr", "nothing is deleted")
            assert snapshot(tmp_path) == before, name


def test_own_output_is_replaced_only_with_force_together_with_its_can_logs(tmp_path, capsys, inputs):
    a, b, raw = inputs
    out = tmp_path / "m.zarr"
    assert run_data_cli(capsys, "merge", out, a, b)[0] == 0
    assert sorted(os.listdir(can_log_dir(out))) == [f"episode_{i:06d}.can0.blf" for i in range(3)]
    assert ReplayBuffer.load(out).attrs["generator"] == "dssp-data merge"

    before = snapshot(tmp_path)
    refusal(run_data_cli(capsys, "merge", out, a, b), "already holds a dataset from dssp-data", "pass --force")
    assert snapshot(tmp_path) == before

    # replaced by a dataset without CAN logs: the old CAN logs go with the old dataset
    assert run_data_cli(capsys, "convert", raw, "--out", out, "--force")[0] == 0
    assert ReplayBuffer.load(out).n_episodes == 2 and not can_log_dir(out).exists()
    assert ReplayBuffer.load(out).attrs["generator"] == "dssp-data convert"
    assert run_data_cli(capsys, "merge", out, b, a, "--force")[0] == 0  # and a dataset with CAN logs
    assert sorted(os.listdir(can_log_dir(out))) == [f"episode_{i:06d}.can0.blf" for i in range(3, 6)]
    assert (
        run_data_cli(
            capsys, "split", out, "--train", tmp_path / "t.zarr", "--val", out, "--val-episodes", "0", "--force"
        )[0]
        == 2
    )  # the input itself is never an output
    train, val = tmp_path / "t.zarr", tmp_path / "v.zarr"
    assert run_data_cli(capsys, "split", out, "--train", train, "--val", val, "--val-episodes", "0")[0] == 0
    assert run_data_cli(capsys, "split", out, "--train", train, "--val", val, "--val-episodes", "1", "--force")[0] == 0
    assert ReplayBuffer.load(val).attrs["split_from"]["episodes"] == [1]
    assert leftovers(tmp_path) == [] and leftovers(a.parent) == []

    # an older convert output (its generator named the source format) is recognised as convert's own
    legacy = plain(tmp_path / "legacy.zarr", generator="dssp-data convert (RoboTwin raw HDF5)")
    assert run_data_cli(capsys, "convert", raw, "--out", legacy, "--force")[0] == 0
    assert ReplayBuffer.load(legacy).n_episodes == 2


def test_an_own_output_whose_can_folder_holds_other_files_is_refused(tmp_path, capsys, inputs):
    a, b, _ = inputs
    out = tmp_path / "m.zarr"
    assert run_data_cli(capsys, "merge", out, a, b)[0] == 0
    (can_log_dir(out) / "notes.txt").write_text("mine")
    before = snapshot(tmp_path)
    refusal(run_data_cli(capsys, "merge", out, a, b, "--force"), "holds files", "nothing is deleted")
    assert snapshot(tmp_path) == before


# ------------------------------------------------------------------ 3. outputs under a file, or unwritable
def test_outputs_under_a_file_or_an_unwritable_folder_are_one_line(tmp_path, capsys, inputs):
    a, b, raw = inputs
    a_file = tmp_path / "some_file"
    a_file.write_text("x")
    (tmp_path / "file.zarr").write_text("x")
    before = snapshot(tmp_path)
    cases = [
        (["merge", a_file / "m.zarr", a, b], "is a file, not a folder"),
        (["split", a, "--train", a_file / "t.zarr", "--val", tmp_path / "v.zarr", "--val-ratio", "0.5"], "is a file"),
        (["convert", raw, "--out", tmp_path / "file.zarr" / "sub"], "is a file, not a folder"),
        (["view", a, "--episode", "0", "--out", a_file], "is a file, not a folder"),
        (["view", a, "--episode", "0", "--out", a_file / "sub"], "is a file, not a folder"),
        (["merge", "/proc/m.zarr", a, b], "/proc"),
        (["view", a, "--episode", "0", "--out", "/proc/views"], "/proc"),
    ]
    for argv, fragment in cases:
        line = refusal(run_data_cli(capsys, *argv), fragment)
        assert "choose" in line, line
    assert snapshot(tmp_path) == before


# ------------------------------------------------------------------ 4. never into an input
def test_an_output_is_never_an_input_or_inside_one(tmp_path, capsys, inputs):
    a, b, raw = inputs
    before = snapshot(tmp_path)
    cases = [
        (["view", a, "--episode", "0", "--out", a], "is also an input"),
        (["view", a, "--episode", "0", "--out", a / "data"], "lies inside the input"),
        (["view", a, "--episode", "0", "--out", can_log_dir(a)], "is also an input"),
        (["merge", a / "data" / "new.zarr", a, b], "lies inside the input"),
        (["merge", can_log_dir(a) / "new.zarr", a, b], "lies inside the input"),
        (["merge", a, a, b, "--force"], "is also an input"),
        (["merge", tmp_path / "m.zarr", a, a], "is given twice"),
        (["merge", tmp_path / "m.zarr", a, b, Path(str(a) + "/")], "is given twice"),
        (["merge", tmp_path / "m.zarr", a, b, a.parent / "." / a.name], "is given twice"),
        (["split", a, "--train", a, "--val", tmp_path / "v.zarr", "--val-ratio", "0.5", "--force"], "is also an input"),
        (
            ["split", a, "--train", a / "meta" / "t.zarr", "--val", tmp_path / "v.zarr", "--val-ratio", "0.5"],
            "lies inside the input",
        ),
        (
            ["split", a, "--train", tmp_path / "v.zarr" / "t.zarr", "--val", tmp_path / "v.zarr", "--val-ratio", "0.5"],
            "lies inside the input",
        ),
        (["convert", raw, "--out", raw], "is also an input"),
        (["convert", raw, "--out", raw / "data" / "x.zarr"], "lies inside the input"),
        (["convert", raw, "--out", raw.parent], "holds the input"),
    ]
    for argv, fragment in cases:
        refusal(run_data_cli(capsys, *argv), fragment)
        assert snapshot(tmp_path) == before, argv
    os.symlink(a, tmp_path / "link.zarr")
    before = snapshot(tmp_path)
    refusal(run_data_cli(capsys, "merge", tmp_path / "m.zarr", a, tmp_path / "link.zarr"), "is given twice")
    refusal(run_data_cli(capsys, "view", a, "--episode", "0", "--out", tmp_path / "link.zarr" / "meta"), "inside")
    assert snapshot(tmp_path) == before


# ------------------------------------------------------------------ 7. seeds
def test_a_negative_seed_is_refused(tmp_path, capsys, inputs):
    a, _, _ = inputs
    before = snapshot(tmp_path)
    argv = ["split", a, "--train", tmp_path / "t.zarr", "--val", tmp_path / "v.zarr", "--val-ratio", "0.5"]
    refusal(run_data_cli(capsys, *argv, "--seed", "-1"), "--seed must be a non-negative integer, got -1")
    assert snapshot(tmp_path) == before
    assert run_data_cli(capsys, *argv, "--seed", "0")[0] == 0


# ------------------------------------------------------------------ 6. a closed pipe
def test_info_into_a_closed_pipe_ends_quietly():
    proc = subprocess.Popen(
        [sys.executable, "-m", "dssp_data.data_cli", "info", str(DP3_DATASET)],
        cwd=ROOT,
        env=ONE_THREAD_ENV,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    proc.stdout.close()  # the reader is gone before anything is written (``| head -0``)
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=120) == 141 and err == "", err


# ------------------------------------------------------------------ 2. Ctrl-C and kill -9
def _start(argv, cwd):
    return subprocess.Popen(
        [sys.executable, "-m", "dssp_data.data_cli", *map(str, argv)],
        cwd=cwd,
        env=ONE_THREAD_ENV,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def _wait_for_staging(proc, folder: Path, prefix: str, timeout: float = 60.0, old: frozenset = frozenset()) -> bool:
    """Wait until ``proc`` has started writing (a staging directory not in ``old`` exists); False if it ended first."""

    def writing() -> bool:
        return any(n.startswith(prefix) and n not in old for n in os.listdir(folder))

    wait_for(
        lambda: writing() or proc.poll() is not None, timeout=timeout, what=f"{prefix}* or the command's end", poll=0.01
    )
    return writing()


def _chunks_staged(folder: Path, prefix: str, old: frozenset = frozenset()) -> int:
    """How many point-cloud chunks the command has written so far into its staging directory (``prefix*``, not
    one in ``old``): how far its copy has got (0 while there is no such directory)."""
    for name in os.listdir(folder):
        if name.startswith(prefix) and name not in old:
            try:
                return sum(not n.startswith(".") for n in os.listdir(folder / name / "data" / "point_cloud"))
            except (FileNotFoundError, NotADirectoryError):  # not made yet, or already moved or removed
                return 0
    return 0


def _wait_for_chunks(
    proc, folder: Path, prefix: str, chunks: int, timeout: float = 60.0, old: frozenset = frozenset()
) -> None:
    """Wait until ``proc`` has written ``chunks`` point-cloud chunks into its staging directory, or has ended."""
    wait_for(
        lambda: _chunks_staged(folder, prefix, old) >= chunks or proc.poll() is not None,
        timeout=timeout,
        what=f"{chunks} point-cloud chunks in {prefix}* or the command's end",
        poll=0.005,
    )


@pytest.fixture(scope="module")
def big(tmp_path_factory):
    """Two datasets large enough that merging them takes a few seconds (120 episodes of 512 points each)."""
    root = tmp_path_factory.mktemp("big")
    write_tap_count_dataset(root / "a.zarr", 120, n_points=512)
    shutil.copytree(root / "a.zarr", root / "b.zarr")
    return root


def test_ctrl_c_leaves_no_temporary_and_a_killed_run_is_swept(big):
    interrupted = 0
    # zarr's writes go on in their own thread after the main one is interrupted, and whether one lands after the
    # temporary was removed depends on the moment: a dozen runs at different moments of the copy, each once a
    # number of point-cloud chunks is written (of the merge's 96 and the split's 34)
    # (the staging folders, not the writer's lock file .m.zarr.lock beside them)
    runs = [(["merge", "m.zarr", "a.zarr", "b.zarr"], ".m.zarr.tmp-", 2 * k) for k in range(12)]
    runs.append((["split", "a.zarr", "--train", "t.zarr", "--val", "v.zarr", "--val-ratio", "0.3"], ".t.zarr.tmp-", 6))
    for argv, prefix, chunks in runs:
        before = sorted(os.listdir(big))
        proc = _start(argv, big)
        started = _wait_for_staging(proc, big, prefix)
        _wait_for_chunks(proc, big, prefix, chunks)
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=120)
        assert "Traceback" not in err, err
        if started and proc.returncode == 130 and err.startswith("interrupted after writing"):
            # the Ctrl-C came once the outputs were in place: they stay, complete and named; no temporary left
            written = sorted(set(os.listdir(big)) - set(before))
            assert written and all(name in err and not name.startswith(".") for name in written), (written, err)
            assert len(err.strip().splitlines()) == 1
            for name in written:
                shutil.rmtree(big / name)
        elif started and proc.returncode == 130:
            interrupted += 1
            assert err.strip() == "interrupted" and out == "", (out, err)
            assert sorted(os.listdir(big)) == before  # nothing written, no temporary left
        else:  # it finished before the signal arrived
            assert proc.returncode == 0, (proc.returncode, err)
            for name in ("m.zarr", "t.zarr", "v.zarr"):
                shutil.rmtree(big / name, ignore_errors=True)
    assert interrupted >= 8

    # kill -9: nothing can clean up; the next command writing the same output removes its temporaries only
    proc = _start(["merge", "m.zarr", "a.zarr", "b.zarr"], big)
    started = _wait_for_staging(proc, big, ".m.zarr.tmp-")
    proc.kill()
    proc.communicate(timeout=60)
    stale = [n for n in os.listdir(big) if n.startswith(".m.zarr.tmp-")]
    assert started and stale
    decoys = [".m.zarr.old-12345678", ".m.zarr.tmp-notours", ".other.zarr.tmp-12345678"]
    for name in decoys:
        (big / name).mkdir()
    (big / ".m.zarr.tmp-abcdef12").write_text("a file, not a staging folder")
    proc = _start(["merge", "m.zarr", "a.zarr", "b.zarr"], big)
    old = frozenset(stale + decoys) | {".m.zarr.tmp-abcdef12"}
    assert _wait_for_staging(proc, big, ".m.zarr.tmp-", old=old)
    assert not any((big / name).exists() for name in stale)  # swept before the new one was made
    _wait_for_chunks(proc, big, ".m.zarr.tmp-", 4, old=old)  # the Ctrl-C comes in the middle of the copy
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert "Traceback" not in err, err
    left = sorted(n for n in os.listdir(big) if n.startswith("."))
    assert left == sorted(decoys + [".m.zarr.tmp-abcdef12"]), left

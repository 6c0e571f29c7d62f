"""Damaged zarr chunks: every reader raises one DatasetError line naming the key (the CLIs exit 2), never
crashes and never reads zeros that were not written; the writer stores every chunk; CAN-log names read from
a dataset stay inside its CAN-log folder; ``dssp-data info`` exits 1 when it lists problems."""

import contextlib
import io
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numcodecs
import numpy as np
import pytest
import zarr
from conftest import copy_dataset, one_line_message, snapshot
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from dssp_core.errors import DatasetError
from dssp_data.bounded import blosc_problem as _blosc_problem
from dssp_data.data_cli import main as data_main
from dssp_data.dataset_layout import Episode
from dssp_data.edit import merge, repair, split
from dssp_data.inspect import inspect_dataset
from dssp_data.recording import can_log_dir
from dssp_data.replay_buffer import ReplayBuffer, ReplayBufferReader
from dssp_data.replay_buffer_writer import ReplayBufferWriter, write_replay_buffer
from dssp_data.view import render_episode
from dssp_data.zarr_chunks import EVERY_CHUNK_ATTR

FORMATS = (2, 3)
LENGTHS = (60, 90, 70)
"""220 steps: time chunks of 100 steps 0..99, 100..199, 200..219; episode 1 spans chunks 0 and 1."""
ENDS = np.cumsum(LENGTHS)
EXTRAS = ("step_problems", "timestamp")
KEYS = ("data/point_cloud", "data/state", "data/action", "meta/episode_ends", "data/timestamp", "data/step_problems")
SETTINGS = {"deadline": None, "derandomize": True, "database": None, "suppress_health_check": [HealthCheck.too_slow]}


def make_episodes(lengths=LENGTHS, seed=0):
    """Random episodes with extras; every step_problems value is 0 and the actions of steps 200.. are 0, so some
    chunks hold only the fill value (zarr 3 would leave them out unless told to store them)."""
    rng = np.random.default_rng(seed)
    episodes, start = [], 0
    for n in lengths:
        action = rng.normal(size=(n, 7)).astype(np.float32)
        action[max(0, 200 - start) :] = 0.0
        episodes.append(
            Episode(
                rng.normal(size=(n, 8, 3)).astype(np.float32),
                rng.normal(size=(n, 7)).astype(np.float32),
                action,
                {"step_problems": np.zeros(n, np.uint8), "timestamp": np.arange(n, dtype=np.float64) / 10.0},
            )
        )
        start += n
    return episodes


def write_dataset(path, zarr_format, episodes=None):
    episodes = make_episodes() if episodes is None else episodes
    infos = [
        {"index": i, "can_logs": {"can0": f"episode_{i:06d}.can0.blf"}, "problems": []} for i in range(len(episodes))
    ]
    write_replay_buffer(path, episodes, attrs={"control_rate_hz": 10.0, "episode_info": infos}, zarr_format=zarr_format)
    can_log_dir(path).mkdir()
    for i in range(len(episodes)):
        (can_log_dir(path) / f"episode_{i:06d}.can0.blf").write_bytes(b"log %d" % i)
    return path


def chunk_file(path, key, c):
    """The file of time chunk ``c`` of ``key`` (first chunk along the other axes), named as zarr names it."""
    array = zarr.open_group(str(path), mode="r", use_consolidated=False)[key]
    return Path(path) / key / array.metadata.encode_chunk_key((c,) + (0,) * (array.ndim - 1))


def cli(*argv):
    """dssp-data in-process: (exit code, stdout, stderr)."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = data_main([str(a) for a in argv])
    return code, out.getvalue(), err.getvalue()


def assert_names(exc_info, key, c=None):
    """The raised error's message is one line naming ``key`` (and time chunk ``c``, if given)."""
    message = one_line_message(exc_info, key)
    if c is not None:
        assert f"chunk {c} " in message, message


@pytest.fixture(scope="module")
def originals(tmp_path_factory):
    """{zarr format: a pristine dataset}, and the values it holds."""
    root = tmp_path_factory.mktemp("originals")
    paths = {fmt: write_dataset(root / f"v{fmt}.zarr", fmt) for fmt in FORMATS}
    return paths, ReplayBuffer.load(paths[2], extras=True)


# ------------------------------------------------------------------------------------------------ the writer
@pytest.mark.parametrize("zarr_format", FORMATS)
def test_writer_stores_every_chunk(tmp_path, zarr_format):
    path = tmp_path / "ds.zarr"
    episodes = make_episodes()
    write_replay_buffer(path, episodes[:2], zarr_format=zarr_format)
    with ReplayBufferWriter(path, extra_keys=EXTRAS) as writer:
        writer.add_episode(episodes[2])  # appended chunks of fill values are stored too
    root = zarr.open_group(str(path), mode="r", use_consolidated=False)
    for key in KEYS:
        array = root[key]
        assert array.attrs[EVERY_CHUNK_ATTR] is True
        for c in range(-(-array.shape[0] // array.chunks[0])):
            assert chunk_file(path, key, c).is_file(), (key, c)
    buffer = ReplayBuffer.load(path, extras=True)
    assert not buffer.extras["step_problems"].any() and not buffer.action[200:].any()
    assert ReplayBufferReader(path).check_chunks() == {}


# ------------------------------------------------------------------------------------------------ every reader
def _episode_at(key, c):
    """An episode that the damaged chunk holds steps of (any for episode_ends)."""
    return 0 if key == "meta/episode_ends" else int(np.searchsorted(ENDS, 100 * c, side="right"))


def _damage(path, key, c, how, data):
    target = chunk_file(path, key, c)
    raw = target.read_bytes()
    if how == "delete":
        target.unlink()
    elif how == "truncate":
        target.write_bytes(raw[: data.draw(st.integers(0, len(raw) - 1), label="kept bytes")])
    else:
        garbage = data.draw(st.binary(min_size=0, max_size=2 * len(raw)), label="garbage")
        assume(garbage != raw)
        target.write_bytes(garbage)


@pytest.mark.parametrize("zarr_format", FORMATS)
@pytest.mark.parametrize("key", KEYS)
@settings(max_examples=3, **SETTINGS)
@given(data=st.data())
def test_every_reader_reports_a_damaged_chunk(originals, zarr_format, key, data):
    paths, pristine = originals
    how = data.draw(st.sampled_from(["truncate", "delete", "garbage"]), label="damage")
    n_chunks = 1 if key == "meta/episode_ends" else 3
    c = data.draw(st.integers(0, n_chunks - 1), label="chunk")
    chunk = None if key == "meta/episode_ends" else c
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        path = copy_dataset(paths[zarr_format], tmp / "ds.zarr")
        clean = copy_dataset(paths[zarr_format], tmp / "clean.zarr")
        _damage(path, key, c, how, data)
        before = snapshot(path)
        episode = _episode_at(key, c)

        with pytest.raises(DatasetError) as info:
            inspect_dataset(path)
        assert_names(info, key, chunk)
        code, _, err = cli("info", path)
        assert code == 2 and err.count("\n") == 1 and err.startswith("error: ") and key in err, (code, err)

        with pytest.raises(DatasetError) as info:
            ReplayBufferReader(path).episode(episode)
        assert_names(info, key, chunk)
        with pytest.raises(DatasetError) as info:
            render_episode(path, episode, tmp / "views")
        assert_names(info, key, chunk)

        with pytest.raises(DatasetError) as info:
            ReplayBuffer.load(path, extras=True)
        assert_names(info, key, chunk)
        if key.startswith("data/") and key.split("/")[1] in EXTRAS:  # the trainer does not read extras
            buffer = ReplayBuffer.load(path)
            for name in ("point_cloud", "state", "action"):
                np.testing.assert_array_equal(getattr(buffer, name), getattr(pristine, name))
        else:
            with pytest.raises(DatasetError) as info:
                ReplayBuffer.load(path)
            assert_names(info, key, chunk)

        listing = sorted(os.listdir(tmp))
        with pytest.raises(DatasetError) as info:
            merge(tmp / "merged.zarr", [clean, path])
        assert_names(info, key, chunk)
        with pytest.raises(DatasetError) as info:
            split(path, tmp / "train.zarr", tmp / "val.zarr", val_ratio=0.3)
        assert_names(info, key, chunk)
        assert sorted(os.listdir(tmp)) == listing  # no output, no leftovers

        with pytest.raises(DatasetError) as info:
            repair(path)
        assert_names(info, key, chunk)
        with pytest.raises(DatasetError) as info:
            ReplayBufferWriter(path, extra_keys=EXTRAS)
        assert_names(info, key, chunk)
        assert snapshot(path) == before  # nothing changed on disk


@pytest.mark.parametrize("zarr_format", FORMATS)
def test_truncated_chunk_is_exit_2_not_a_crash(tmp_path, originals, zarr_format):
    """In a separate process, so that a crash of the decompressor (SIGSEGV) would show as its return code."""
    path = copy_dataset(originals[0][zarr_format], tmp_path / "ds.zarr")
    target = chunk_file(path, "data/action", 1)
    target.write_bytes(target.read_bytes()[:-7])
    result = subprocess.run(
        [sys.executable, "-m", "dssp_data.data_cli", "info", str(path)],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
    )
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2, (result.returncode, result.stderr)
    assert len(lines) == 1 and lines[0].startswith("error: "), result.stderr
    assert "data/action chunk 1 (steps 100..199, episodes 1..2) is corrupt (truncated" in lines[0]
    assert "dssp-data repair cannot restore lost data" in lines[0]


def test_missing_chunk_is_lost_data_and_can_be_left_out(tmp_path, originals):
    path = copy_dataset(originals[0][2], tmp_path / "ds.zarr")
    (path / "data" / "action" / "2.0").unlink()  # a chunk of zeros: stored, so its absence is lost data
    code, out, err = cli("info", path)
    assert code == 2 and "problems" not in out
    assert (
        "data/action chunk 2 (steps 200..219, episode 2) is missing (no data/action/2.0 in the store): "
        "re-record or re-convert episode 2, or leave it out with dssp-data split"
    ) in err
    assert "--drop-episodes 2 (dssp-data repair cannot restore lost data)" in err
    code, _, err = cli("repair", path)
    assert code == 2 and "data/action chunk 2" in err
    np.testing.assert_array_equal(ReplayBufferReader(path).episode(1).action, originals[1].episode(1).action)

    train, val = tmp_path / "train.zarr", tmp_path / "val.zarr"
    code, out, err = cli("split", path, "--train", train, "--val", val, "--val-episodes", "0", "--drop-episodes", "2")
    assert code == 0 and "left out episodes [2] (--drop-episodes)" in out, err
    assert ReplayBuffer.load(train).n_episodes == ReplayBuffer.load(val).n_episodes == 1
    np.testing.assert_array_equal(ReplayBuffer.load(train).action, originals[1].episode(1).action)
    code, _, err = cli("split", path, "--train", train, "--val", val, "--val-ratio", "0.5", "--drop-episodes", "x")
    assert code == 2 and "--drop-episodes must be comma-separated episode indices or ranges" in err


def _write_with_zarr_defaults(path, zarr_format, values):
    """Arrays as other tools write them with zarr 3's defaults: a chunk that holds only the fill value is not stored."""
    root = zarr.open_group(str(path), mode="w", zarr_format=zarr_format)
    for key, value in values.items():
        parent, name = key.split("/")
        root.require_group(parent).create_array(name, data=value, chunks=(100,) + value.shape[1:])
    return root


def _default_values():
    episodes = make_episodes()
    values = {
        f"data/{k}": np.concatenate([getattr(e, k) for e in episodes]) for k in ("point_cloud", "state", "action")
    }
    values["data/step_problems"] = np.zeros(sum(LENGTHS), np.uint8)
    values["meta/episode_ends"] = ENDS.astype(np.int64)
    return values


def test_unmarked_zarr3_chunks_may_hold_only_the_fill_value(tmp_path):
    """A zarr-3 dataset written by another tool with zarr's defaults (chunks of only zeros not stored) is valid:
    a missing chunk reads as the fill value, in every array, and info says how many; appending to it stores every
    chunk and marks the arrays that hold every chunk."""
    path = tmp_path / "other.zarr"
    values = _default_values()
    _write_with_zarr_defaults(path, 3, values)
    assert not chunk_file(path, "data/step_problems", 0).exists()
    assert not chunk_file(path, "data/action", 2).exists()  # only zeros

    buffer = ReplayBuffer.load(path, extras=True)
    assert not buffer.extras["step_problems"].any()
    np.testing.assert_array_equal(buffer.action, values["data/action"])
    assert ReplayBufferReader(path).check_chunks() == {"data/action": 1, "data/step_problems": 3}
    code, out, err = cli("info", path)
    assert code == 0 and "problems    none found" in out, (out, err)
    assert "data/action: 1 chunk(s) are not stored and read as the fill value" in out
    assert "data/step_problems: 3 chunk(s) are not stored and read as the fill value" in out

    new = make_episodes((30,), seed=1)[0]
    new = Episode(new.point_cloud, new.state, new.action, {"step_problems": new.extras["step_problems"]})
    with ReplayBufferWriter(path, extra_keys=["step_problems"]) as writer:
        writer.add_episode(new)
    root = zarr.open_group(str(path), mode="r")
    assert root["data/state"].attrs[EVERY_CHUNK_ATTR] is True  # it held every chunk
    assert EVERY_CHUNK_ATTR not in root["data/action"].attrs  # chunk 2 of its old steps was left out
    assert EVERY_CHUNK_ATTR not in root["data/step_problems"].attrs
    assert chunk_file(path, "data/step_problems", 2).is_file()  # the one the append wrote is stored


def test_a_missing_chunk_of_a_zarr2_or_marked_array_is_lost_data(tmp_path):
    """zarr format 2 (zarr-python 2 stores every chunk) and arrays this package marked: a missing chunk is lost."""
    path = tmp_path / "v2.zarr"
    _write_with_zarr_defaults(path, 2, _default_values())
    assert not chunk_file(path, "data/action", 2).exists()
    with pytest.raises(DatasetError, match=r"data/action chunk 2 \(steps 200..219, episode 2\) is missing"):
        ReplayBuffer.load(path)
    assert cli("info", path)[0] == 2

    marked = write_dataset(tmp_path / "marked.zarr", 3)
    chunk_file(marked, "data/state", 1).unlink()
    with pytest.raises(DatasetError, match=r"data/state chunk 1 \(steps 100..199, episodes 1..2\) is missing"):
        ReplayBuffer.load(marked)


@pytest.mark.parametrize("zarr_format", FORMATS)
def test_an_empty_episode_is_not_lost_data(tmp_path, zarr_format):
    """episode_ends = [0] written with zarr's defaults: its only chunk holds the fill value and is not stored."""
    path = tmp_path / "empty.zarr"
    values = {key: value[:0] if key.startswith("data/") else value for key, value in _default_values().items()}
    values["meta/episode_ends"] = np.array([0], np.int64)
    _write_with_zarr_defaults(path, zarr_format, values)
    assert not chunk_file(path, "meta/episode_ends", 0).exists()
    code, _, err = cli("info", path)
    assert code == 2 and err.count("\n") == 1
    if zarr_format == 3:  # the fill value, as zarr defines it
        assert "meta/episode_ends[0] = 0: episode 0 is empty" in err, err
    else:  # lost, or left out as the fill value: either way the episode is empty
        assert "meta/episode_ends chunk 0 (episodes 0..0) is missing" in err, err
        assert "held only the fill value 0, and then episodes 0..0 are empty" in err, err


@pytest.mark.parametrize("zarr_format", FORMATS)
def test_an_enlarged_shape_is_a_metadata_mismatch_not_an_interrupted_write(tmp_path, zarr_format):
    path = write_dataset(tmp_path / "ds.zarr", zarr_format)
    meta = path / "data" / "state" / (".zarray" if zarr_format == 2 else "zarr.json")
    doc = json.loads(meta.read_text())
    doc["shape"][0] = 400  # no chunk behind steps 300..399
    meta.write_text(json.dumps(doc))
    with pytest.raises(DatasetError) as info:
        ReplayBuffer.load(path)
    message = str(info.value)
    assert "data/state has 400 steps in its metadata" in message and "no chunk is stored for steps 300..399" in message
    assert "its shape does not match the stored data" in message and "interrupted" not in message, message
    code, out, _ = cli("info", path)
    assert code == 1 and "data/state has 400 steps in its metadata" in out and "a write was interrupted" not in out, out
    code, out, _ = cli("repair", path)
    assert code == 0 and "set data/state back to the last episode end (its metadata gave 400 steps" in out, out
    assert "cut off" not in out
    assert ReplayBuffer.load(path).n_steps == int(ENDS[-1])
    out = cli("info", path)[1]
    assert "in its metadata" not in out and "after the last episode end" not in out, out


def test_blosc_frame_check():
    rng = np.random.default_rng(0)
    for values in (
        rng.normal(size=5000).astype(np.float32),
        np.zeros(5000, np.float32),
        rng.integers(0, 256, 5000).astype(np.uint8),
    ):  # compressible, all zeros, incompressible
        for shuffle in (numcodecs.Blosc.SHUFFLE, numcodecs.Blosc.NOSHUFFLE):
            frame = np.frombuffer(numcodecs.Blosc(cname="zstd", clevel=3, shuffle=shuffle).encode(values), np.uint8)
            assert _blosc_problem(lambda a, b, f=frame: f[a:b], frame.size, values.nbytes) is None
            assert "announces" in _blosc_problem(lambda a, b, f=frame: f[a:b], frame.size, values.nbytes + 4)
            for n in range(0, frame.size, max(1, frame.size // 50)):
                assert _blosc_problem(lambda a, b, f=frame[:n]: f[a:b], n, values.nbytes) is not None


# ------------------------------------------------------------------------------------------------ CAN-log names
@pytest.mark.parametrize("name", ["/etc/passwd", "../../etc/passwd", "sub/../../x.blf", "", "link.blf", 7])
def test_merge_refuses_can_logs_outside_the_dataset(tmp_path, originals, name):
    path = copy_dataset(originals[0][2], tmp_path / "crafted.zarr")
    os.symlink("/etc/hosts", can_log_dir(path) / "link.blf")
    root = zarr.open_group(str(path), mode="r+", use_consolidated=False)
    infos = list(root.attrs["episode_info"])
    infos[1] = dict(infos[1], can_logs={"can0": name})
    root.attrs["episode_info"] = infos
    listing = sorted(os.listdir(tmp_path))

    with pytest.raises(DatasetError, match=r"episode_info\[1\]\.can_logs names") as info:
        merge(tmp_path / "out.zarr", [originals[0][2], path])
    assert "\n" not in str(info.value)
    code, _, err = cli("merge", tmp_path / "out.zarr", path, originals[0][2])
    assert code == 2 and err.count("\n") == 1 and "can_logs names" in err
    code, _, err = cli(
        "split", path, "--train", tmp_path / "t.zarr", "--val", tmp_path / "v.zarr", "--val-ratio", "0.3"
    )
    assert code == 2 and "can_logs names" in err
    assert sorted(os.listdir(tmp_path)) == listing  # nothing written

    report = inspect_dataset(path)  # info lists it as a problem and does not look at the file
    assert any("episode_info[1].can_logs names" in p for p in report["problems"])
    assert cli("info", path)[0] == 1


def test_can_logs_must_be_an_object(tmp_path, originals):
    path = copy_dataset(originals[0][3], tmp_path / "crafted.zarr")
    root = zarr.open_group(str(path), mode="r+", use_consolidated=False)
    root.attrs["episode_info"] = [{"can_logs": ["/etc/passwd"]}, None, None]
    with pytest.raises(DatasetError, match=r"episode_info\[0\]\.can_logs is list, not an object"):
        merge(tmp_path / "out.zarr", [path, originals[0][3]])
    assert not (tmp_path / "out.zarr").exists()


# ------------------------------------------------------------------------------------------------ info's exit code
def test_info_exit_code_says_whether_problems_were_found(tmp_path):
    episodes = make_episodes()
    write_replay_buffer(tmp_path / "good.zarr", episodes, attrs={"control_rate_hz": 10.0})
    assert cli("info", tmp_path / "good.zarr")[0] == 0
    shutil.copytree(tmp_path / "good.zarr", tmp_path / "nan.zarr")
    zarr.open_group(str(tmp_path / "nan.zarr"), mode="r+")["data/state"][LENGTHS[0] + 3, 2] = np.nan
    code, out, _ = cli("info", tmp_path / "nan.zarr")
    assert code == 1 and "data/state holds NaN or inf in episode(s) 1" in out
    code, out, _ = cli("info", tmp_path / "nan.zarr", "--json")
    assert code == 1 and '"problems": [' in out


# ------------------------------------------------------------------------------------------------ decompression bombs
def recode(path, key, **codecs):
    """Rewrite the array ``key`` of the dataset at ``path`` with other codecs (same values, shape and chunks)."""
    root = zarr.open_group(str(path), mode="r+", use_consolidated=False)
    old = root[key]
    values, chunks, attrs = old[...], old.chunks, old.attrs.asdict()
    parent, name = key.rsplit("/", 1)
    del root[parent][name]
    new = root[parent].create_array(
        name,
        shape=values.shape,
        dtype=values.dtype,
        chunks=chunks,
        attributes=attrs,
        config={"write_empty_chunks": True},
        **codecs,
    )
    new[...] = values


ZERO_GIB = np.zeros(1 << 30, np.uint8)  # untouched pages: no memory until read
BOMBS = {  # (zarr format, codecs of data/state, a small stored chunk that decodes to far more than 2.7 KiB)
    "zstd": (2, {"compressors": numcodecs.Zstd(level=1)}, lambda: numcodecs.Zstd(level=1).encode(ZERO_GIB)),
    "zstd, zarr 3": (
        3,
        {"compressors": zarr.codecs.ZstdCodec(level=1)},
        lambda: numcodecs.Zstd(level=1).encode(ZERO_GIB),
    ),
    "gzip, zarr 3": (
        3,
        {"compressors": zarr.codecs.GzipCodec()},
        lambda: numcodecs.GZip(9).encode(ZERO_GIB[: 32 << 20]),
    ),
    "blosc behind a filter": (
        2,
        {"compressors": numcodecs.Blosc(cname="zstd"), "filters": [numcodecs.Delta("<f4")]},
        lambda: numcodecs.Blosc(cname="zstd", clevel=9).encode(ZERO_GIB[: 32 << 20]),
    ),
}


def bombed(tmp_path, originals, name, c=0, folder="bombed.zarr"):
    """A copy of the dataset whose data/state is stored with the bomb's codecs, its time chunk ``c`` the bomb."""
    zarr_format, codecs, bomb = BOMBS[name]
    path = copy_dataset(originals[0][zarr_format], tmp_path / folder)
    recode(path, "data/state", **codecs)
    np.testing.assert_allclose(ReplayBuffer.load(path).state, originals[1].state, atol=1e-5)  # readable as recoded
    data = bomb()
    assert len(data) < 40_000
    chunk_file(path, "data/state", c).write_bytes(data)
    return path


@pytest.mark.parametrize("name", BOMBS)
def test_a_decompression_bomb_is_one_line_in_every_reader(tmp_path, originals, name):
    path = bombed(tmp_path, originals, name)
    last = bombed(tmp_path, originals, name, c=2, folder="last.zarr")  # the chunk an append reads back
    readers = (
        (lambda: ReplayBuffer.load(path), 0),
        (lambda: ReplayBufferReader(path).episode(0), 0),
        (lambda: ReplayBufferReader(path).check_chunks(decode=True), 0),
        (lambda: ReplayBufferWriter(last, extra_keys=EXTRAS), 2),
    )
    for read, c in readers:
        with pytest.raises(DatasetError) as info:
            read()
        assert_names(info, "data/state", c)
        assert "decompression bomb" in str(info.value)
    listing = sorted(os.listdir(tmp_path))
    for argv in (("info", path), ("repair", path), ("merge", tmp_path / "m.zarr", path, originals[0][2])):
        code, _, err = cli(*argv)
        assert code == 2 and err.count("\n") == 1 and "decompression bomb" in err, (argv, err)
    assert sorted(os.listdir(tmp_path)) == listing  # nothing written


PEAK = """
import resource, sys
from dssp_data.replay_buffer import ReplayBuffer
from dssp_core.errors import DatasetError
try:
    ReplayBuffer.load(sys.argv[1])
    print("read")
except DatasetError as exc:
    print(exc)
print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss // 1024)
"""


def test_a_decompression_bomb_takes_no_memory(tmp_path, originals):
    """A 32 kB chunk that decodes to 1 GiB: reading it peaks no higher than reading the intact dataset."""
    path = bombed(tmp_path, originals, "zstd")
    runs = {}
    for which in (originals[0][2], path):
        proc = subprocess.run(
            [sys.executable, "-c", PEAK, str(which)],
            capture_output=True,
            text=True,
            timeout=300,
            env={**os.environ, "OMP_NUM_THREADS": "1"},
        )
        assert proc.returncode == 0, proc.stderr
        message, peak_mib = proc.stdout.strip().rsplit("\n", 1)
        runs[str(which)] = (message, int(peak_mib))
    intact, bomb = runs[str(originals[0][2])], runs[str(path)]
    assert intact[0] == "read" and "decodes to 1.0 GiB" in bomb[0], runs
    assert bomb[1] < intact[1] + 100, runs  # MiB: the gigabyte was never allocated


def test_reads_beyond_the_read_budget_are_one_line(tmp_path, originals, monkeypatch):
    path = originals[0][2]  # 220 steps; loading point_cloud, state and action takes 33 kB
    monkeypatch.setenv("DSSP_READ_BUDGET", "16K")
    with pytest.raises(DatasetError) as info:
        ReplayBuffer.load(path)
    assert_names(info, "over the read budget of 16.0 KiB (DSSP_READ_BUDGET)")
    ep = ReplayBufferReader(path).episode(1)  # one episode at a time fits
    np.testing.assert_array_equal(ep.state, originals[1].episode(1).state)
    code, out, err = cli("info", path)  # reads one episode at a time
    assert code == 1 and err == "" and "episodes    3, 220 steps" in out  # 1: the random actions jump
    monkeypatch.setenv(
        "DSSP_READ_BUDGET", "9000"
    )  # an episode's 8640 bytes of clouds fit, their 9600-byte chunks do not
    with pytest.raises(DatasetError) as info:
        ReplayBufferReader(path).episode(1)
    assert_names(info, "one chunk of data/point_cloud")
    assert "DSSP_READ_BUDGET" in str(info.value)
    monkeypatch.setenv("DSSP_READ_BUDGET", "lots")
    code, _, err = cli("info", path)
    assert code == 2 and err.count("\n") == 1 and "DSSP_READ_BUDGET='lots' is not a size" in err


def test_a_chunk_shape_beyond_the_budget_and_an_unknown_codec_are_one_line(tmp_path, originals):
    path = copy_dataset(originals[0][2], tmp_path / "crafted.zarr")
    meta_file = path / "data" / "state" / ".zarray"
    meta = json.loads(meta_file.read_text())
    meta_file.write_text(json.dumps(dict(meta, chunks=[10**9, 7])))  # one chunk "holds" 26 GiB
    with pytest.raises(DatasetError) as info:
        ReplayBuffer.load(path)
    assert_names(info, "one chunk of data/state (chunk shape (1000000000, 7))")
    assert "over the read budget" in str(info.value)
    meta_file.write_text(json.dumps(dict(meta, filters=[{"id": "packbits"}])))
    for read in (lambda: ReplayBuffer.load(path), lambda: ReplayBufferReader(path).episode(0)):
        with pytest.raises(DatasetError) as info:
            read()
        assert_names(info, "data/state is stored with the codec packbits")

"""Tests for reading, writing and appending DP3 replay-buffer zarr datasets."""

import json
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest
import zarr
from conftest import DP3_DATASET, FIXTURES
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from dssp_core.errors import DatasetError
from dssp_data.dataset_layout import Episode
from dssp_data.replay_buffer import ReplayBuffer, ReplayBufferReader
from dssp_data.replay_buffer_writer import ReplayBufferWriter, write_replay_buffer

P, C, S, A = 8, 6, 14, 14


def make_episodes(lengths, n_points=P, point_dim=C, state_dim=S, action_dim=A, seed=0):
    rng = np.random.default_rng(seed)
    return [
        Episode(
            point_cloud=rng.normal(size=(t, n_points, point_dim)).astype(np.float32),
            state=rng.normal(size=(t, state_dim)).astype(np.float32),
            action=rng.normal(size=(t, action_dim)).astype(np.float32),
        )
        for t in lengths
    ]


def concat(episodes, key):
    return np.concatenate([getattr(ep, key) for ep in episodes])


def assert_same_episodes(buffer, episodes):
    assert buffer.n_episodes == len(episodes)
    for i, ep in enumerate(episodes):
        got = buffer.episode(i)
        for key in ("point_cloud", "state", "action"):
            value = getattr(got, key)
            assert value.dtype == np.float32
            np.testing.assert_array_equal(value.view(np.uint32), getattr(ep, key).view(np.uint32))


def raw_arrays(lengths=(3, 4)):
    """The arrays of a valid dataset, plus an ``img`` array that readers ignore."""
    t = sum(lengths)
    rng = np.random.default_rng(1)
    return {
        "data/point_cloud": rng.normal(size=(t, P, C)).astype(np.float32),
        "data/state": rng.normal(size=(t, S)).astype(np.float32),
        "data/action": rng.normal(size=(t, A)).astype(np.float32),
        "data/img": np.zeros((t, 2, 2, 3), np.uint8),
        "meta/episode_ends": np.cumsum(lengths).astype(np.int64),
    }


def write_raw(path, arrays, zarr_format=2, attrs=None):
    """Write arrays with zarr directly, without any validation."""
    root = zarr.open_group(str(path), mode="w", zarr_format=zarr_format, attributes=attrs or {})
    for key, value in arrays.items():
        parent, name = key.rsplit("/", 1)
        root.require_group(parent).create_array(name, data=value)
    return path


# --------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("zarr_format", [2, 3])
def test_round_trip(tmp_path, zarr_format):
    episodes = make_episodes([5, 1, 130])
    path = tmp_path / "ds.zarr"
    write_replay_buffer(path, episodes, attrs={"control_rate_hz": 15.0, "task": "x"}, zarr_format=zarr_format)

    buffer = ReplayBuffer.load(path)
    assert_same_episodes(buffer, episodes)
    assert buffer.episode_ends.dtype == np.int64
    np.testing.assert_array_equal(buffer.episode_ends, [5, 6, 136])
    np.testing.assert_array_equal(buffer.episode_lengths(), [5, 1, 130])
    assert buffer.episode_range(1) == (5, 6)
    assert buffer.episode_range(-1) == (6, 136)
    assert (buffer.n_steps, buffer.n_points, buffer.point_dim, buffer.state_dim, buffer.action_dim) == (136, P, C, S, A)
    assert buffer.attrs == {"control_rate_hz": 15.0, "task": "x"}
    assert buffer.control_rate_hz == 15.0
    assert buffer.dropped_tail_steps == 0
    np.testing.assert_array_equal(buffer.point_cloud, concat(episodes, "point_cloud"))
    with pytest.raises(IndexError):
        buffer.episode(3)
    # Only the dataset is left behind: no temporary directory.
    assert os.listdir(tmp_path) == ["ds.zarr"]


def test_format_2_layout_matches_zarr2(tmp_path):
    path = tmp_path / "ds.zarr"
    write_replay_buffer(path, make_episodes([3, 4]))
    assert (path / ".zgroup").is_file() and (path / "data" / ".zgroup").is_file()
    meta = json.loads((path / "data" / "point_cloud" / ".zarray").read_text())
    assert meta["zarr_format"] == 2
    assert meta["chunks"] == [100, P, C]
    assert meta["dtype"] == "<f4"
    assert meta["compressor"] == {"id": "blosc", "cname": "zstd", "clevel": 3, "shuffle": 1, "blocksize": 0}
    ends = json.loads((path / "meta" / "episode_ends" / ".zarray").read_text())
    assert ends["dtype"] == "<i8"
    assert not (path / "zarr.json").exists()


def test_format_3_layout(tmp_path):
    path = tmp_path / "ds.zarr"
    write_replay_buffer(path, make_episodes([3]), zarr_format=3)
    meta = json.loads((path / "data" / "state" / "zarr.json").read_text())
    assert meta["zarr_format"] == 3
    assert meta["chunk_grid"]["configuration"]["chunk_shape"] == [100, S]
    blosc = [c for c in meta["codecs"] if c["name"] == "blosc"][0]["configuration"]
    assert (blosc["cname"], blosc["clevel"], blosc["shuffle"]) == ("zstd", 3, "shuffle")


def test_reads_store_written_by_zarr2(tmp_path):
    """The fixture was written by zarr-python 2.x exactly as DP3 does (make_dp3_zarr2_fixture.py)."""
    expected = json.loads((FIXTURES / "dp3_zarr2_tiny.json").read_text())
    buffer = ReplayBuffer.load(DP3_DATASET)

    np.testing.assert_array_equal(buffer.episode_ends, expected["episode_ends"])
    assert list(buffer.point_cloud.shape) == expected["shapes"]["point_cloud"]
    assert list(buffer.state.shape) == expected["shapes"]["state"]
    assert list(buffer.action.shape) == expected["shapes"]["action"]
    assert buffer.control_rate_hz is None and buffer.attrs == {}

    # The values follow the formulas in make_dp3_zarr2_fixture.expected_arrays.
    t = np.arange(7, dtype=np.float32)
    point_cloud = (
        t[:, None, None]
        + 0.01 * np.arange(8, dtype=np.float32)[None, :, None]
        + 0.001 * np.arange(6, dtype=np.float32)[None, None, :]
    ).astype(np.float32)
    state = (t[:, None] * 0.5 - np.arange(14, dtype=np.float32)[None, :] * 0.25).astype(np.float32)
    np.testing.assert_array_equal(buffer.point_cloud, point_cloud)
    np.testing.assert_array_equal(buffer.state, state)
    np.testing.assert_array_equal(buffer.action, (state + 0.125).astype(np.float32))
    np.testing.assert_array_equal(buffer.point_cloud[0, 0], np.float32(expected["first_point"]))
    np.testing.assert_array_equal(buffer.state[-1], np.float32(expected["last_state"]))
    for key in ("point_cloud", "state", "action"):
        assert getattr(buffer, key).astype(np.float64).sum() == pytest.approx(expected["sums"][key], abs=1e-6)
    np.testing.assert_array_equal(buffer.episode(1).state, state[3:])


def test_in_memory_buffer_is_validated():
    arrays = raw_arrays()
    buffer = ReplayBuffer(
        arrays["data/point_cloud"],
        arrays["data/state"],
        arrays["data/action"],
        arrays["meta/episode_ends"].astype(np.int32),
        attrs={"control_rate_hz": 5},
    )
    assert buffer.episode_ends.dtype == np.int64 and buffer.control_rate_hz == 5.0
    with pytest.raises(DatasetError, match="episode 1 is empty"):
        ReplayBuffer(arrays["data/point_cloud"], arrays["data/state"], arrays["data/action"], [3, 3, 7])


# --------------------------------------------------------------------------- validation on load


def _set(key, value):
    def mutate(arrays):
        arrays[key] = value(arrays) if callable(value) else value

    return mutate


def _drop(key):
    def mutate(arrays):
        del arrays[key]

    return mutate


def _poison(key, index, value):
    def mutate(arrays):
        arrays[key][index] = value

    return mutate


BROKEN = {
    "missing point_cloud": (_drop("data/point_cloud"), ["missing key data/point_cloud"]),
    "missing state": (_drop("data/state"), ["missing key data/state"]),
    "missing action": (_drop("data/action"), ["missing key data/action"]),
    "missing episode_ends": (_drop("meta/episode_ends"), ["missing key meta/episode_ends"]),
    "length mismatch": (
        _set("data/state", lambda a: a["data/state"][:6]),
        ["differ in length", "data/state: 6", "data/point_cloud: 7"],
    ),
    "ends empty": (_set("meta/episode_ends", np.zeros(0, np.int64)), ["meta/episode_ends is empty"]),
    "ends 2-D": (_set("meta/episode_ends", np.array([[3, 7]], np.int64)), ["meta/episode_ends", "1-D"]),
    "ends float": (_set("meta/episode_ends", np.array([3.0, 7.0])), ["meta/episode_ends", "integer"]),
    "ends repeat": (
        _set("meta/episode_ends", np.array([3, 3, 7], np.int64)),
        ["not strictly increasing", "episode 1 is empty"],
    ),
    "ends decrease": (_set("meta/episode_ends", np.array([5, 3, 7], np.int64)), ["episode 1 is empty"]),
    "first end 0": (_set("meta/episode_ends", np.array([0, 3, 7], np.int64)), ["episode 0 is empty"]),
    "first end negative": (_set("meta/episode_ends", np.array([-1, 7], np.int64)), ["out of range"]),
    "data longer": (
        _set("meta/episode_ends", np.array([3, 5], np.int64)),
        ["2 steps after the last episode end", "incomplete episode", "allow_incomplete_tail"],
    ),
    "data shorter": (
        _set("meta/episode_ends", np.array([3, 9], np.int64)),
        ["meta/episode_ends[-1] = 9 is out of range", "only 7 steps"],
    ),
    "nan point": (
        _poison("data/point_cloud", (5, 2, 1), np.nan),
        ["data/point_cloud", "NaN or inf", "step 5", "episode 1"],
    ),
    "inf action": (_poison("data/action", (1, 0), np.inf), ["data/action", "step 1", "episode 0"]),
    "nan state": (_poison("data/state", (3, 13), np.nan), ["data/state", "step 3", "episode 1"]),
    "point dim 4": (
        _set("data/point_cloud", lambda a: np.zeros((7, P, 4), np.float32)),
        ["data/point_cloud", "C = 3 (xyz) or 6"],
    ),
    "point cloud 2-D": (
        _set("data/point_cloud", lambda a: np.zeros((7, P * C), np.float32)),
        ["data/point_cloud has shape (7, 48)", "(T, P, C)"],
    ),
    "state 3-D": (_set("data/state", lambda a: np.zeros((7, 2, 7), np.float32)), ["data/state", "2-D (T, S)"]),
    "action 1-D": (_set("data/action", lambda a: np.zeros(7, np.float32)), ["data/action", "2-D (T, A)"]),
    "bool state": (_set("data/state", lambda a: np.zeros((7, S), bool)), ["data/state has dtype bool", "float"]),
}


@pytest.mark.parametrize("zarr_format", [2, 3])
@pytest.mark.parametrize("case", list(BROKEN))
def test_broken_store_is_reported(tmp_path, case, zarr_format):
    mutate, expected = BROKEN[case]
    arrays = raw_arrays()
    mutate(arrays)
    path = write_raw(tmp_path / "broken.zarr", arrays, zarr_format)
    with pytest.raises(DatasetError) as info:
        ReplayBuffer.load(path)
    message = str(info.value)
    assert "\n" not in message
    assert str(path) in message
    for part in expected:
        assert part in message


def test_missing_path(tmp_path):
    with pytest.raises(DatasetError, match="does not exist"):
        ReplayBuffer.load(tmp_path / "nope.zarr")


def test_path_is_a_file(tmp_path):
    (tmp_path / "file.zarr").write_text("x")
    with pytest.raises(DatasetError, match="is a file"):
        ReplayBuffer.load(tmp_path / "file.zarr")


def test_directory_that_is_not_zarr(tmp_path):
    (tmp_path / "plain").mkdir()
    (tmp_path / "plain" / "notes.txt").write_text("x")
    with pytest.raises(DatasetError, match="is not a zarr group"):
        ReplayBuffer.load(tmp_path / "plain")


def test_pointing_at_data_group_gives_a_hint(tmp_path):
    path = write_raw(tmp_path / "ds.zarr", raw_arrays())
    with pytest.raises(DatasetError, match="point to the dataset root"):
        ReplayBuffer.load(path / "data")


def test_corrupt_chunk_is_reported(tmp_path):
    path = tmp_path / "ds.zarr"
    write_replay_buffer(path, make_episodes([3]))
    (path / "data" / "state" / "0.0").write_bytes(b"garbage")
    with pytest.raises(DatasetError, match=r"data/state chunk 0 \(steps 0..2, episode 0\) is corrupt") as info:
        ReplayBuffer.load(path)
    assert "\n" not in str(info.value) and "data/state/0.0" in str(info.value)


def test_corrupt_metadata_is_reported(tmp_path):
    path = tmp_path / "ds.zarr"
    write_replay_buffer(path, make_episodes([3]))
    (path / "data" / "action" / ".zarray").write_text("{not json")
    with pytest.raises(DatasetError, match="cannot open data/action") as info:
        ReplayBuffer.load(path)
    assert "\n" not in str(info.value)


def test_float64_data_is_read_as_float32(tmp_path):
    arrays = raw_arrays()
    arrays["data/state"] = arrays["data/state"].astype(np.float64)
    buffer = ReplayBuffer.load(write_raw(tmp_path / "ds.zarr", arrays))
    assert buffer.state.dtype == np.float32
    np.testing.assert_array_equal(buffer.state, arrays["data/state"].astype(np.float32))


# --------------------------------------------------------------------------- writing


def test_write_replaces_existing_dataset_atomically(tmp_path):
    path = tmp_path / "ds.zarr"
    write_replay_buffer(path, make_episodes([3, 4], seed=1))
    new = make_episodes([2], seed=2)
    write_replay_buffer(path, new, attrs={"control_rate_hz": 10.0})
    assert_same_episodes(ReplayBuffer.load(path), new)
    assert os.listdir(tmp_path) == ["ds.zarr"]


def test_failed_write_leaves_existing_dataset(tmp_path):
    path = tmp_path / "ds.zarr"
    old = make_episodes([3, 4])
    write_replay_buffer(path, old)
    bad = make_episodes([2, 2])
    bad[1].action[1, 0] = np.nan
    with pytest.raises(DatasetError, match="episode 1: action holds NaN or inf"):
        write_replay_buffer(path, bad)
    assert_same_episodes(ReplayBuffer.load(path), old)
    assert os.listdir(tmp_path) == ["ds.zarr"]


def test_write_refuses_to_replace_other_directories(tmp_path):
    (tmp_path / "keep").mkdir()
    (tmp_path / "keep" / "precious.txt").write_text("x")
    with pytest.raises(DatasetError, match="refusing to replace"):
        write_replay_buffer(tmp_path / "keep", make_episodes([2]))
    assert (tmp_path / "keep" / "precious.txt").read_text() == "x"


@pytest.mark.parametrize(
    "episodes, match",
    [
        ([], "no episodes"),
        (make_episodes([0]), "episode 0: the episode is empty"),
        (make_episodes([2]) + make_episodes([2], n_points=5), r"episode 1: \(P, C, S, A\) = \(5, 6, 14, 14\)"),
        (make_episodes([2], point_dim=4), "episode 0: point_cloud has shape"),
        ([Episode(np.zeros((3, 4, 3)), np.zeros((2, 1)), np.zeros((3, 1)))], "differ in length"),
    ],
)
def test_write_validates_episodes(tmp_path, episodes, match):
    with pytest.raises(DatasetError, match=match):
        write_replay_buffer(tmp_path / "ds.zarr", episodes)
    assert os.listdir(tmp_path) == []


def test_write_rejects_bad_arguments(tmp_path):
    with pytest.raises(DatasetError, match="zarr_format"):
        write_replay_buffer(tmp_path / "ds.zarr", make_episodes([2]), zarr_format=4)
    with pytest.raises(DatasetError, match="JSON"):
        write_replay_buffer(tmp_path / "ds.zarr", make_episodes([2]), attrs={"x": object()})


# --------------------------------------------------------------------------- appending


@pytest.mark.parametrize("zarr_format", [2, 3])
def test_writer_appends_across_sessions(tmp_path, zarr_format):
    path = tmp_path / "ds.zarr"
    episodes = make_episodes([3, 120, 4, 2])
    with ReplayBufferWriter(path, attrs={"control_rate_hz": 10.0}, zarr_format=zarr_format) as writer:
        assert not path.exists()  # the store appears with its first episode
        for ep in episodes[:2]:
            writer.add_episode(ep)
        assert (writer.n_episodes, writer.n_steps) == (2, 123)
    assert_same_episodes(ReplayBuffer.load(path), episodes[:2])

    with ReplayBufferWriter(path, attrs={"task": "demo"}) as writer:
        assert writer.zarr_format == zarr_format  # an existing dataset keeps its format
        assert (writer.n_episodes, writer.n_steps) == (2, 123)
        for ep in episodes[2:]:
            writer.add_episode(ep)
    buffer = ReplayBuffer.load(path)
    assert_same_episodes(buffer, episodes)
    assert buffer.attrs == {"control_rate_hz": 10.0, "task": "demo"}
    assert os.listdir(tmp_path) == ["ds.zarr"]


def test_writer_validates_episodes(tmp_path):
    path = tmp_path / "ds.zarr"
    episodes = make_episodes([3])
    with ReplayBufferWriter(path) as writer:
        writer.add_episode(episodes[0])
        with pytest.raises(DatasetError, match=r"episode 1: \(P, C, S, A\)"):
            writer.add_episode(make_episodes([2], state_dim=3)[0])
        bad = make_episodes([2])[0]
        bad.point_cloud[1, 0, 0] = np.inf
        with pytest.raises(DatasetError, match="episode 1: point_cloud holds NaN or inf"):
            writer.add_episode(bad)
        with pytest.raises(DatasetError, match="empty"):
            writer.add_episode(make_episodes([0])[0])
    assert_same_episodes(ReplayBuffer.load(path), episodes)
    with pytest.raises(ValueError, match="closed"):
        writer.add_episode(episodes[0])


def test_writer_rejects_invalid_existing_dataset(tmp_path):
    arrays = raw_arrays()
    arrays["meta/episode_ends"] = np.array([3, 3, 7], np.int64)
    path = write_raw(tmp_path / "ds.zarr", arrays)
    with pytest.raises(DatasetError, match="episode 1 is empty"):
        ReplayBufferWriter(path)


def test_writer_refuses_datasets_with_other_arrays(tmp_path):
    path = tmp_path / "dp3.zarr"
    shutil.copytree(DP3_DATASET, path)
    with pytest.raises(DatasetError, match="data/img exists"):
        ReplayBufferWriter(path)


def _simulate_crash(path, episode, keys=("point_cloud", "state", "action")):
    """What an append interrupted before its last write leaves: data appended, episode_ends not."""
    root = zarr.open_group(str(path), mode="r+")
    for key in keys:
        root[f"data/{key}"].append(getattr(episode, key))


def test_interrupted_append(tmp_path):
    """Behaviour after a crash between the data appends and the episode_ends append.

    Loading reports the trailing steps; ``allow_incomplete_tail=True`` drops
    exactly those steps; the writer refuses to append until told to repair.
    """
    path = tmp_path / "ds.zarr"
    episodes = make_episodes([3, 4, 5, 6])
    with ReplayBufferWriter(path) as writer:
        writer.add_episode(episodes[0])
        writer.add_episode(episodes[1])
    _simulate_crash(path, episodes[2])

    with pytest.raises(DatasetError, match="5 steps after the last episode end .* incomplete episode"):
        ReplayBuffer.load(path)
    buffer = ReplayBuffer.load(path, allow_incomplete_tail=True)
    assert buffer.dropped_tail_steps == 5
    assert buffer.n_steps == 7 and len(buffer.state) == 7
    assert_same_episodes(buffer, episodes[:2])

    with pytest.raises(DatasetError, match="5 steps after .* repair_incomplete_tail=True"):
        ReplayBufferWriter(path)
    with ReplayBufferWriter(path, repair_incomplete_tail=True) as writer:
        assert writer.n_steps == 7 and writer.dropped_tail_steps == 5
        writer.add_episode(episodes[3])
    buffer = ReplayBuffer.load(path)
    assert buffer.dropped_tail_steps == 0
    assert_same_episodes(buffer, [episodes[0], episodes[1], episodes[3]])


def test_interrupted_append_between_arrays(tmp_path):
    path = tmp_path / "ds.zarr"
    episodes = make_episodes([3, 4])
    write_replay_buffer(path, episodes[:1], zarr_format=3)
    _simulate_crash(path, episodes[1], keys=("point_cloud",))
    with pytest.raises(DatasetError, match="4 steps after the last episode end"):
        ReplayBuffer.load(path)
    buffer = ReplayBuffer.load(path, allow_incomplete_tail=True)
    assert buffer.dropped_tail_steps == 4
    assert_same_episodes(buffer, episodes[:1])


# --------------------------------------------------------------------------- property


@st.composite
def episode_lists(draw):
    n_points = draw(st.integers(1, 5))
    point_dim = draw(st.sampled_from([3, 6]))
    state_dim = draw(st.integers(1, 4))
    action_dim = draw(st.integers(1, 4))
    floats = st.floats(width=32, allow_nan=False, allow_infinity=False)
    episodes = []
    for _ in range(draw(st.integers(1, 4))):
        t = draw(st.integers(1, 6))
        episodes.append(
            Episode(
                point_cloud=draw(hnp.arrays(np.float32, (t, n_points, point_dim), elements=floats)),
                state=draw(hnp.arrays(np.float32, (t, state_dim), elements=floats)),
                action=draw(hnp.arrays(np.float32, (t, action_dim), elements=floats)),
            )
        )
    return episodes


@settings(max_examples=30, deadline=None)
@given(episodes=episode_lists(), zarr_format=st.sampled_from([2, 3]))
def test_any_valid_episodes_round_trip(episodes, zarr_format):
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "ds.zarr"
        write_replay_buffer(path, episodes, zarr_format=zarr_format)
        buffer = ReplayBuffer.load(path)
    assert_same_episodes(buffer, episodes)
    np.testing.assert_array_equal(buffer.episode_lengths(), [ep.n_steps for ep in episodes])


@settings(max_examples=12, deadline=None)
@given(data=st.data(), zarr_format=st.sampled_from([2, 3]))
def test_reads_any_chunk_layout_chunk_by_chunk(data, zarr_format):
    """Other tools chunk along every axis (and zarr 2 may name chunks ``3/0``): reading whole chunks and
    cutting out the steps asked for gives exactly what zarr itself reads."""
    arrays = raw_arrays((5, 9, 3))
    chunks = {
        key: tuple(
            data.draw(st.integers(1 if axis == 0 else max(1, n // 3), n), label=f"{key} chunk {axis}")
            for axis, n in enumerate(value.shape)
        )
        for key, value in arrays.items()
    }
    separator = data.draw(st.sampled_from([".", "/"])) if zarr_format == 2 else None
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "ds.zarr"
        root = zarr.open_group(str(path), mode="w", zarr_format=zarr_format)
        for key, value in arrays.items():
            parent, name = key.rsplit("/", 1)
            extra = {"chunk_key_encoding": {"name": "v2", "separator": separator}} if separator else {}
            root.require_group(parent).create_array(
                name, data=value, chunks=chunks[key], config={"write_empty_chunks": True}, **extra
            )
        buffer = ReplayBuffer.load(path, extras=True)
        for key in ("point_cloud", "state", "action"):
            np.testing.assert_array_equal(getattr(buffer, key), arrays[f"data/{key}"])
        np.testing.assert_array_equal(buffer.extras["img"], arrays["data/img"])
        reader = ReplayBufferReader(path)
        assert reader.check_chunks() == {}
        for _ in range(3):
            start = data.draw(st.integers(0, 17), label="start")
            end = data.draw(st.integers(start, 17), label="end")
            for key in ("data/point_cloud", "data/img"):
                np.testing.assert_array_equal(reader.read(key, start, end), arrays[key][start:end])


# --------------------------------------------------------------------------- extra per-step arrays


def with_extras(episodes, seed=0):
    """The episodes with a float64 timestamp (T,) and a uint16 image (T, 3, 4) per step."""
    rng = np.random.default_rng(seed)
    return [
        Episode(
            ep.point_cloud,
            ep.state,
            ep.action,
            extras={
                "timestamp": np.arange(ep.n_steps) * 0.1 + rng.normal(),
                "depth": rng.integers(0, 4000, (ep.n_steps, 3, 4)).astype(np.uint16),
            },
        )
        for ep in episodes
    ]


@pytest.mark.parametrize("zarr_format", [2, 3])
def test_extras_round_trip_and_append(tmp_path, zarr_format):
    from dssp_data.replay_buffer import ReplayBufferReader

    episodes = with_extras(make_episodes([3, 5, 2]))
    path = tmp_path / "ds.zarr"
    write_replay_buffer(path, episodes[:1], zarr_format=zarr_format)
    with ReplayBufferWriter(path, extra_keys=["timestamp", "depth"]) as writer:
        writer.add_episode(episodes[1], attrs={"episode_info": [{"i": 0}, {"i": 1}]})
        writer.add_episode(episodes[2])
    plain = ReplayBuffer.load(path)
    assert plain.extras == {} and plain.n_episodes == 3
    buffer = ReplayBuffer.load(path, extras=True)
    assert buffer.attrs["episode_info"] == [{"i": 0}, {"i": 1}]
    assert buffer.extras["timestamp"].dtype == np.float64 and buffer.extras["depth"].dtype == np.uint16
    for i, ep in enumerate(episodes):
        got = buffer.episode(i)
        for name in ("timestamp", "depth"):
            np.testing.assert_array_equal(got.extras[name], ep.extras[name])
    reader = ReplayBufferReader(path)
    assert reader.extra_keys == ("depth", "timestamp") and reader.arrays["data/depth"][0] == (10, 3, 4)
    np.testing.assert_array_equal(reader.episode(1).extras["depth"], episodes[1].extras["depth"])
    np.testing.assert_array_equal(reader.episode(2, extras=["timestamp"]).state, episodes[2].state)
    assert ReplayBuffer.load(path, extras=["timestamp"]).extras.keys() == {"timestamp"}
    with pytest.raises(DatasetError, match="missing key data/nope"):
        ReplayBuffer.load(path, extras=["nope"])


def test_extras_must_line_up(tmp_path):
    episodes = with_extras(make_episodes([3, 4]))
    path = tmp_path / "ds.zarr"
    write_replay_buffer(path, episodes[:1])
    with pytest.raises(DatasetError, match="data/depth exists: appending would leave it shorter"):
        ReplayBufferWriter(path, extra_keys=["timestamp"])
    with pytest.raises(DatasetError, match="data/frame is missing: the dataset was written without it"):
        ReplayBufferWriter(path, extra_keys=["depth", "frame", "timestamp"])
    with ReplayBufferWriter(path, extra_keys=["depth", "timestamp"]) as writer:
        bad = Episode(
            episodes[1].point_cloud,
            episodes[1].state,
            episodes[1].action,
            extras={"timestamp": episodes[1].extras["timestamp"]},
        )
        with pytest.raises(DatasetError, match="the episode brings extras \\[timestamp\\]"):
            writer.add_episode(bad)
        wrong = Episode(
            *(getattr(episodes[1], k) for k in ("point_cloud", "state", "action")),
            extras={
                "timestamp": episodes[1].extras["timestamp"],
                "depth": episodes[1].extras["depth"].astype(np.float32),
            },
        )
        with pytest.raises(
            DatasetError, match="do not match the dataset's \\(depth uint16\\[3, 4\\], timestamp float64\\)"
        ):
            writer.add_episode(wrong)
        short = Episode(
            *(getattr(episodes[1], k) for k in ("point_cloud", "state", "action")),
            extras={"timestamp": np.zeros(2), "depth": episodes[1].extras["depth"]},
        )
        with pytest.raises(DatasetError, match="extra timestamp has shape \\(2,\\); expected \\(4, ...\\)"):
            writer.add_episode(short)
        assert writer.n_episodes == 1
    clash = Episode(episodes[0].point_cloud, episodes[0].state, episodes[0].action, extras={"state": episodes[0].state})
    with pytest.raises(DatasetError, match="'state' cannot name an extra"):
        write_replay_buffer(tmp_path / "x.zarr", [clash])
    assert ReplayBuffer.load(path, extras=True).n_episodes == 1


def test_interrupted_append_with_extras(tmp_path):
    episodes = with_extras(make_episodes([3, 4, 5]))
    path = tmp_path / "ds.zarr"
    write_replay_buffer(path, episodes[:1])
    root = zarr.open_group(str(path), mode="r+")
    root["data/timestamp"].append(episodes[1].extras["timestamp"])  # the crash came after one extra array
    assert ReplayBuffer.load(path).n_episodes == 1  # the tail is only in an array this load ignores
    with pytest.raises(DatasetError, match="4 steps after the last episode end"):
        ReplayBuffer.load(path, extras=True)
    with pytest.raises(DatasetError, match="4 steps after .* repair_incomplete_tail=True"):
        ReplayBufferWriter(path, extra_keys=["depth", "timestamp"])
    with ReplayBufferWriter(path, extra_keys=["depth", "timestamp"], repair_incomplete_tail=True) as writer:
        assert writer.dropped_tail_steps == 4
        writer.add_episode(episodes[2])
    buffer = ReplayBuffer.load(path, extras=True)
    np.testing.assert_array_equal(buffer.episode(1).extras["timestamp"], episodes[2].extras["timestamp"])


def test_large_extra_rows_get_smaller_chunks(tmp_path):
    from dssp_data.replay_buffer_writer import _extra_chunk_steps

    assert _extra_chunk_steps(np.zeros((5, 480, 640), np.uint16)) == 27  # 16 MiB / 600 KiB per depth image
    assert _extra_chunk_steps(np.zeros((5,), np.float64)) == 100


# --------------------------------------------------------------------------- attributes


@pytest.mark.parametrize("value", [-10, 0, float("nan"), float("inf"), "10", "abc", True, [10], {"hz": 10}])
def test_a_control_rate_that_is_not_a_rate_is_refused_naming_the_attribute(tmp_path, value):
    path = tmp_path / "ds.zarr"
    write_replay_buffer(path, make_episodes([3, 4]), attrs={"control_rate_hz": value})
    for rate in (lambda: ReplayBuffer.load(path).control_rate_hz, lambda: ReplayBufferReader(path).control_rate_hz):
        with pytest.raises(DatasetError) as info:
            rate()
        message = str(info.value)
        assert "\n" not in message and str(path) in message and "attribute control_rate_hz is" in message, message
        assert "not a rate in Hz" in message and "fix it with" in message, message
    write_replay_buffer(path, make_episodes([3, 4]), attrs={"control_rate_hz": 15})
    assert ReplayBuffer.load(path).control_rate_hz == 15.0 and ReplayBufferReader(path).control_rate_hz == 15.0
    write_replay_buffer(path, make_episodes([3, 4]), attrs={"control_rate_hz": None})
    assert ReplayBuffer.load(path).control_rate_hz is None


@pytest.mark.parametrize(
    "name, value, fragment",
    [
        ("episode_info", "hello", "attribute episode_info is 'hello', not a list"),
        ("episode_info", [{"index": 0}, 5], "attribute episode_info[1] is 5, not an object or null"),
        ("recording_sessions", {"a": 1}, "attribute recording_sessions is"),
        ("action_convention", 7, "attribute action_convention is 7"),
        ("pointcloud", "default", "attribute pointcloud is 'default', not an object"),
        ("camera_intrinsics", [1, 2], "attribute camera_intrinsics is [1, 2]"),
        ("camera_intrinsics", {"width": True, "fx": 1.0}, "attribute camera_intrinsics.width is true"),
        ("camera_intrinsics", {"width": 4, "fx": "600"}, "attribute camera_intrinsics.fx is '600'"),
        ("camera_to_base", [[1, 0, 0, 0]] * 3, "attribute camera_to_base is"),
        ("camera_to_base", [[1, 0, 0, "x"]] * 4, "not a 4x4 matrix of finite numbers"),
        ("camera_depth_unit", -0.001, "attribute camera_depth_unit is -0.001"),
    ],
)
def test_every_attribute_reader_refuses_a_wrong_type_naming_it(name, value, fragment):
    from dssp_data import attributes
    from dssp_data.recording import episode_infos

    attrs = {name: value}
    with pytest.raises(DatasetError) as info:
        attributes.READERS[name](attrs, "d.zarr")
    message = str(info.value)
    assert "\n" not in message and message.startswith("d.zarr: ") and fragment in message, message
    assert attributes.attribute_problems(attrs, "d.zarr") == {name: message}
    if name == "episode_info":  # never read as "no metadata"
        with pytest.raises(DatasetError, match="episode_info"):
            episode_infos(attrs, 2, "d.zarr")
    valid = {
        "control_rate_hz": 10,
        "action_convention": "leader_command: x",
        "episode_info": [None, {"index": 1}],
        "recording_sessions": [{}],
        "pointcloud": {"n_points": 8},
        "camera_depth_unit": 0.00025,
        "camera_intrinsics": {"width": 4, "height": 3, "fx": 1.0, "fy": 1, "ppx": 2.0, "ppy": 1.5},
        "camera_to_base": [[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]],
    }
    assert attributes.attribute_problems(valid, "d.zarr") == {}
    assert attributes.control_rate(valid) == 10.0 and isinstance(attributes.control_rate(valid), float)

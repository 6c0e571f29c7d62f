"""Tests for the synthetic tap-count task: determinism, shapes and observation aliasing."""

import numpy as np
import pytest

from dssp_core.errors import ConfigError
from dssp_data.replay_buffer import ReplayBuffer
from dssp_train.data.synthetic import (
    CUE_CENTERS,
    CUE_STEPS,
    EPISODE_LENGTH,
    FIRST_PAUSE_STEPS,
    NOISE_STD,
    count_taps,
    make_tap_count_episodes,
    tap_count_states,
    write_tap_count_dataset,
)


def test_deterministic_by_seed():
    a = make_tap_count_episodes(4, seed=3)
    b = make_tap_count_episodes(4, seed=3)
    c = make_tap_count_episodes(4, seed=4)
    for x, y in zip(a, b):
        for key in ("point_cloud", "state", "action"):
            np.testing.assert_array_equal(getattr(x, key), getattr(y, key))
    assert not np.array_equal(a[0].point_cloud, c[0].point_cloud)
    # The first episodes do not depend on how many are generated.
    longer = make_tap_count_episodes(7, seed=3)
    np.testing.assert_array_equal(longer[3].point_cloud, a[3].point_cloud)


@pytest.mark.parametrize("n_points", [24, 64])
def test_shapes_dtypes_and_finite(n_points):
    episodes = make_tap_count_episodes(6, seed=0, n_points=n_points)
    for ep in episodes:
        assert ep.point_cloud.shape == (EPISODE_LENGTH, n_points, 3)
        assert ep.state.shape == (EPISODE_LENGTH, 2) and ep.action.shape == (EPISODE_LENGTH, 2)
        for value in (ep.point_cloud, ep.state, ep.action):
            assert value.dtype == np.float32 and np.isfinite(value).all()
        np.testing.assert_array_equal(ep.action[:-1], ep.state[1:])
        np.testing.assert_array_equal(ep.action[-1], ep.state[-1])
        np.testing.assert_array_equal(ep.state[-1], [1.0, 0.0])  # parked
    assert sorted(count_taps(ep.state) for ep in episodes) == [1, 1, 1, 2, 2, 2]
    with pytest.raises(ConfigError, match=r"n_points must be an integer in \[24, 100000\], got"):
        make_tap_count_episodes(2, n_points=10)


def test_timing():
    one, two = tap_count_states(1), tap_count_states(2)
    np.testing.assert_allclose(one[3:8, 1], [0.2, 0.4, 0.6, 0.8, 1.0], atol=1e-6)
    np.testing.assert_allclose(one[8:13, 1], [0.8, 0.6, 0.4, 0.2, 0.0], atol=1e-6)
    assert list(FIRST_PAUSE_STEPS) == [13, 14, 15, 16]
    np.testing.assert_array_equal(one[:17], two[:17])  # alike up to the end of the first pause
    np.testing.assert_allclose(one[17:22, 0], [0.2, 0.4, 0.6, 0.8, 1.0], atol=1e-6)  # park
    np.testing.assert_allclose(two[17:22, 1], [0.2, 0.4, 0.6, 0.8, 1.0], atol=1e-6)  # tap again
    np.testing.assert_allclose(two[31:36, 0], [0.2, 0.4, 0.6, 0.8, 1.0], atol=1e-6)  # park after tap 2
    assert (count_taps(one), count_taps(two)) == (1, 2)


def test_observation_aliasing():
    episodes = make_tap_count_episodes(4, seed=0)
    one = next(ep for ep in episodes if count_taps(ep.state) == 1)
    two = next(ep for ep in episodes if count_taps(ep.state) == 2)
    for t in FIRST_PAUSE_STEPS:
        np.testing.assert_array_equal(one.state[t], [0.0, 0.0])
        np.testing.assert_array_equal(one.state[t], two.state[t])
        assert np.abs(one.point_cloud[t] - two.point_cloud[t]).max() < 10 * NOISE_STD
    # The whole history after the cue looks alike, so only the cue decides ...
    np.testing.assert_array_equal(one.state[CUE_STEPS:17], two.state[CUE_STEPS:17])
    assert np.abs(one.point_cloud[CUE_STEPS:17] - two.point_cloud[CUE_STEPS:17]).max() < 10 * NOISE_STD
    # ... what the expert does next.
    last = FIRST_PAUSE_STEPS[-1]
    assert np.abs(one.action[last : last + 5] - two.action[last : last + 5]).max() > 0.1
    assert one.action[last, 0] > 0 and two.action[last, 1] > 0


def test_cue_only_in_first_steps():
    episodes = make_tap_count_episodes(4, seed=1)
    for ep in episodes:
        n_taps = count_taps(ep.state)
        for taps, center in CUE_CENTERS.items():
            near = np.linalg.norm(ep.point_cloud - np.asarray(center, np.float32), axis=-1) < 0.1
            per_step = near.sum(axis=1)
            assert (per_step[CUE_STEPS:] == 0).all()
            assert (per_step[:CUE_STEPS] > 0).all() == (taps == n_taps)
            assert (per_step[:CUE_STEPS] == 0).all() == (taps != n_taps)


def test_write_dataset(tmp_path):
    path = write_tap_count_dataset(tmp_path / "tap.zarr", n_episodes=4, seed=2, n_points=32)
    buffer = ReplayBuffer.load(path)
    assert buffer.n_episodes == 4 and buffer.n_steps == 4 * EPISODE_LENGTH
    assert (buffer.n_points, buffer.point_dim, buffer.state_dim, buffer.action_dim) == (32, 3, 2, 2)
    assert buffer.control_rate_hz == 10.0
    assert buffer.attrs["task"] == "tap_count"
    assert buffer.attrs["generator"] == "dssp_train.data.synthetic"
    expected = make_tap_count_episodes(4, seed=2, n_points=32)
    np.testing.assert_array_equal(buffer.episode(3).point_cloud, expected[3].point_cloud)


@pytest.mark.parametrize(
    "kwargs,message",
    [
        ({"seed": -1}, r"seed must be an integer in \[0, 9223372036854775807\], got -1"),
        ({"n_episodes": 0}, r"n_episodes must be an integer in \[1, 10000\], got 0"),
        ({"n_episodes": 10_001}, r"n_episodes must be an integer in \[1, 10000\], got 10001"),
        ({"n_points": 100_001}, r"n_points must be an integer in \[24, 100000\], got 100001"),
        (
            {"n_episodes": 1000, "n_points": 20_000},
            r"n_episodes 1000 x n_points 20000 make 9.6 GB of point clouds, more than "
            r"the 2 GB the generator holds in memory; lower n_episodes or n_points",
        ),
    ],
)
def test_out_of_bounds_requests_are_refused_before_any_work(kwargs, message, tmp_path):
    args = {"n_episodes": 2, "seed": 0, "n_points": 24, **kwargs}
    with pytest.raises(ConfigError, match=f"^{message}$"):
        make_tap_count_episodes(**args)
    with pytest.raises(ConfigError, match=f"^{message}$"):
        write_tap_count_dataset(tmp_path / "d.zarr", **args)
    assert not (tmp_path / "d.zarr").exists()


def test_numpy_integers_are_accepted():
    a = make_tap_count_episodes(np.int64(2), seed=np.int64(3), n_points=np.int64(24))
    b = make_tap_count_episodes(2, seed=3, n_points=24)
    np.testing.assert_array_equal(a[1].point_cloud, b[1].point_cloud)

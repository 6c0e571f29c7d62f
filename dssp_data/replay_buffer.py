"""Read DP3 "ReplayBuffer" zarr datasets (written by :mod:`dssp_data.replay_buffer_writer`).

On-disk layout (as DP3 and RoboTwin write it), with T the total number of steps
over all episodes and E the number of episodes::

    <root>/                     zarr group; its attributes are free-form JSON
        data/point_cloud        (T, P, C) float, C = 3 (xyz) or 6 (xyz + rgb)
        data/state              (T, S) float
        data/action             (T, A) float
        data/<other>            (T, ...) per-step extras, e.g. img, depth, timestamps
        meta/episode_ends       (E,) int64, cumulative exclusive end of each episode

Episode ``i`` covers steps ``episode_ends[i-1]:episode_ends[i]`` (from 0 for
``i = 0``). Both zarr format 2 (what zarr-python 2.x writes: ``.zgroup`` and
``.zarray`` files) and zarr format 3 (``zarr.json``) stores are read. Writing
uses format 2 by default, Blosc zstd level 3 with byte shuffle and chunks of 100
steps along time, like DP3.

Per-step arrays other than point_cloud, state and action ("extras": timestamps,
raw depth images, ...) keep their own dtype. Reading ignores them unless asked
(``ReplayBuffer.load(..., extras=True)``, :class:`ReplayBufferReader`); writing
and appending carry them (:attr:`~dssp_data.dataset_layout.Episode.extras`), and an append must bring
exactly the extras the dataset holds, so every array keeps one entry per step.

Crashes: a crash in the middle of an append
(:class:`~dssp_data.replay_buffer_writer.ReplayBufferWriter`) leaves every earlier episode intact, followed by steps
that belong to no episode. :meth:`ReplayBuffer.load`
reports such a tail as an error unless ``allow_incomplete_tail=True``, which drops exactly those steps and records
how many in :attr:`ReplayBuffer.dropped_tail_steps`. Attributes given with an episode are written before its data,
so after a crash they may describe one episode more than ``meta/episode_ends`` holds: readers index such
per-episode attributes by episode count.

Attributes are read through :mod:`dssp_data.attributes`: a value of the wrong type (a
``control_rate_hz`` of ``"10"``, ``true`` or ``-10``) raises DatasetError naming the attribute.

Where the rest lives: the keys, :class:`~dssp_data.dataset_layout.Episode` and the shape and value checks in
:mod:`dssp_data.dataset_layout`; chunk-level access (checked chunks, bounds, empty chunks) in
:mod:`dssp_data.zarr_chunks`; writing and appending in :mod:`dssp_data.replay_buffer_writer`.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from dssp_core.errors import DatasetError
from dssp_data import attributes
from dssp_data.bounded import check_budget, nbytes_of
from dssp_data.dataset_layout import (
    DATA_KEYS,
    ENDS_KEY,
    REQUIRED_KEYS,
    Episode,
    check_data_structure,
    check_ends_structure,
    check_episode_ends,
    check_extra_array,
    check_extra_name,
    check_finite_values,
    first_bad_steps,
    resolve_length,
)
from dssp_data.zarr_chunks import StoredArray, find_unbacked, open_extra_arrays, open_required, read_checked

__all__ = ["ReplayBuffer", "ReplayBufferReader"]


# --------------------------------------------------------------------------- reading


class ReplayBuffer:
    """A whole DP3 dataset in memory.

    Attributes:
        point_cloud: (T, P, C) float32, all episodes concatenated along time.
        state: (T, S) float32.
        action: (T, A) float32.
        episode_ends: (E,) int64, cumulative exclusive end of each episode.
        attrs: the root group's attributes (JSON).
        dropped_tail_steps: steps after the last episode end that
            ``load(..., allow_incomplete_tail=True)`` dropped (0 otherwise).
        extras: extra per-step arrays by name, (T, ...) each, in their stored
            dtype (empty unless loaded with ``extras``).
        path: where it was loaded from (None for a buffer built in memory).
    """

    def __init__(
        self,
        point_cloud: np.ndarray,
        state: np.ndarray,
        action: np.ndarray,
        episode_ends: np.ndarray,
        attrs: dict | None = None,
        extras: Mapping[str, np.ndarray] | None = None,
    ):
        """Wrap in-memory arrays (shapes as in the class docstring) after validating them.

        Data arrays are converted to float32 and episode_ends to int64;
        ``extras`` (each (T, ...)) keep their dtype.

        Raises:
            DatasetError: the arrays do not form a valid dataset.
        """
        where = "replay buffer"
        point_cloud, state, action, ends = (np.asarray(a) for a in (point_cloud, state, action, episode_ends))
        check_data_structure(point_cloud, state, action, where)
        check_ends_structure(ends, where)
        ends = ends.astype(np.int64)
        check_episode_ends(ends, where)
        lengths = {"data/point_cloud": len(point_cloud), "data/state": len(state), "data/action": len(action)}
        resolve_length(lengths, int(ends[-1]), False, where)
        values = {}
        for key, array in zip(REQUIRED_KEYS, (point_cloud, state, action)):
            with np.errstate(over="ignore"):
                values[key] = array.astype(np.float32, copy=False)
            check_finite_values(key, values[key], ends, where)
        checked_extras = {}
        for name, array in (extras or {}).items():
            check_extra_name(name, where)
            checked_extras[name] = check_extra_array(name, np.asarray(array), int(ends[-1]), where)
        self._set(values, ends, attrs, 0, checked_extras)

    def _set(
        self,
        values: Mapping[str, np.ndarray],
        ends: np.ndarray,
        attrs: dict | None,
        dropped_tail_steps: int,
        extras: Mapping[str, np.ndarray] | None = None,
    ) -> None:
        self.point_cloud = values["data/point_cloud"]
        self.state = values["data/state"]
        self.action = values["data/action"]
        self.episode_ends = ends
        self.attrs = dict(attrs or {})
        self.dropped_tail_steps = int(dropped_tail_steps)
        self.extras = dict(extras or {})
        self.path = None

    @classmethod
    def load(
        cls, path: str | os.PathLike, *, allow_incomplete_tail: bool = False, extras: bool | Sequence[str] = False
    ) -> ReplayBuffer:
        """Read a dataset (zarr format 2 or 3) into memory and validate it.

        Data arrays are converted to float32. Arrays under ``data/`` other than
        point_cloud, state and action are read only when ``extras`` asks.

        Args:
            path: the dataset's root directory.
            allow_incomplete_tail: drop the steps after the last episode end (left
                by an interrupted append) instead of raising; their number is
                stored in :attr:`dropped_tail_steps`. Nothing else is dropped.
            extras: also read these extra per-step arrays (True: all of them)
                into :attr:`extras`, each (T, ...) in its stored dtype.

        Raises:
            DatasetError: the path is not a valid dataset; the message says why.
        """
        path = Path(path)
        where = str(path)
        group, arrays, ends = open_required(path, "r")
        extra_arrays = open_extra_arrays(group, where, extras)
        lengths = {key: arrays[key].shape[0] for key in REQUIRED_KEYS[:3]}
        lengths.update({f"data/{name}": array.shape[0] for name, array in extra_arrays.items()})
        data_arrays = {**arrays, **{f"data/{name}": a for name, a in extra_arrays.items()}}
        n_steps, dropped = resolve_length(
            lengths,
            int(ends[-1]),
            allow_incomplete_tail,
            where,
            unbacked=find_unbacked(data_arrays, int(ends[-1]), where),
        )
        need = sum(
            n_steps
            * (
                nbytes_of(arrays[key].shape[1:], arrays[key].dtype)
                + (0 if arrays[key].dtype == np.float32 else nbytes_of(arrays[key].shape[1:], np.float32))
            )
            for key in REQUIRED_KEYS[:3]
        )
        need += sum(n_steps * nbytes_of(array.shape[1:], array.dtype) for array in extra_arrays.values())
        check_budget(need, f"{where}: loading {n_steps} steps", "read it one episode at a time (ReplayBufferReader)")
        values = {}
        for key in REQUIRED_KEYS[:3]:
            raw = read_checked(arrays[key], key, where, n_steps, ends)
            with np.errstate(over="ignore"):
                values[key] = raw.astype(np.float32, copy=False)
            check_finite_values(key, values[key], ends, where)
        extra_values = {
            name: read_checked(array, f"data/{name}", where, n_steps, ends) for name, array in extra_arrays.items()
        }
        buffer = cls.__new__(cls)
        buffer._set(values, ends, group.attrs.asdict(), dropped, extra_values)
        buffer.path = path
        return buffer

    @property
    def n_episodes(self) -> int:
        """E, the number of episodes."""
        return int(self.episode_ends.shape[0])

    @property
    def n_steps(self) -> int:
        """T, the number of steps over all episodes."""
        return int(self.episode_ends[-1])

    @property
    def n_points(self) -> int:
        """P, points per cloud."""
        return int(self.point_cloud.shape[1])

    @property
    def point_dim(self) -> int:
        """C, values per point: 3 (xyz) or 6 (xyz + rgb)."""
        return int(self.point_cloud.shape[2])

    @property
    def state_dim(self) -> int:
        """S."""
        return int(self.state.shape[1])

    @property
    def action_dim(self) -> int:
        """A."""
        return int(self.action.shape[1])

    @property
    def control_rate_hz(self) -> float | None:
        """``attrs["control_rate_hz"]`` in Hz, or None when absent.

        Raises DatasetError naming the attribute when it is not a number > 0 (``"10"``, ``true``, NaN, -10)."""
        return attributes.control_rate(self.attrs, self.path if self.path is not None else "replay buffer")

    def episode_lengths(self) -> np.ndarray:
        """(E,) int64, the number of steps of each episode."""
        return np.diff(self.episode_ends, prepend=0)

    def episode_range(self, i: int) -> tuple[int, int]:
        """(start, end) step indices of episode ``i`` (negative ``i`` counts from the end)."""
        if not -self.n_episodes <= i < self.n_episodes:
            raise IndexError(f"episode {i} out of range for {self.n_episodes} episodes")
        i %= self.n_episodes
        start = int(self.episode_ends[i - 1]) if i > 0 else 0
        return start, int(self.episode_ends[i])

    def episode(self, i: int) -> Episode:
        """Episode ``i`` as float32 views into this buffer: (T_i, P, C), (T_i, S), (T_i, A), and views
        (T_i, ...) of the loaded extras."""
        start, end = self.episode_range(i)
        return Episode(
            self.point_cloud[start:end],
            self.state[start:end],
            self.action[start:end],
            {name: array[start:end] for name, array in self.extras.items()},
        )

    def __repr__(self) -> str:
        return (
            f"ReplayBuffer(n_episodes={self.n_episodes}, n_steps={self.n_steps}, "
            f"point_cloud=({self.n_points}, {self.point_dim}), state_dim={self.state_dim}, "
            f"action_dim={self.action_dim})"
        )


class ReplayBufferReader:
    """A dataset on disk, read one episode (or one slice) at a time: nothing is loaded up front.

    The structure and episode ends are checked on opening, like
    :meth:`ReplayBuffer.load`; values are checked when read, each read through
    the checked path of the module docstring (the chunks it needs must be stored
    and decode). :meth:`check_chunks` checks every chunk without decoding.

    Attributes:
        path: the dataset's root directory.
        zarr_format: 2 or 3.
        attrs: the root group's attributes (JSON).
        episode_ends: (E,) int64.
        dropped_tail_steps: steps after the last episode end that are ignored
            (an interrupted append; only with ``allow_incomplete_tail=True``).
        arrays: {key: (shape, dtype)} of every array under ``data/`` and ``meta/``,
            with shapes as stored (including an ignored tail).
        extra_keys: names of the extra per-step arrays under ``data/``.
        unbacked_steps: {key: (first step, length, metadata file)} of arrays whose metadata gives steps
            after the last episode end that no stored chunk holds (a shape that does not match the data;
            only with ``allow_incomplete_tail=True``, else an error).
    """

    def __init__(self, path: str | os.PathLike, *, allow_incomplete_tail: bool = False):
        self.path = Path(path)
        where = str(self.path)
        group, arrays, ends = open_required(self.path, "r")
        extras = open_extra_arrays(group, where)
        lengths = {key: arrays[key].shape[0] for key in REQUIRED_KEYS[:3]}
        lengths.update({f"data/{name}": array.shape[0] for name, array in extras.items()})
        self._arrays = {**{k: v for k, v in arrays.items()}, **{f"data/{n}": a for n, a in extras.items()}}
        self.unbacked_steps = find_unbacked(self._arrays, int(ends[-1]), where)
        n_steps, dropped = resolve_length(
            lengths, int(ends[-1]), allow_incomplete_tail, where, unbacked=self.unbacked_steps
        )
        self._stored = {key: StoredArray(array, key, where) for key, array in self._arrays.items()}
        self.zarr_format = group.metadata.zarr_format
        self.attrs = group.attrs.asdict()
        self.episode_ends = ends
        self.dropped_tail_steps = dropped
        self.extra_keys = tuple(sorted(extras))
        self.arrays = {key: (tuple(a.shape), np.dtype(a.dtype)) for key, a in sorted(self._arrays.items())}
        self._n_steps = n_steps

    @property
    def n_episodes(self) -> int:
        """E, the number of episodes."""
        return int(self.episode_ends.shape[0])

    @property
    def n_steps(self) -> int:
        """T, the number of steps that belong to episodes."""
        return self._n_steps

    @property
    def control_rate_hz(self) -> float | None:
        """``attrs["control_rate_hz"]`` in Hz, or None when absent; DatasetError when it is not a number > 0."""
        return attributes.control_rate(self.attrs, self.path)

    def episode_lengths(self) -> np.ndarray:
        """(E,) int64, the number of steps of each episode."""
        return np.diff(self.episode_ends, prepend=0)

    def episode_range(self, i: int) -> tuple[int, int]:
        """(start, end) step indices of episode ``i`` (0 <= i < E)."""
        if not 0 <= i < self.n_episodes:
            raise DatasetError(
                f"{self.path}: episode {i} is out of range: the dataset holds episodes 0..{self.n_episodes - 1}"
            )
        return (int(self.episode_ends[i - 1]) if i > 0 else 0), int(self.episode_ends[i])

    def read(self, key: str, start: int = 0, end: int | None = None) -> np.ndarray:
        """Steps [start, end) of ``key`` (e.g. ``data/state``) in its stored dtype: (end - start, ...).

        ``end`` defaults to :attr:`n_steps`; negative indices count from the stored length.

        Raises:
            DatasetError: a chunk the steps need is missing or corrupt (the message names the key,
                the chunk, its steps and episodes), or there is no such key.
        """
        if key not in self._arrays:
            raise DatasetError(f"{self.path}: no array {key}")
        length = int(self._arrays[key].shape[0])
        start, end, _ = slice(start, self._n_steps if end is None else end).indices(length)
        return self._stored[key].read(start, max(start, end), self.episode_ends)

    def check_chunks(self, keys: Sequence[str] | None = None, decode: bool = False) -> dict[str, int]:
        """Check every chunk of ``keys`` (default: every array) over the episodes' steps.

        Each must be listed by the store and, for Blosc-compressed arrays, hold a whole Blosc frame
        (header and block offsets that fit the bytes stored; a few kilobytes read per chunk). With
        ``decode``, each chunk is also decoded (the whole dataset is read, one chunk at a time).

        Returns:
            {key: number of chunks not stored} for arrays whose chunks that hold only the fill value may
            be left out (extras without the ``every_chunk_written`` mark); they read as the fill value.

        Raises:
            DatasetError: the first missing or broken chunk (key, chunk, steps, episodes, what to do).
        """
        unstored = {}
        for key in sorted(self._arrays) if keys is None else keys:
            if key not in self._stored:
                raise DatasetError(f"{self.path}: no array {key}")
            stored = self._stored[key]
            n = stored.probe(0, self.n_episodes if key == ENDS_KEY else self._n_steps, self.episode_ends, decode)
            if n:
                unstored[key] = n
        return unstored

    def episode(self, i: int, extras: bool | Sequence[str] = True, check_finite: bool = True) -> Episode:
        """Episode ``i``: point_cloud, state, action as float32 and the extras asked for (stored dtype).

        Raises DatasetError if ``check_finite`` and the data holds NaN or inf.
        """
        start, end = self.episode_range(i)
        values = []
        for key in DATA_KEYS:
            with np.errstate(over="ignore"):
                array = self.read(f"data/{key}", start, end).astype(np.float32, copy=False)
            if check_finite:
                bad = first_bad_steps(array)
                if bad.size:
                    raise DatasetError(
                        f"{self.path}: data/{key} holds NaN or inf in episode {i} (step {start + int(bad[0])}): "
                        f"fix or remove that episode"
                    )
            values.append(array)
        names = self.extra_keys if extras is True else () if extras is False else tuple(extras)
        return Episode(*values, extras={name: self.read(f"data/{name}", start, end) for name in names})

"""Write and append DP3 "ReplayBuffer" zarr datasets (the layout: :mod:`dssp_data.replay_buffer`).

Appending (:class:`ReplayBufferWriter`) writes the data arrays first and
``meta/episode_ends`` last, and zarr's local store replaces each file
atomically, so a crash in the middle of an append leaves every earlier episode
intact, followed by steps that belong to no episode. :meth:`~dssp_data.replay_buffer.ReplayBuffer.load`
reports such a tail as an error unless ``allow_incomplete_tail=True``, which
drops exactly those steps and records how many in
:attr:`~dssp_data.replay_buffer.ReplayBuffer.dropped_tail_steps`. Attributes given with an episode
(``add_episode(episode, attrs=...)``) are written before its data, so after a
crash they may describe one episode more than ``meta/episode_ends`` holds:
readers index such per-episode attributes by episode count.
"""

from __future__ import annotations

import contextlib
import functools
import inspect
import json
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import zarr
import zarr.codecs

from dssp_core.errors import DatasetError
from dssp_core.files import make_dirs, remove_created
from dssp_core.staging import Staging, WriterLock, is_staging_name, staging_target
from dssp_data.dataset_layout import (
    CHUNK_STEPS,
    DATA_KEYS,
    ENDS_CHUNK,
    ENDS_KEY,
    EXTRA_CHUNK_BYTES,
    Episode,
    as_float32,
    check_data_structure,
    check_extra_array,
    check_extra_name,
    describe_extras_layout,
    extras_layout,
    resolve_length,
)
from dssp_data.zarr_chunks import (
    EVERY_CHUNK_ATTR,
    WRITE_CONFIG,
    StoredArray,
    check_zarr_format,
    compressor_kwargs,
    find_unbacked,
    get_array,
    is_zarr_store,
    open_extra_arrays,
    open_required,
)

__all__ = [
    "write_replay_buffer",
    "ReplayBufferWriter",
    "dataset_lock",
    "dataset_writer",
    "DATASET_WRITERS",
    "DatasetWriter",
    "require_dataset_lock",
]


# --------------------------------------------------------------------------- writing


def _validated_episode(
    episode: Episode,
    where: str,
    dims: tuple[int, int, int, int] | None = None,
    layout: Mapping[str, tuple[str, tuple[int, ...]]] | None = None,
) -> Episode:
    """Return ``episode`` as float32 arrays (extras as given) after checking shapes and values.

    ``dims`` = (P, C, S, A) and ``layout`` = the extras' {name: (dtype, trailing shape)}
    that the episode must match, if given.
    """
    pc, state, action = (np.asarray(getattr(episode, k)) for k in DATA_KEYS)
    check_data_structure(pc, state, action, where, prefix="")
    lengths = {"point_cloud": pc.shape[0], "state": state.shape[0], "action": action.shape[0]}
    if len(set(lengths.values())) != 1:
        listing = ", ".join(f"{k}: {n}" for k, n in lengths.items())
        raise DatasetError(f"{where}: arrays differ in length along time ({listing}): give one entry per step")
    if state.shape[0] == 0:
        raise DatasetError(f"{where}: the episode is empty (0 steps): leave it out")
    got = (pc.shape[1], pc.shape[2], state.shape[1], action.shape[1])
    if dims is not None and got != dims:
        raise DatasetError(
            f"{where}: (P, C, S, A) = {got} does not match the dataset's {dims}: "
            f"resample the points or write a separate dataset"
        )
    values = [as_float32(array, f"{where}: {key}") for key, array in zip(DATA_KEYS, (pc, state, action))]
    extras = {}
    for name, array in dict(getattr(episode, "extras", None) or {}).items():
        check_extra_name(name, where)
        extras[name] = check_extra_array(name, np.asarray(array), state.shape[0], where)
    if layout is not None and extras_layout(extras) != dict(layout):
        raise DatasetError(
            f"{where}: extra per-step arrays ({describe_extras_layout(extras_layout(extras))}) do not match the dataset's "
            f"({describe_extras_layout(layout)}): write a separate dataset"
        )
    return Episode(*values, extras=extras)


def _episode_dims(episode: Episode) -> tuple[int, int, int, int]:
    """(P, C, S, A) of an episode."""
    return (episode.point_cloud.shape[1], episode.point_cloud.shape[2], episode.state.shape[1], episode.action.shape[1])


def _check_attrs(attrs: dict | None) -> dict:
    attrs = dict(attrs or {})
    try:
        json.dumps(attrs)
    except (TypeError, ValueError) as exc:
        raise DatasetError(
            f"dataset attributes are not JSON-serialisable ({exc}): use plain numbers, strings, lists and dicts"
        ) from exc
    return attrs


def _write_store(path: Path, episodes: Sequence[Episode], attrs: dict, zarr_format: int) -> None:
    """Write validated float32 episodes as a new store at ``path`` (a new or empty directory; the writer lock
    of the dataset it is for held)."""
    require_dataset_lock(path)
    root = zarr.open_group(str(path), mode="w-", zarr_format=zarr_format, attributes=attrs)
    data = root.create_group("data")
    meta = root.create_group("meta")
    # every chunk is stored, also one that holds only the fill value: a missing chunk is then lost data
    codec = {**compressor_kwargs(zarr_format), "config": WRITE_CONFIG, "attributes": {EVERY_CHUNK_ATTR: True}}
    for key in DATA_KEYS:
        values = np.concatenate([getattr(ep, key) for ep in episodes], axis=0)
        array = data.create_array(
            key, shape=values.shape, dtype=np.float32, chunks=(CHUNK_STEPS,) + values.shape[1:], **codec
        )
        array[...] = values
    for name in sorted(episodes[0].extras):
        values = np.concatenate([ep.extras[name] for ep in episodes], axis=0)
        array = data.create_array(
            name,
            shape=values.shape,
            dtype=values.dtype,
            chunks=(_extra_chunk_steps(values),) + values.shape[1:],
            **codec,
        )
        array[...] = values
    ends = np.cumsum([ep.n_steps for ep in episodes], dtype=np.int64)
    array = meta.create_array("episode_ends", shape=ends.shape, dtype=np.int64, chunks=(ENDS_CHUNK,), **codec)
    array[...] = ends


def _extra_chunk_steps(values: np.ndarray) -> int:
    """Steps per chunk of an extra (T, ...) array: CHUNK_STEPS, fewer for large rows (depth images)."""
    row_bytes = max(1, int(np.prod(values.shape[1:], dtype=np.int64)) * values.dtype.itemsize)
    return int(max(1, min(CHUNK_STEPS, EXTRA_CHUNK_BYTES // row_bytes)))


def _check_replaceable(path: Path) -> None:
    if path.is_symlink() or (
        path.exists() and not (path.is_dir() and (is_zarr_store(path) or not any(path.iterdir())))
    ):
        raise DatasetError(
            f"{path} exists and is not a zarr dataset or an empty directory: refusing to replace it; "
            f"choose another path or remove it"
        )


def _lock_target(path: str | os.PathLike) -> Path:
    """The name a dataset's lock is taken for: links in the folders above resolved, so that two names for one
    dataset share one lock."""
    path = Path(path).absolute()
    return Path(os.path.realpath(path.parent)) / path.name


def dataset_lock(path: str | os.PathLike, *, flag: str = "path", doing: str = "written") -> WriterLock:
    """One writer per dataset: the :class:`~dssp_core.staging.WriterLock` of the dataset at ``path``
    (``.NAME.lock`` beside it, links in the folders above resolved, so that two names for one dataset share
    one lock). Every dataset writer holds it (:data:`DATASET_WRITERS`, ``dssp-sim collect``, a recording
    session); a second one gets one DatasetError line naming the holder (``flag``: the option that names the
    dataset; ``doing``: what this writer does, as the line a second one gets says it)."""
    return WriterLock(_lock_target(path), what="dataset", flag=flag, error=DatasetError, doing=doing)


def require_dataset_lock(path: str | os.PathLike) -> None:
    """Raise RuntimeError (a bug, not bad input) unless this process holds the writer lock of the dataset at
    ``path`` — of the output it is staged for, when ``path`` is a staging directory. Every write of a dataset
    passes here (a new store, an append), so a writer that does not take the lock cannot write."""
    target = staging_target(path) or Path(path)
    if not WriterLock.held_here(_lock_target(target)):
        raise RuntimeError(
            f"{target} is written without its writer lock: a dataset writer takes it first "
            f"(dataset_writer, dataset_lock)"
        )


@dataclass(frozen=True)
class DatasetWriter:
    """One way a dataset is written: ``function`` (or class), and its parameters that name the datasets it
    writes, each with the option that names it in messages (None: the call's own ``flag`` argument)."""

    function: Callable
    outputs: tuple[tuple[str, str | None], ...]

    @property
    def name(self) -> str:
        return f"{self.function.__module__}.{self.function.__qualname__}"


DATASET_WRITERS: list[DatasetWriter] = []
"""Every dataset writer (:func:`dataset_writer` adds each; :class:`ReplayBufferWriter` takes the lock in its
constructor): each holds the writer lock of every dataset it writes from before any work until it is done."""


def dataset_writer(*, check: Callable[[Mapping[str, Any]], object] | None = None, **outputs: str | None):
    """Mark a function that writes datasets: ``outputs`` maps each parameter naming a dataset it writes to the
    option that names it in messages (None: the call's ``flag`` argument). The function runs holding the writer
    lock (:func:`dataset_lock`) of each, taken before its body (a second writer of one of them gets one line
    naming the holder, and nothing is done); the folders the locks need are created and, if still empty, removed
    again. ``check(arguments)`` runs first, with the call's arguments by name: the rules of the output paths (an
    output inside an input, under a file, over foreign data), so that a refused path creates no folder; the body
    checks them again under the lock. The function is listed in :data:`DATASET_WRITERS`.

        @dataset_writer(out=None, check=lambda a: check_data_output(a["out"], a["inputs"], a["force"], a["flag"]))
        def merge(out, inputs, *, force=False, flag="OUT"): ...
    """

    def decorate(function: Callable) -> Callable:
        signature = inspect.signature(function)

        @functools.wraps(function)
        def locked(*args, **kwargs):
            bound = signature.bind(*args, **kwargs)
            bound.apply_defaults()
            if check is not None:
                check(bound.arguments)
            with contextlib.ExitStack() as stack:
                seen = set()
                for name, flag in outputs.items():
                    path = Path(bound.arguments[name])
                    flag = flag if flag is not None else bound.arguments.get("flag", "--out")
                    if _lock_target(path) in seen:  # the same dataset twice: the function says why not
                        continue
                    seen.add(_lock_target(path))
                    created = make_dirs(path.absolute().parent, flag=flag, error=DatasetError)
                    stack.callback(remove_created, created)
                    stack.enter_context(dataset_lock(path, flag=flag))
                return function(*args, **kwargs)

        DATASET_WRITERS.append(DatasetWriter(locked, tuple(outputs.items())))
        return locked

    return decorate


@dataset_writer(path="path", check=lambda a: _check_replaceable(Path(a["path"])))
def write_replay_buffer(
    path: str | os.PathLike, episodes: Sequence[Episode], attrs: dict | None = None, zarr_format: int = 2
) -> None:
    """Write ``episodes`` as a complete dataset at ``path``.

    Each episode holds point_cloud (T_i, P, C), state (T_i, S) and action
    (T_i, A); P, C, S and A, and the extras' names, dtypes and trailing shapes,
    must agree over all episodes. The store is written into a temporary sibling
    directory (``.NAME.tmp-XXXXXXXX``, :class:`~dssp_core.staging.Staging`)
    and then renamed onto ``path``; an existing dataset at ``path`` is moved
    aside only once the new one is complete, and deleted after the new one is
    in place. On any failure or interruption (Ctrl-C) the temporary directory
    is removed once zarr's background writes have settled; one left by a killed
    process is removed by the next write to ``path``.

    Args:
        path: directory to create (parents are created too).
        episodes: at least one non-empty episode with finite values.
        attrs: JSON attributes for the root group (e.g. ``control_rate_hz``).
        zarr_format: 2 (default, what zarr-python 2.x and DP3 use) or 3.

    It holds the dataset's writer lock while it writes (:func:`dataset_writer`).

    Raises:
        DatasetError: an episode is invalid, ``path`` holds something other
            than a zarr dataset or an empty directory, or cannot be written,
            or another writer holds the dataset.
    """
    _write_complete(path, episodes, attrs, zarr_format)


def _write_complete(path: str | os.PathLike, episodes: Sequence[Episode], attrs: dict | None, zarr_format: int) -> None:
    """:func:`write_replay_buffer` for a caller that holds the dataset's writer lock."""
    check_zarr_format(zarr_format)
    attrs = _check_attrs(attrs)
    if len(episodes) == 0:
        raise DatasetError(f"{path}: no episodes to write: give at least one")
    checked = [_validated_episode(episodes[0], "episode 0")]
    dims, layout = _episode_dims(checked[0]), extras_layout(checked[0].extras)
    checked += [_validated_episode(ep, f"episode {i}", dims, layout) for i, ep in enumerate(episodes[1:], start=1)]

    path = Path(path)
    _check_replaceable(path)
    with Staging(flag="path", error=DatasetError) as staging:
        tmp = staging.make(staging.reserve(path))
        _write_store(tmp, checked, attrs, zarr_format)
        staging.commit([(tmp, path)])


class ReplayBufferWriter:
    """Append episodes one at a time to a new or existing dataset.

    A new dataset appears on disk, written atomically, with its first episode.
    For an existing one, its structure and episode ends are checked, every chunk
    must be stored with a whole frame and the last chunk of each array (which an
    append rewrites) must decode (other values are not read); episodes are then
    appended: the data arrays (and extras) first, ``meta/episode_ends`` last, so
    an interrupted append leaves every earlier episode readable (see the module
    docstring). Every chunk is stored, also one that holds only the fill value.
    Use as a context manager::

        with ReplayBufferWriter("demo.zarr", attrs={"control_rate_hz": 10.0}) as writer:
            writer.add_episode(episode)

    Args:
        path: dataset directory.
        attrs: JSON attributes merged into the root group's attributes.
        zarr_format: format of a new dataset (2 or 3); an existing dataset
            keeps its own format.
        repair_incomplete_tail: if the existing dataset ends with steps that
            belong to no episode (an interrupted append), cut them off before
            appending instead of raising DatasetError.
        extra_keys: names of the extra per-step arrays every added episode
            brings (:attr:`Episode.extras`); an existing dataset must hold
            exactly these under ``data/`` besides point_cloud, state and action.
        staged: ``path`` is an empty staging directory of the caller's, which
            puts it in place when complete (:class:`~dssp_core.staging.Staging`):
            the first episode is written into it directly instead of beside it.
        lock: hold the dataset's writer lock (:func:`dataset_lock`) until :meth:`close`,
            so that a second writer of the same dataset is refused with one line;
            False when the caller holds it already (a staged writer: the lock of the
            output it is staged for), which is checked.

    An existing dataset is checked before anything is written: no symbolic link, FIFO
    or device anywhere in its folder (:func:`check_dataset_tree`), its structure and
    its chunks as above.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        attrs: dict | None = None,
        zarr_format: int = 2,
        *,
        repair_incomplete_tail: bool = False,
        extra_keys: Sequence[str] = (),
        staged: bool = False,
        lock: bool = True,
    ):
        check_zarr_format(zarr_format)
        self.path = Path(path)
        self.staged = staged
        self.zarr_format = zarr_format
        self._attrs = _check_attrs(attrs)
        for name in extra_keys:
            check_extra_name(name, str(self.path))
        self.extra_keys = tuple(sorted(extra_keys))
        self._closed = False
        self._unmarked: list[str] = []
        self._group: zarr.Group | None = None
        self._arrays: dict[str, zarr.Array] | None = None
        self._dims: tuple[int, int, int, int] | None = None
        self._layout: dict[str, tuple[str, tuple[int, ...]]] | None = None
        self._n_steps = 0
        self._n_episodes = 0
        self.dropped_tail_steps = 0
        """Steps after the last episode end that ``repair_incomplete_tail=True`` cut off."""
        self.unbacked_steps: dict[str, tuple[int, int, str]] = {}
        """Arrays whose metadata gave steps after the last episode end that no stored chunk held
        (``{key: (first such step, length, metadata file)}``); ``repair_incomplete_tail=True`` set them back."""
        self._shown = staging_target(self.path) or self.path
        """What messages call the dataset: the output, never a staging directory."""
        self._lock = dataset_lock(self.path) if lock and not staged else None
        if self._lock is None:
            require_dataset_lock(self.path)
        try:
            if self.path.is_symlink() or is_zarr_store(self.path) or (self.path.exists() and not self._is_empty_dir()):
                self._open_existing(repair_incomplete_tail)
        except BaseException:
            self.close()
            raise

    def _is_empty_dir(self) -> bool:
        return self.path.is_dir() and not any(self.path.iterdir())

    def _open_existing(self, repair_incomplete_tail: bool) -> None:
        where = str(self.path)
        group, arrays, ends = open_required(self.path, "r+")
        extras = open_extra_arrays(group, where)
        unexpected = sorted(set(extras) - set(self.extra_keys))
        if unexpected:
            raise DatasetError(
                f"{where}: data/{unexpected[0]} exists: appending would leave it shorter than the other arrays; "
                f"write a new dataset instead"
            )
        missing = sorted(set(self.extra_keys) - set(extras))
        if missing:
            raise DatasetError(
                f"{where}: data/{missing[0]} is missing: the dataset was written without it, so appended "
                f"episodes would not line up; write a new dataset instead"
            )
        arrays.update({f"data/{name}": extras[name] for name in self.extra_keys})
        data_keys = [key for key in arrays if key != ENDS_KEY]
        lengths = {key: arrays[key].shape[0] for key in data_keys}
        self.unbacked_steps = find_unbacked(arrays, int(ends[-1]), where)
        n_steps, dropped = resolve_length(
            lengths,
            int(ends[-1]),
            repair_incomplete_tail,
            where,
            remedy="open the writer with repair_incomplete_tail=True to cut them off",
            unbacked=self.unbacked_steps,
            shape_remedy="open the writer with repair_incomplete_tail=True to set it back (nothing stored is lost)",
        )
        # Every chunk of the episodes must be stored and hold a whole frame (lost data is not appended to),
        # and the last one, which the next append reads back and rewrites, must decode.
        arrays = {key: array.with_config(WRITE_CONFIG) for key, array in arrays.items()}
        self._unmarked = []
        for key, array in arrays.items():
            stored = StoredArray(array, key, where)
            end = int(ends.shape[0]) if key == ENDS_KEY else n_steps
            if stored.probe(0, end, ends) == 0 and not stored.marked:
                self._unmarked.append(key)
            if key != ENDS_KEY:
                stored.read(end - 1, end, ends)
        self.dropped_tail_steps = dropped
        if dropped:
            for key in data_keys:
                if arrays[key].shape[0] != n_steps:
                    arrays[key].resize((n_steps,) + tuple(arrays[key].shape[1:]))
        if self._attrs:
            group.attrs.update(self._attrs)
        self.zarr_format = group.metadata.zarr_format
        self._group = group
        self._arrays = arrays
        self._dims = (
            arrays["data/point_cloud"].shape[1],
            arrays["data/point_cloud"].shape[2],
            arrays["data/state"].shape[1],
            arrays["data/action"].shape[1],
        )
        self._layout = extras_layout({name: extras[name] for name in self.extra_keys})
        self._n_steps = n_steps
        self._n_episodes = int(ends.shape[0])

    @property
    def n_episodes(self) -> int:
        """Episodes in the dataset so far."""
        return self._n_episodes

    @property
    def n_steps(self) -> int:
        """Steps in the dataset so far."""
        return self._n_steps

    @property
    def attrs(self) -> dict:
        """The dataset's root attributes as on disk (those given to the writer until the first episode)."""
        if self._group is None:
            return dict(self._attrs)
        return self._group.attrs.asdict()

    def add_episode(self, episode: Episode, attrs: dict | None = None) -> None:
        """Append one episode: point_cloud (T, P, C), state (T, S), action (T, A), and its extras.

        ``attrs`` are merged into the root group's attributes before the
        episode's data is written (with a new dataset: written with it), so
        they may describe the episode; after a crash during the append they
        may describe an episode the dataset does not hold.

        Raises:
            DatasetError: the episode is empty, holds NaN/inf, or does not match
                the dataset's (P, C, S, A) or extras; or the dataset changed underneath.
        """
        if self._closed:
            raise ValueError("ReplayBufferWriter is closed")
        where = f"{self._shown}: episode {self._n_episodes}"
        brought = tuple(sorted(getattr(episode, "extras", None) or {}))
        if brought != self.extra_keys:
            raise DatasetError(
                f"{where}: the episode brings extras [{', '.join(brought)}] but the writer was opened for "
                f"[{', '.join(self.extra_keys)}]: pass the same extra_keys"
            )
        episode = _validated_episode(episode, where, self._dims, self._layout)
        attrs = _check_attrs(attrs)
        if self._arrays is None:
            if self.staged and self._is_empty_dir() and is_staging_name(self.path.name):
                _write_store(self.path, [episode], {**self._attrs, **attrs}, self.zarr_format)
            else:
                _write_complete(self.path, [episode], {**self._attrs, **attrs}, self.zarr_format)
            self._group, arrays, _ = open_required(self.path, "r+")
            arrays.update(
                {f"data/{name}": get_array(self._group, f"data/{name}", str(self.path)) for name in self.extra_keys}
            )
            self._arrays = {key: array.with_config(WRITE_CONFIG) for key, array in arrays.items()}
            self._dims = _episode_dims(episode)
            self._layout = extras_layout(episode.extras)
        else:
            keys = [key for key in self._arrays if key != ENDS_KEY]
            lengths = [self._arrays[key].shape[0] for key in keys] + [self._arrays[ENDS_KEY].shape[0]]
            if lengths != [self._n_steps] * len(keys) + [self._n_episodes]:
                raise DatasetError(
                    f"{where}: the dataset no longer has the expected {self._n_steps} steps and "
                    f"{self._n_episodes} episodes (an earlier append failed?): reopen the writer with "
                    f"repair_incomplete_tail=True"
                )
            if attrs:
                self._group.attrs.update(attrs)
            for key in DATA_KEYS:
                self._arrays[f"data/{key}"].append(getattr(episode, key), axis=0)
            for name in self.extra_keys:
                self._arrays[f"data/{name}"].append(episode.extras[name], axis=0)
            self._arrays[ENDS_KEY].append(np.array([self._n_steps + episode.n_steps], dtype=np.int64))
            for key in self._unmarked:  # they held every chunk, and every chunk written from now on is stored
                self._arrays[key].attrs[EVERY_CHUNK_ATTR] = True
            self._unmarked = []
        self._n_steps += episode.n_steps
        self._n_episodes += 1

    def close(self) -> None:
        """Stop writing (and let go of the dataset's writer lock); every added episode is already on disk."""
        self._closed = True
        self._arrays = None
        self._group = None
        lock, self._lock = getattr(self, "_lock", None), None
        if lock is not None:
            lock.release()

    def __enter__(self) -> ReplayBufferWriter:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()


DATASET_WRITERS.append(DatasetWriter(ReplayBufferWriter, (("path", "path"),)))

"""Datasets made from datasets: ``merge``, ``split`` (train/validation by episode) and ``repair``.

    merge("all.zarr", ["monday.zarr", "tuesday.zarr"])
    split("all.zarr", "train.zarr", "val.zarr", val_ratio=0.1, seed=0)
    split("all.zarr", "train.zarr", "val.zarr", val_ratio=0.1, drop_episodes=[7, 8])  # leave 7 and 8 out
    repair("demo.zarr")          # cut off the steps of an interrupted append

Episodes are copied one at a time (memory holds one episode), into a temporary directory beside the output
(``.OUT.tmp-XXXXXXXX``, its CAN logs in ``.OUT.tmp-XXXXXXXX.can``) that is renamed onto the output when
complete. What may be at an output (:data:`~dssp_data.edit.DATA_DATASET`): nothing, or a dataset
``dssp-data`` merge, split or convert made (its ``generator`` attribute), replaced only with ``force``,
together with its ``OUT.can`` CAN logs; anything else — a recorded, synthetic or foreign dataset, a
``OUT.can`` folder without its dataset — is refused, ``force`` or not, and nothing is deleted. An output
may not be an input, lie inside one (or its CAN-log folder) or hold one; an input may not be given twice.
On an error or Ctrl-C the temporary directories are removed (once zarr's background writes have settled).
What travels with each
episode: its arrays (point_cloud, state, action, and the extras every input holds with the same layout;
the others are dropped and named in the returned warnings), its ``episode_info`` entry (session indices
renumbered), and its CAN logs (``<dataset>.can/``, renamed to the new episode index). The root attributes
are the first input's, plus ``merged_from`` / ``split_from`` saying where each episode came from (with the
input's own ``generator``), and ``generator`` = ``dssp-data merge`` / ``dssp-data split``.

Everything is read through the dataset reader's checked path, so a missing or corrupt chunk stops the
command with one line naming the key and the chunk, before the output replaces anything. The CAN-log
names come from the inputs' ``episode_info``; each must stay inside that input's CAN-log folder
(:func:`~dssp_data.recording.can_log_path`), checked for every episode before anything is written, and
each log is copied only as a regular file of that folder (:func:`~dssp_core.files.copy_regular_file`: a
linked folder or file, a FIFO or a device is refused with one line, never followed). ``merge``, ``split``,
``repair`` and every ``convert`` (through :func:`write_converted`) are dataset writers
(:func:`~dssp_data.replay_buffer_writer.dataset_writer`): each holds the writer lock of every dataset it writes
from before its first look at its inputs (no recording session, collect or second command meanwhile; a second
one gets one line naming the holder). ``repair`` refuses a dataset folder holding a symbolic link, and first
checks every chunk of the complete episodes (decoding them): it cannot restore lost data, so a missing or
corrupt chunk is an error and nothing on disk changes.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import zarr

from dssp_core.errors import ConfigError, DatasetError
from dssp_core.files import copy_regular_file
from dssp_core.output_guard import OutputKind, check_not_inside, check_output
from dssp_core.staging import Staging, interrupts_deferred, settle_background_writes
from dssp_data import attributes
from dssp_data.attributes import ZARR_ENTRIES, zarr_generator
from dssp_data.dataset_layout import Episode
from dssp_data.recording import (
    can_log_dir,
    can_log_name,
    convention_name,
    episode_can_logs,
    episode_infos,
)
from dssp_data.replay_buffer import ReplayBufferReader
from dssp_data.replay_buffer_writer import ReplayBufferWriter, dataset_writer
from dssp_data.zarr_chunks import check_dataset_tree

DATA_GENERATORS = {"merge": "dssp-data merge", "split": "dssp-data split", "convert": "dssp-data convert"}
"""The ``generator`` attribute each ``dssp-data`` command writes into the datasets it makes."""
_LEGACY_DATA_GENERATORS = ("dssp-data convert (RoboTwin raw HDF5)",)
"""What older versions of ``dssp-data convert`` wrote (merge and split copied their input's generator:
their older outputs are not recognised, so they are never replaced)."""

DATA_DATASET = OutputKind(
    "a dataset",
    "dssp-data merge, split or convert",
    entries=ZARR_ENTRIES,
    marker=False,
    signature=lambda p: zarr_generator(p) in (*DATA_GENERATORS.values(), *_LEGACY_DATA_GENERATORS),
    companion=".can",
    companion_entries=("episode_*.blf",),
)
"""``dssp-data merge OUT``, ``split --train/--val``, ``convert --out``: a zarr dataset whose ``generator``
attribute is one of :data:`DATA_GENERATORS`, with its CAN logs at ``OUT.can`` (only ``episode_*.blf``)."""

PER_EPISODE_ATTRS = ("episode_info", "recording_sessions")


@dataclass(frozen=True)
class ConvertedEpisode:
    """One episode of a conversion: ``episode``, what it came from (``source``: a file, a bag, an episode of the
    input; None when the episode's own messages say it), and root ``attrs`` it brings (the first episode's go
    into the new dataset with it: what only the input's first episode tells, e.g. its camera)."""

    source: str | None
    episode: Episode
    attrs: dict = field(default_factory=dict)


def write_converted(
    out: Path,
    attrs: dict,
    episodes: Iterable[ConvertedEpisode],
    *,
    extra_keys: Sequence[str] = (),
    force: bool = False,
    flag: str = "--out",
) -> int:
    """``dssp-data convert``'s output: the episodes, in order, as a new dataset at ``out`` with ``attrs``, written into a
    staging folder beside it (removed on an error or Ctrl-C) and moved into place when complete, ``out`` checked
    again first (:data:`DATA_DATASET`). The caller is a :func:`~dssp_data.replay_buffer_writer.dataset_writer` of
    ``out`` (it holds the dataset's writer lock from before its first look at the input). ``episodes`` may read
    its source lazily, one episode at a time; a refused episode's line names its source. Returns the steps."""
    steps = 0
    try:
        with Staging(flag=flag, error=DatasetError) as staging:
            tmp = staging.make(staging.reserve(out))
            with ReplayBufferWriter(tmp, attrs=attrs, staged=True, extra_keys=extra_keys) as writer:
                for item in episodes:
                    try:
                        writer.add_episode(item.episode, attrs=item.attrs if writer.n_episodes == 0 else None)
                    except DatasetError as exc:
                        raise (DatasetError(f"{item.source}: {exc}") if item.source else exc) from None
                    steps += item.episode.n_steps
            staging.commit(
                [(tmp, out), (None, can_log_dir(out))],  # the output checked again first
                check=lambda: check_output(out, force=force, kind=DATA_DATASET, flag=flag, error=DatasetError),
            )
    finally:
        settle_background_writes()
    return steps


def check_inputs(inputs: Sequence[str | os.PathLike]) -> None:
    """Each input dataset once (symbolic links resolved): the same one twice would duplicate its episodes."""
    seen = {}
    for item in inputs:
        real = os.path.realpath(Path(item).absolute())
        if real in seen:
            also = "" if str(seen[real]) == str(item) else f" (as {seen[real]} and {item})"
            raise DatasetError(
                f"{item} is given twice{also}: every episode of it would be in the output twice; give each input once"
            )
        seen[real] = item


def check_data_output(
    out: str | os.PathLike, inputs: Sequence[str | os.PathLike], force: bool, flag: str = "OUT"
) -> str:
    """Where ``dssp-data`` merge, split or convert may write a dataset (see the module docstring): NEW or OWN."""
    sources = [p for item in inputs for p in (Path(item), can_log_dir(item))]
    check_not_inside(out, sources, flag=flag, error=DatasetError)
    check_not_inside(can_log_dir(out), sources, flag=flag, error=DatasetError)
    return check_output(out, force=force, kind=DATA_DATASET, flag=flag, error=DatasetError)


def check_converted_output(arguments: dict) -> None:
    """``dssp-data convert``'s output rule, from a converter's arguments (``out``, ``source``, ``force``, ``flag``):
    :func:`check_data_output` with the source as the input (the output may not be it, lie inside it or hold it)."""
    check_data_output(arguments["out"], [arguments["source"]], arguments["force"], arguments["flag"])


def _common_extras(readers: Sequence[ReplayBufferReader]) -> tuple[list[str], list[str]]:
    """(extras every input holds with the same dtype and trailing shape, the others)."""

    def layout(reader, name):
        shape, dtype = reader.arrays[f"data/{name}"]
        return str(dtype), tuple(shape[1:])

    names = set(readers[0].extra_keys)
    for reader in readers[1:]:
        names &= set(reader.extra_keys)
    common = sorted(n for n in names if len({layout(r, n) for r in readers}) == 1)
    every = sorted(set().union(*(r.extra_keys for r in readers)))
    return common, [n for n in every if n not in common]


def _dims(reader: ReplayBufferReader) -> tuple[int, int, int, int]:
    pc, state, action = (reader.arrays[f"data/{k}"][0] for k in ("point_cloud", "state", "action"))
    return pc[1], pc[2], state[1], action[1]


def _check_parts(parts: Sequence[tuple[ReplayBufferReader, Sequence[int]]], out: Path, force: bool, flag: str) -> dict:
    """Check one output before anything is written; return {(id(reader), episode): {bus: CAN log path}}."""
    readers = [reader for reader, _ in parts]
    check_data_output(out, [r.path for r in readers], force, flag)
    dims = {_dims(r) for r in readers}
    if len(dims) > 1:
        listing = ", ".join(f"{r.path}: {_dims(r)}" for r in readers)
        raise DatasetError(
            f"the inputs differ in (points, point dims, state dims, action dims) ({listing}): "
            f"they cannot form one dataset"
        )
    if sum(len(indices) for _, indices in parts) == 0:
        raise DatasetError("no episodes to write")
    for reader in readers:  # their attributes travel into the output: one of the wrong type is refused here
        for message in attributes.attribute_problems(reader.attrs, reader.path).values():
            raise DatasetError(message)
    logs_of = {}
    for reader, indices in parts:
        reader_infos = episode_infos(reader.attrs, reader.n_episodes, reader.path)
        for i in indices:
            logs_of[id(reader), i] = episode_can_logs(reader.path, reader_infos[i], i)
    return logs_of


def _stage(
    parts: Sequence[tuple[ReplayBufferReader, Sequence[int]]], tmp: Path, attrs: dict, logs_of: dict, staging: Staging
) -> dict:
    """Write the chosen episodes of each reader, in order, as a new dataset in the staging directory ``tmp``
    (CAN logs in its ``.can`` companion)."""
    readers = [reader for reader, _ in parts]
    common, dropped = _common_extras(readers)
    tmp_logs = can_log_dir(tmp)
    infos, sessions, n_logs, steps = [], [], 0, 0
    with ReplayBufferWriter(tmp, attrs=attrs, extra_keys=common, staged=True) as writer:
        for reader, indices in parts:
            reader_infos = episode_infos(reader.attrs, reader.n_episodes, reader.path)
            reader_sessions = list(attributes.recording_sessions(reader.attrs, reader.path) or [])
            session_offset = len(sessions)
            sessions += reader_sessions
            for i in indices:
                episode = reader.episode(i, extras=common)
                index = writer.n_episodes
                info = reader_infos[i]
                if info is not None:
                    info = dict(info, index=index)
                    if isinstance(info.get("session"), int):
                        info["session"] = info["session"] + session_offset
                    logs = {}
                    for bus, src in logs_of[id(reader), i].items():
                        if os.path.lexists(src):  # a log never written is not there; anything else is copied or refused
                            if not tmp_logs.is_dir():
                                staging.make(tmp_logs)
                            new_name = can_log_name(index, bus)
                            copy_regular_file(
                                src, tmp_logs / new_name, inside=can_log_dir(reader.path), error=DatasetError
                            )
                            logs[bus] = new_name
                            n_logs += 1
                    info["can_logs"] = logs
                infos.append(info)
                writer.add_episode(episode)
                steps += episode.n_steps
    final = {}
    if any(info is not None for info in infos):
        final["episode_info"] = infos
    if sessions:
        final["recording_sessions"] = sessions
    if final:
        zarr.open_group(str(tmp), mode="r+", use_consolidated=False).attrs.update(final)
    return {"episodes": len(infos), "steps": steps, "dropped_extras": dropped, "can_logs": n_logs}


def _copy(
    jobs: Sequence[tuple[Sequence[tuple[ReplayBufferReader, Sequence[int]]], Path, dict, str]], force: bool
) -> list[dict]:
    """Write each job (parts = [(reader, episode indices)], output, root attributes, its flag) as a new dataset.

    Every output is checked first (output path, dimensions, the CAN-log names of every episode), then
    written into a staging directory beside it; only when all are complete are they moved onto their
    outputs (with their CAN logs), so an error (a corrupt chunk, a bad CAN-log name) or Ctrl-C leaves no
    output and no temporary behind. Returns one {"episodes": n, "steps": n, "dropped_extras": [...],
    "can_logs": n} per job.
    """
    logs_of = {}
    outputs = [Path(out) for _, out, _, _ in jobs]
    for k, (parts, out, _, flag) in enumerate(jobs):
        logs_of.update(_check_parts(parts, out, force, flag))
        others = [p for j, other in enumerate(outputs) if j != k for p in (other, can_log_dir(other))]
        check_not_inside(out, others, flag=flag, error=DatasetError)
    summaries = []
    try:
        with Staging(flag=jobs[0][3], error=DatasetError) as staging:
            staged = []
            for parts, out, attrs, flag in jobs:
                staging.flag = flag
                tmp = staging.make(staging.reserve(out))
                staged.append((tmp, Path(out), flag))
                summaries.append(_stage(parts, tmp, attrs, logs_of, staging))
            moves = []
            for tmp, out, _ in staged:
                tmp_logs = can_log_dir(tmp)
                moves += [(tmp, out), (tmp_logs if tmp_logs.is_dir() else None, can_log_dir(out))]

            def nothing_appeared() -> None:  # again: something may have appeared meanwhile
                for _, out, flag in staged:
                    check_data_output(out, [], force, flag)

            staging.commit(moves, check=nothing_appeared)
    finally:
        settle_background_writes()  # a read interrupted by Ctrl-C finishes before the process exits
    return summaries


def _json_key(value) -> str:
    return json.dumps(value, sort_keys=True)


def marked_episodes(reader: ReplayBufferReader) -> list[int]:
    """Episodes whose recording metadata lists problems (stale streams, dropped frames, ...)."""
    return [
        i
        for i, info in enumerate(episode_infos(reader.attrs, reader.n_episodes, reader.path))
        if info and info.get("problems")
    ]


def _base_attrs(attrs: dict) -> dict:
    return {k: v for k, v in attrs.items() if k not in PER_EPISODE_ATTRS}


def _source(reader: ReplayBufferReader, **fields) -> dict:
    """Where episodes came from: the input's path, its own ``generator`` (if it records one), and ``fields``."""
    source = {"path": str(reader.path), **fields}
    if isinstance(reader.attrs.get("generator"), str):
        source["generator"] = reader.attrs["generator"]
    return source


def _check_merge(arguments: dict) -> None:
    if len(arguments["inputs"]) < 2:
        raise DatasetError("merge needs at least two input datasets")
    check_inputs(arguments["inputs"])
    check_data_output(arguments["out"], arguments["inputs"], arguments["force"], arguments["flag"])


@dataset_writer(out=None, check=_check_merge)
def merge(
    out: str | os.PathLike,
    inputs: Sequence[str | os.PathLike],
    force: bool = False,
    drop_marked: bool = False,
    flag: str = "OUT",
) -> dict:
    """Concatenate the episodes of ``inputs`` (in order) into a new dataset ``out``.

    The inputs must agree on (P, C, S, A), and on ``control_rate_hz`` and the action convention where
    they record them; each is given once. ``drop_marked`` leaves out episodes recorded with problems.
    ``flag`` names ``out`` in messages. Returns the summary of :func:`_copy` plus ``warnings`` (lines to
    show the user) and ``dropped`` ({input: [episodes]}).
    """
    _check_merge({"inputs": inputs, "out": out, "force": force, "flag": flag})
    readers = [ReplayBufferReader(p) for p in inputs]
    warnings = []
    for key, describe in (("control_rate_hz", attributes.control_rate), ("action convention", convention_name)):
        values = {str(r.path): describe(r.attrs, r.path) for r in readers}
        known = {v for v in values.values() if v is not None}
        if len(known) > 1:
            raise DatasetError(
                f"the inputs differ in {key} ({values}): episodes with different meanings cannot be merged"
            )
        if known and None in values.values():
            missing = [p for p, v in values.items() if v is None]
            warnings.append(
                f"{key} is not recorded in {', '.join(missing)}: the merged dataset says "
                f"{next(iter(known))} for all episodes"
            )
    clouds = {
        _json_key(attributes.pointcloud(r.attrs, r.path)) for r in readers if r.attrs.get("pointcloud") is not None
    }
    if len(clouds) > 1:
        warnings.append(
            "the inputs were made with different point-cloud settings (attribute pointcloud); "
            "the first input's are kept"
        )
    attrs = _base_attrs(readers[0].attrs)
    for r in readers[1:]:
        for key, value in _base_attrs(r.attrs).items():
            attrs.setdefault(key, value)
    attrs["merged_from"] = [_source(r, episodes=r.n_episodes) for r in readers]
    attrs["generator"] = DATA_GENERATORS["merge"]
    dropped = {str(r.path): marked_episodes(r) for r in readers} if drop_marked else {}
    parts = [(r, [i for i in range(r.n_episodes) if i not in set(dropped.get(str(r.path), ()))]) for r in readers]
    (summary,) = _copy([(parts, Path(out), attrs, flag)], force)
    summary["dropped"] = {k: v for k, v in dropped.items() if v}
    if summary["dropped_extras"]:
        warnings.append(
            f"per-step arrays not held by every input (or stored differently) were left out: "
            f"{', '.join('data/' + n for n in summary['dropped_extras'])}"
        )
    summary["warnings"] = warnings
    return summary


def choose_validation(
    n_episodes: int, val_ratio: float | None = None, val_episodes: Sequence[int] | None = None, seed: int = 0
) -> list[int]:
    """Sorted validation episode indices: the given ones, or round(val_ratio * E) drawn with ``seed``
    (at least 1, at most E - 1)."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ConfigError(f"--seed must be a non-negative integer, got {seed!r}")
    if val_episodes is not None:
        chosen = sorted(set(int(i) for i in val_episodes))
        bad = [i for i in chosen if not 0 <= i < n_episodes]
        if bad:
            raise DatasetError(
                f"validation episode(s) {bad} out of range: the dataset holds episodes 0..{n_episodes - 1}"
            )
    else:
        if val_ratio is None or not 0 < val_ratio < 1:
            raise DatasetError(f"the validation ratio must be in (0, 1), got {val_ratio}")
        n_val = min(n_episodes - 1, max(1, round(val_ratio * n_episodes)))
        chosen = sorted(np.random.default_rng(seed).permutation(n_episodes)[:n_val].tolist())
    if not chosen or len(chosen) >= n_episodes:
        raise DatasetError(f"a split needs at least one episode on each side; the dataset holds {n_episodes}")
    return chosen


def _check_split(arguments: dict) -> None:
    train, val, path, force = arguments["train_out"], arguments["val_out"], arguments["path"], arguments["force"]
    if os.path.realpath(Path(train).absolute()) == os.path.realpath(Path(val).absolute()):
        raise DatasetError("--train and --val must be different paths")
    check_data_output(train, [path], force, "--train")
    check_data_output(val, [path], force, "--val")
    for out, other, flag in ((train, val, "--train"), (val, train, "--val")):
        check_not_inside(out, [other, can_log_dir(other)], flag=flag, error=DatasetError)


@dataset_writer(train_out="--train", val_out="--val", check=_check_split)
def split(
    path: str | os.PathLike,
    train_out: str | os.PathLike,
    val_out: str | os.PathLike,
    *,
    val_ratio: float | None = None,
    val_episodes: Sequence[int] | None = None,
    seed: int = 0,
    force: bool = False,
    drop_marked: bool = False,
    drop_episodes: Sequence[int] = (),
) -> dict:
    """Write the episodes of ``path`` into a training and a validation dataset (whole episodes each).

    ``drop_marked`` first leaves out the episodes recorded with problems, and ``drop_episodes`` the
    episodes named (e.g. those whose data is lost: they are not read); ``val_ratio`` then applies to the
    rest, and ``val_episodes`` may not name them. Returns {"train": [source indices], "val": [...],
    "dropped": [marked episodes left out], "left_out": [drop_episodes], "train_summary": ..., "val_summary": ...}.
    """
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ConfigError(f"--seed must be a non-negative integer, got {seed!r}")
    _check_split({"train_out": train_out, "val_out": val_out, "path": path, "force": force})
    reader = ReplayBufferReader(path)
    named = sorted({int(i) for i in drop_episodes})
    bad = [i for i in named if not 0 <= i < reader.n_episodes]
    if bad:
        raise DatasetError(
            f"episode(s) {bad} to drop are out of range: the dataset holds episodes 0..{reader.n_episodes - 1}"
        )
    marked = marked_episodes(reader) if drop_marked else []
    keep = [i for i in range(reader.n_episodes) if i not in set(marked) | set(named)]
    if val_episodes is not None:
        clash = sorted(set(val_episodes) & set(named))
        if clash:
            raise DatasetError(f"validation episode(s) {clash} are also named by --drop-episodes: name each once")
        clash = sorted(set(val_episodes) & set(marked))
        if clash:
            raise DatasetError(f"validation episode(s) {clash} were recorded with problems and are dropped")
        val = choose_validation(reader.n_episodes, None, val_episodes, seed)
        if len(val) >= len(keep):
            raise DatasetError(f"a split needs at least one episode on each side; {len(keep)} episodes are kept")
    else:
        val = [keep[i] for i in choose_validation(len(keep), val_ratio, None, seed)]
    train = [i for i in keep if i not in set(val)]
    base = _base_attrs(reader.attrs)
    jobs = [
        (
            [(reader, indices)],
            Path(target),
            dict(
                base,
                split_from=_source(reader, part=part, episodes=indices, seed=seed),
                generator=DATA_GENERATORS["split"],
            ),
            f"--{part}",
        )
        for part, indices, target in (("train", train, train_out), ("val", val, val_out))
    ]
    train_summary, val_summary = _copy(jobs, force)
    return {
        "train": train,
        "val": val,
        "dropped": marked,
        "left_out": named,
        "train_summary": train_summary,
        "val_summary": val_summary,
    }


@dataset_writer(path="PATH", check=lambda a: ReplayBufferReader(a["path"], allow_incomplete_tail=True))
def repair(path: str | os.PathLike) -> dict:
    """Cut off the steps an interrupted append left after the last episode end, and per-episode metadata
    beyond the last episode; set back to the last episode end an array whose metadata gives steps that no
    stored chunk holds. Returns {"dropped_steps": n, "dropped_infos": n, "reset_shapes": {key: [first step
    without a chunk, length it had]}}.

    Lost data cannot be repaired: a missing or corrupt chunk of a complete episode raises DatasetError
    (the key, the chunk, its steps and episodes) before anything on disk changes. The changes themselves
    are made with Ctrl-C held back until they are done. It holds the dataset's writer lock throughout (no
    recording session, collect or other writer meanwhile).
    """
    ReplayBufferReader(path, allow_incomplete_tail=True)  # a missing or broken dataset
    check_dataset_tree(path, appending=True)  # changed in place: no link to write through
    # every chunk of the complete episodes is decoded
    ReplayBufferReader(path, allow_incomplete_tail=True).check_chunks(decode=True)
    return _repair(path)


def _repair(path) -> dict:
    reader = ReplayBufferReader(path, allow_incomplete_tail=True)
    unbacked = reader.unbacked_steps
    cut = max(
        [
            shape[0] - reader.n_steps
            for key, (shape, _) in reader.arrays.items()
            if key.startswith("data/") and key not in unbacked
        ]
        + [0]
    )
    raw = attributes.episode_info(reader.attrs, reader.path)
    extra_infos = max(0, len(raw) - reader.n_episodes) if raw is not None else 0
    try:
        with interrupts_deferred():
            if reader.dropped_tail_steps:
                with ReplayBufferWriter(path, repair_incomplete_tail=True, extra_keys=reader.extra_keys, lock=False):
                    pass
            if extra_infos:
                zarr.open_group(str(path), mode="r+", use_consolidated=False).attrs.update(
                    {"episode_info": raw[: reader.n_episodes]}
                )
    finally:
        settle_background_writes()
    return {
        "dropped_steps": cut,
        "dropped_infos": extra_infos,
        "reset_shapes": {key: [start, length] for key, (start, length, _) in unbacked.items()},
    }

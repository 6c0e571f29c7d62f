"""Datasets made from datasets: ``merge``, ``split`` (train/validation by episode) and ``repair``.

    merge("all.zarr", ["monday.zarr", "tuesday.zarr"])
    split("all.zarr", "train.zarr", "val.zarr", val_ratio=0.1, seed=0)
    split("all.zarr", "train.zarr", "val.zarr", val_ratio=0.1, drop_episodes=[7, 8])  # leave 7 and 8 out
    repair("demo.zarr")          # cut off the steps of an interrupted append

Episodes are copied one at a time (memory holds one episode), into a temporary directory that is renamed
onto the output when complete; an existing output is replaced only with ``force``. What travels with each
episode: its arrays (point_cloud, state, action, and the extras every input holds with the same layout;
the others are dropped and named in the returned warnings), its ``episode_info`` entry (session indices
renumbered), and its CAN logs (``<dataset>.can/``, renamed to the new episode index). The root attributes
are the first input's, plus ``merged_from`` / ``split_from`` saying where each episode came from.

Everything is read through the dataset reader's checked path, so a missing or corrupt chunk stops the
command with one line naming the key and the chunk, before the output replaces anything. The CAN-log
names come from the inputs' ``episode_info``; each must stay inside that input's CAN-log folder
(:func:`~dssp_train.data.recording.can_log_path`), checked for every episode before anything is written.
``repair`` first checks every chunk of the complete episodes (decoding them): it cannot restore lost
data, so a missing or corrupt chunk is an error and nothing on disk changes.
"""

from __future__ import annotations

import json
import os
import shutil
import uuid
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import zarr

from dssp_train.atomic import replace_dir
from dssp_train.data.recording import (
    LOCK_NAME,
    DatasetLock,
    can_log_dir,
    can_log_name,
    convention_name,
    episode_can_logs,
    episode_infos,
)
from dssp_train.data.replay_buffer import ReplayBufferReader, ReplayBufferWriter
from dssp_train.errors import DatasetError

PER_EPISODE_ATTRS = ("episode_info", "recording_sessions")


def _check_output(out: Path, inputs: Sequence[Path], force: bool) -> None:
    for src in inputs:
        if out.resolve() == src.resolve():
            raise DatasetError(f"the output {out} is also an input: write to a new path")
    if out.exists() and not force:
        raise DatasetError(f"{out} exists: choose another output or pass --force to replace it")
    if out.exists() and not (out / ".zgroup").is_file() and not (out / "zarr.json").is_file():
        raise DatasetError(f"{out} exists and is not a zarr dataset: refusing to replace it")


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


def _check_parts(parts: Sequence[tuple[ReplayBufferReader, Sequence[int]]], out: Path, force: bool) -> dict:
    """Check one output before anything is written; return {(id(reader), episode): {bus: CAN log path}}."""
    readers = [reader for reader, _ in parts]
    _check_output(out, [r.path for r in readers], force)
    dims = {_dims(r) for r in readers}
    if len(dims) > 1:
        listing = ", ".join(f"{r.path}: {_dims(r)}" for r in readers)
        raise DatasetError(f"the inputs differ in (points, point dims, state dims, action dims) ({listing}): "
                           f"they cannot form one dataset")
    if sum(len(indices) for _, indices in parts) == 0:
        raise DatasetError("no episodes to write")
    logs_of = {}
    for reader, indices in parts:
        reader_infos = episode_infos(reader.attrs, reader.n_episodes)
        for i in indices:
            logs_of[id(reader), i] = episode_can_logs(reader.path, reader_infos[i], i)
    return logs_of


def _stage(parts: Sequence[tuple[ReplayBufferReader, Sequence[int]]], tmp: Path, attrs: dict, logs_of: dict) -> dict:
    """Write the chosen episodes of each reader, in order, as a new dataset at ``tmp`` (CAN logs beside it)."""
    readers = [reader for reader, _ in parts]
    common, dropped = _common_extras(readers)
    tmp_logs = can_log_dir(tmp)
    infos, sessions, n_logs, steps = [], [], 0, 0
    with ReplayBufferWriter(tmp, attrs=attrs, extra_keys=common) as writer:
        for reader, indices in parts:
            reader_infos = episode_infos(reader.attrs, reader.n_episodes)
            reader_sessions = reader.attrs.get("recording_sessions")
            reader_sessions = list(reader_sessions) if isinstance(reader_sessions, list) else []
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
                        if src.is_file():
                            tmp_logs.mkdir(parents=True, exist_ok=True)
                            new_name = can_log_name(index, bus)
                            shutil.copy2(src, tmp_logs / new_name)
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


def _copy(jobs: Sequence[tuple[Sequence[tuple[ReplayBufferReader, Sequence[int]]], Path, dict]],
          force: bool) -> list[dict]:
    """Write each job (parts = [(reader, episode indices)], output, root attributes) as a new dataset.

    Every output is checked first (output path, dimensions, the CAN-log names of every episode), then
    written into a temporary directory beside it; only when all are complete are they moved onto their
    outputs, so an error (a corrupt chunk, a bad CAN-log name) leaves no output behind.
    Returns one {"episodes": n, "steps": n, "dropped_extras": [...], "can_logs": n} per job.
    """
    logs_of = {}
    for parts, out, _ in jobs:
        logs_of.update(_check_parts(parts, out, force))
    staged, summaries = [], []
    try:
        for parts, out, attrs in jobs:
            out.parent.mkdir(parents=True, exist_ok=True)
            tmp = out.with_name(f".{out.name}.tmp-{uuid.uuid4().hex[:8]}")
            staged.append((tmp, out))
            summaries.append(_stage(parts, tmp, attrs, logs_of))
        for tmp, out in staged:
            out_logs, tmp_logs = can_log_dir(out), can_log_dir(tmp)
            if tmp_logs.is_dir():
                if out_logs.exists():
                    shutil.rmtree(out_logs)
                os.replace(tmp_logs, out_logs)
            elif out_logs.exists() and force:
                shutil.rmtree(out_logs)
            replace_dir(tmp, out)
    finally:
        for tmp, _ in staged:
            for leftover in (tmp, can_log_dir(tmp)):
                if leftover.exists():
                    shutil.rmtree(leftover, ignore_errors=True)
    return summaries


def _json_key(value) -> str:
    return json.dumps(value, sort_keys=True)


def marked_episodes(reader: ReplayBufferReader) -> list[int]:
    """Episodes whose recording metadata lists problems (stale streams, dropped frames, ...)."""
    return [i for i, info in enumerate(episode_infos(reader.attrs, reader.n_episodes)) if info and info.get("problems")]


def _base_attrs(attrs: dict) -> dict:
    return {k: v for k, v in attrs.items() if k not in PER_EPISODE_ATTRS}


def merge(out: str | os.PathLike, inputs: Sequence[str | os.PathLike], force: bool = False,
          drop_marked: bool = False) -> dict:
    """Concatenate the episodes of ``inputs`` (in order) into a new dataset ``out``.

    The inputs must agree on (P, C, S, A), and on ``control_rate_hz`` and the action convention where
    they record them. ``drop_marked`` leaves out episodes recorded with problems. Returns the summary of
    :func:`_copy` plus ``warnings`` (lines to show the user) and ``dropped`` ({input: [episodes]}).
    """
    if len(inputs) < 2:
        raise DatasetError("merge needs at least two input datasets")
    readers = [ReplayBufferReader(p) for p in inputs]
    warnings = []
    for key, describe in (("control_rate_hz", lambda a: a.get("control_rate_hz")), ("action convention", convention_name)):
        values = {str(r.path): describe(r.attrs) for r in readers}
        known = {v for v in values.values() if v is not None}
        if len(known) > 1:
            raise DatasetError(f"the inputs differ in {key} ({values}): episodes with different meanings cannot be "
                               f"merged")
        if known and None in values.values():
            missing = [p for p, v in values.items() if v is None]
            warnings.append(f"{key} is not recorded in {', '.join(missing)}: the merged dataset says "
                            f"{next(iter(known))} for all episodes")
    clouds = {_json_key(r.attrs.get("pointcloud")) for r in readers if r.attrs.get("pointcloud") is not None}
    if len(clouds) > 1:
        warnings.append("the inputs were made with different point-cloud settings (attribute pointcloud); "
                        "the first input's are kept")
    attrs = _base_attrs(readers[0].attrs)
    for r in readers[1:]:
        for key, value in _base_attrs(r.attrs).items():
            attrs.setdefault(key, value)
    attrs["merged_from"] = [{"path": str(r.path), "episodes": r.n_episodes} for r in readers]
    dropped = {str(r.path): marked_episodes(r) for r in readers} if drop_marked else {}
    parts = [(r, [i for i in range(r.n_episodes) if i not in set(dropped.get(str(r.path), ()))]) for r in readers]
    (summary,) = _copy([(parts, Path(out), attrs)], force)
    summary["dropped"] = {k: v for k, v in dropped.items() if v}
    if summary["dropped_extras"]:
        warnings.append(f"per-step arrays not held by every input (or stored differently) were left out: "
                        f"{', '.join('data/' + n for n in summary['dropped_extras'])}")
    summary["warnings"] = warnings
    return summary


def choose_validation(n_episodes: int, val_ratio: float | None = None, val_episodes: Sequence[int] | None = None,
                      seed: int = 0) -> list[int]:
    """Sorted validation episode indices: the given ones, or round(val_ratio * E) drawn with ``seed``
    (at least 1, at most E - 1)."""
    if val_episodes is not None:
        chosen = sorted(set(int(i) for i in val_episodes))
        bad = [i for i in chosen if not 0 <= i < n_episodes]
        if bad:
            raise DatasetError(f"validation episode(s) {bad} out of range: the dataset holds episodes 0..{n_episodes - 1}")
    else:
        if val_ratio is None or not 0 < val_ratio < 1:
            raise DatasetError(f"the validation ratio must be in (0, 1), got {val_ratio}")
        n_val = min(n_episodes - 1, max(1, round(val_ratio * n_episodes)))
        chosen = sorted(np.random.default_rng(seed).permutation(n_episodes)[:n_val].tolist())
    if not chosen or len(chosen) >= n_episodes:
        raise DatasetError(f"a split needs at least one episode on each side; the dataset holds {n_episodes}")
    return chosen


def split(path: str | os.PathLike, train_out: str | os.PathLike, val_out: str | os.PathLike, *,
          val_ratio: float | None = None, val_episodes: Sequence[int] | None = None, seed: int = 0,
          force: bool = False, drop_marked: bool = False, drop_episodes: Sequence[int] = ()) -> dict:
    """Write the episodes of ``path`` into a training and a validation dataset (whole episodes each).

    ``drop_marked`` first leaves out the episodes recorded with problems, and ``drop_episodes`` the
    episodes named (e.g. those whose data is lost: they are not read); ``val_ratio`` then applies to the
    rest, and ``val_episodes`` may not name them. Returns {"train": [source indices], "val": [...],
    "dropped": [marked episodes left out], "left_out": [drop_episodes], "train_summary": ..., "val_summary": ...}.
    """
    reader = ReplayBufferReader(path)
    if Path(train_out).resolve() == Path(val_out).resolve():
        raise DatasetError("--train and --val must be different paths")
    named = sorted({int(i) for i in drop_episodes})
    bad = [i for i in named if not 0 <= i < reader.n_episodes]
    if bad:
        raise DatasetError(f"episode(s) {bad} to drop are out of range: the dataset holds episodes "
                           f"0..{reader.n_episodes - 1}")
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
    jobs = [([(reader, indices)], Path(target),
             dict(base, split_from={"path": str(reader.path), "part": part, "episodes": indices, "seed": seed}))
            for part, indices, target in (("train", train, train_out), ("val", val, val_out))]
    train_summary, val_summary = _copy(jobs, force)
    return {"train": train, "val": val, "dropped": marked, "left_out": named, "train_summary": train_summary,
            "val_summary": val_summary}


def repair(path: str | os.PathLike) -> dict:
    """Cut off the steps an interrupted append left after the last episode end, and per-episode metadata
    beyond the last episode. Returns {"dropped_steps": n, "dropped_infos": n}.

    Lost data cannot be repaired: a missing or corrupt chunk of a complete episode raises DatasetError
    (the key, the chunk, its steps and episodes) before anything on disk changes.
    """
    # a missing or broken dataset is reported first; every chunk of the complete episodes is decoded
    ReplayBufferReader(path, allow_incomplete_tail=True).check_chunks(decode=True)
    if not can_log_dir(path).is_dir():  # never recorded into: no recording session can hold it
        return _repair(path)
    lock = DatasetLock(can_log_dir(path) / LOCK_NAME)
    try:
        return _repair(path)
    finally:
        lock.release()


def _repair(path) -> dict:
    reader = ReplayBufferReader(path, allow_incomplete_tail=True)
    dropped = reader.dropped_tail_steps
    if dropped:
        with ReplayBufferWriter(path, repair_incomplete_tail=True, extra_keys=reader.extra_keys) as writer:
            dropped = writer.dropped_tail_steps
    raw = reader.attrs.get("episode_info")
    extra_infos = max(0, len(raw) - reader.n_episodes) if isinstance(raw, list) else 0
    if extra_infos:
        zarr.open_group(str(path), mode="r+", use_consolidated=False).attrs.update(
            {"episode_info": raw[: reader.n_episodes]})
    return {"dropped_steps": dropped, "dropped_infos": extra_infos}

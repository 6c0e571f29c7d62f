"""Datasets made from datasets: ``merge``, ``split`` (train/validation by episode) and ``repair``.

    merge("all.zarr", ["monday.zarr", "tuesday.zarr"])
    split("all.zarr", "train.zarr", "val.zarr", val_ratio=0.1, seed=0)
    repair("demo.zarr")          # cut off the steps of an interrupted append

Episodes are copied one at a time (memory holds one episode), into a temporary directory that is renamed
onto the output when complete; an existing output is replaced only with ``force``. What travels with each
episode: its arrays (point_cloud, state, action, and the extras every input holds with the same layout;
the others are dropped and named in the returned warnings), its ``episode_info`` entry (session indices
renumbered), and its CAN logs (``<dataset>.can/``, renamed to the new episode index). The root attributes
are the first input's, plus ``merged_from`` / ``split_from`` saying where each episode came from.
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


def _copy(parts: Sequence[tuple[ReplayBufferReader, Sequence[int]]], out: Path, attrs: dict, force: bool) -> dict:
    """Write the chosen episodes of each reader, in order, as a new dataset at ``out``.

    Returns {"episodes": n, "steps": n, "dropped_extras": [...], "can_logs": n}.
    """
    readers = [reader for reader, _ in parts]
    _check_output(out, [r.path for r in readers], force)
    dims = {_dims(r) for r in readers}
    if len(dims) > 1:
        listing = ", ".join(f"{r.path}: {_dims(r)}" for r in readers)
        raise DatasetError(f"the inputs differ in (points, point dims, state dims, action dims) ({listing}): "
                           f"they cannot form one dataset")
    if sum(len(indices) for _, indices in parts) == 0:
        raise DatasetError("no episodes to write")
    common, dropped = _common_extras(readers)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.name}.tmp-{uuid.uuid4().hex[:8]}")
    out_logs, tmp_logs = can_log_dir(out), can_log_dir(tmp)
    infos, sessions, n_logs, steps = [], [], 0, 0
    try:
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
                        for bus, name in (info.get("can_logs") or {}).items():
                            src = can_log_dir(reader.path) / name
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
        if tmp_logs.is_dir():
            if out_logs.exists():
                shutil.rmtree(out_logs)
            os.replace(tmp_logs, out_logs)
        elif out_logs.exists() and force:
            shutil.rmtree(out_logs)
        replace_dir(tmp, out)
    finally:
        for leftover in (tmp, tmp_logs):
            if leftover.exists():
                shutil.rmtree(leftover, ignore_errors=True)
    return {"episodes": len(infos), "steps": steps, "dropped_extras": dropped, "can_logs": n_logs}


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
    summary = _copy(parts, Path(out), attrs, force)
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
          force: bool = False, drop_marked: bool = False) -> dict:
    """Write the episodes of ``path`` into a training and a validation dataset (whole episodes each).

    ``drop_marked`` first leaves out the episodes recorded with problems (``val_ratio`` then applies to
    the rest; ``val_episodes`` may not name them). Returns {"train": [source indices], "val": [...],
    "dropped": [...], "train_summary": ..., "val_summary": ...}.
    """
    reader = ReplayBufferReader(path)
    if Path(train_out).resolve() == Path(val_out).resolve():
        raise DatasetError("--train and --val must be different paths")
    dropped = marked_episodes(reader) if drop_marked else []
    keep = [i for i in range(reader.n_episodes) if i not in set(dropped)]
    if val_episodes is not None:
        named = sorted(set(val_episodes) & set(dropped))
        if named:
            raise DatasetError(f"validation episode(s) {named} were recorded with problems and are dropped")
        val = choose_validation(reader.n_episodes, None, val_episodes, seed)
        if len(val) >= len(keep):
            raise DatasetError(f"a split needs at least one episode on each side; {len(keep)} episodes are kept")
    else:
        val = [keep[i] for i in choose_validation(len(keep), val_ratio, None, seed)]
    train = [i for i in keep if i not in set(val)]
    base = _base_attrs(reader.attrs)
    out = {"train": train, "val": val, "dropped": dropped}
    for part, indices, target in (("train", train, train_out), ("val", val, val_out)):
        attrs = dict(base, split_from={"path": str(reader.path), "part": part, "episodes": indices, "seed": seed})
        out[f"{part}_summary"] = _copy([(reader, indices)], Path(target), attrs, force)
    return out


def repair(path: str | os.PathLike) -> dict:
    """Cut off the steps an interrupted append left after the last episode end, and per-episode metadata
    beyond the last episode. Returns {"dropped_steps": n, "dropped_infos": n}."""
    ReplayBufferReader(path, allow_incomplete_tail=True)  # a missing or broken dataset is reported first
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

"""Typed readers of a dataset's root attributes: a value of the wrong type is an error, never a guess.

Each reader takes the attributes (a JSON dict) and the dataset's path for the message, and returns the
value, ``None`` when the attribute is absent (or null), or raises :class:`~dssp_core.errors.DatasetError` with one
line naming the dataset, the attribute and its value, and how to fix it. Nothing is converted behind the
user's back: ``"10"`` is not a rate, ``true`` is not 1 Hz, and an ``episode_info`` that is not a list is
not read as "no metadata". :func:`attribute_problems` runs every reader and returns their messages, for
``dssp-data info`` to list.

    control_rate_hz     a number > 0, finite (Hz)
    action_convention   a non-empty string ("<name>: <what it means>")
    episode_info        a list with one object (or null) per episode
    recording_sessions  a list of objects
    pointcloud          an object (the point-cloud settings the clouds were made with)
    camera_intrinsics   an object; width and height positive integers, fx, fy, ppx, ppy finite numbers
    camera_to_base      4x4 finite numbers
    camera_depth_unit   a number > 0, finite (metres per depth unit)

:func:`zarr_attrs` reads the attributes from the files without zarr and without following a link, and
:func:`made_by` / :func:`zarr_generator` say which program wrote a dataset: the signatures by which each
command recognises its own datasets (``dssp_core.output_guard.OutputKind``).
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path

from dssp_core.errors import DatasetError
from dssp_core.files import read_regular_text
from dssp_core.schema import parse_json

INTRINSICS_INTEGERS = ("width", "height")
INTRINSICS_NUMBERS = ("fx", "fy", "ppx", "ppy")


def _shown(value, limit: int = 60) -> str:
    text = json.dumps(value) if not isinstance(value, str) else repr(value)
    return text if len(text) <= limit else text[: limit - 4] + " ..."


def _bad(where, name: str, value, what: str, example: str | None = None) -> DatasetError:
    """The error for attribute ``name`` (``top.key`` or ``top[i]`` for a part of one) holding ``value``."""
    where = "the dataset" if where is None else str(where)
    path = "PATH" if where == "the dataset" else where
    top = name.split(".", 1)[0].split("[", 1)[0]
    attrs = f"zarr.open_group({path!r}, mode='r+').attrs"
    fix = f"{attrs}[{top!r}] = {example}" if example is not None and top == name else f"{top} in {attrs}"
    return DatasetError(f"{where}: attribute {name} is {_shown(value)}, not {what}; fix it with {fix}")


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _positive(attrs: Mapping, name: str, where, what: str, example: str) -> float | None:
    value = attrs.get(name)
    if value is None:
        return None
    if not _is_number(value) or value <= 0:
        raise _bad(where, name, value, what, example)
    return float(value)


def control_rate(attrs: Mapping, where=None) -> float | None:
    """``control_rate_hz``: the rate the episodes were recorded at, in Hz (None when not recorded)."""
    return _positive(attrs, "control_rate_hz", where, "a rate in Hz (a number > 0)", "10.0")


def depth_unit(attrs: Mapping, where=None) -> float | None:
    """``camera_depth_unit``: metres per raw depth unit."""
    return _positive(attrs, "camera_depth_unit", where, "metres per depth unit (a number > 0)", "0.001")


def action_convention(attrs: Mapping, where=None) -> str | None:
    """``action_convention``: what ``data/action`` means, ``"<name>: <description>"``."""
    value = attrs.get("action_convention")
    if value is None:
        return None
    if not isinstance(value, str) or not value.split(":", 1)[0].strip():
        raise _bad(where, "action_convention", value, 'a text "<name>: <what the action is>"', "'leader_command: ...'")
    return value


def convention_name(attrs: Mapping, where=None) -> str | None:
    """The action convention's short name (the text before ``:``), or None when not recorded."""
    text = action_convention(attrs, where)
    return None if text is None else text.split(":", 1)[0].strip()


def episode_info(attrs: Mapping, where=None) -> list | None:
    """``episode_info`` as stored: a list of objects (or nulls), one per episode, checked entry by entry."""
    value = attrs.get("episode_info")
    if value is None:
        return None
    if not isinstance(value, list):
        raise _bad(where, "episode_info", value, "a list (one object or null per episode)", "[...]")
    for i, entry in enumerate(value):
        if entry is not None and not isinstance(entry, Mapping):
            raise _bad(where, f"episode_info[{i}]", entry, "an object or null")
    return value


def recording_sessions(attrs: Mapping, where=None) -> list | None:
    """``recording_sessions``: one object per recording session."""
    value = attrs.get("recording_sessions")
    if value is None:
        return None
    if not isinstance(value, list) or not all(isinstance(s, Mapping) for s in value):
        raise _bad(where, "recording_sessions", value, "a list of objects", "[...]")
    return value


def pointcloud(attrs: Mapping, where=None) -> dict | None:
    """``pointcloud``: the point-cloud settings the clouds were made with (a JSON object)."""
    value = attrs.get("pointcloud")
    if value is None:
        return None
    if not isinstance(value, Mapping):
        raise _bad(where, "pointcloud", value, "an object of point-cloud settings", "{...}")
    return dict(value)


def camera_intrinsics(attrs: Mapping, where=None) -> dict | None:
    """``camera_intrinsics``: ``{"width", "height", "fx", "fy", "ppx", "ppy"}`` in pixels."""
    value = attrs.get("camera_intrinsics")
    if value is None:
        return None
    example = "{'width': 640, 'height': 480, 'fx': ..., 'fy': ..., 'ppx': ..., 'ppy': ...}"
    if not isinstance(value, Mapping):
        raise _bad(where, "camera_intrinsics", value, "an object of pinhole intrinsics", example)
    for key in INTRINSICS_INTEGERS:
        if key in value and not (isinstance(value[key], int) and not isinstance(value[key], bool) and value[key] > 0):
            raise _bad(where, f"camera_intrinsics.{key}", value[key], "a positive integer (pixels)")
    for key in INTRINSICS_NUMBERS:
        if key in value and not _is_number(value[key]):
            raise _bad(where, f"camera_intrinsics.{key}", value[key], "a finite number (pixels)")
    return dict(value)


def camera_to_base(attrs: Mapping, where=None) -> list | None:
    """``camera_to_base``: the camera's pose in the robot-base frame, 4x4 numbers."""
    value = attrs.get("camera_to_base")
    if value is None:
        return None
    if not (
        isinstance(value, list)
        and len(value) == 4
        and all(isinstance(row, list) and len(row) == 4 and all(_is_number(v) for v in row) for row in value)
    ):
        raise _bad(where, "camera_to_base", value, "a 4x4 matrix of finite numbers", "[[1, 0, 0, 0], ...]")
    return value


READERS: dict[str, Callable] = {
    "control_rate_hz": control_rate,
    "action_convention": action_convention,
    "episode_info": episode_info,
    "recording_sessions": recording_sessions,
    "pointcloud": pointcloud,
    "camera_intrinsics": camera_intrinsics,
    "camera_to_base": camera_to_base,
    "camera_depth_unit": depth_unit,
}
"""Every attribute with a reader here, by name."""


def attribute_problems(attrs: Mapping, where: str | os.PathLike | None = None) -> dict[str, str]:
    """{attribute: the reader's message} for each attribute whose value its reader refuses."""
    problems = {}
    for name, read in READERS.items():
        try:
            read(attrs, where)
        except DatasetError as exc:
            problems[name] = str(exc)
    return problems


# ------------------------------------------------------------------------------------------- from disk
def zarr_attrs(path: str | os.PathLike) -> dict | None:
    """The root attributes of a zarr group at ``path`` (format 2 or 3), read as JSON; None if it is not one.
    ValueError for JSON that is not (nested too deep, a key given twice: :func:`~dssp_core.schema.parse_json`).

    Its metadata files are read only as regular files (:func:`~dssp_core.files.read_regular_text`), no link followed: with a
    linked ``.zgroup`` or ``zarr.json`` the folder is not a zarr group, with a linked ``.zattrs`` it has no
    attributes."""
    path = Path(path)
    if read_regular_text(path / ".zgroup") is not None:
        text = read_regular_text(path / ".zattrs")
        attrs = parse_json(text) if text is not None else {}
    elif (text := read_regular_text(path / "zarr.json")) is not None:
        meta = parse_json(text)
        attrs = meta.get("attributes", {}) if isinstance(meta, dict) else None
    else:
        return None
    return attrs if isinstance(attrs, dict) else None


def zarr_generator(path: str | os.PathLike) -> str | None:
    """The ``generator`` attribute of a zarr dataset (which program wrote it), or None."""
    try:
        attrs = zarr_attrs(path)
    except (OSError, ValueError):
        return None
    value = (attrs or {}).get("generator")
    return value if isinstance(value, str) else None


ZARR_ENTRIES = (".zgroup", ".zattrs", ".zmetadata", "zarr.json", "data", "meta")
"""The top-level names of a DP3 zarr dataset as :mod:`dssp_data.replay_buffer` writes it."""


def made_by(path: str | os.PathLike, generators: Iterable[str]) -> bool:
    """The zarr dataset at ``path`` names one of ``generators`` as its ``generator``, and was not made from
    other datasets by an older ``dssp-data merge``/``split`` (which copied its first input's generator)."""
    attrs = zarr_attrs(path) or {}
    return attrs.get("generator") in tuple(generators) and "merged_from" not in attrs and "split_from" not in attrs

"""The DP3 zarr dataset's layout, shared by its reader and its writer: the keys, :class:`Episode`, and the checks
of shapes, episode ends, extras and values (:mod:`dssp_data.replay_buffer` reads, :mod:`dssp_data.replay_buffer_writer`
writes; the chunk-level access is :mod:`dssp_data.zarr_chunks`).

Every problem raises :class:`~dssp_core.errors.DatasetError` with one line naming the key, the problem and what to do.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from dssp_core.errors import DatasetError

__all__ = ["Episode", "DATA_KEYS", "ENDS_KEY", "REQUIRED_KEYS", "POINT_DIMS", "CHUNK_STEPS", "ZARR_FORMATS"]


DATA_KEYS = ("point_cloud", "state", "action")
"""Per-step arrays under ``data/`` that this package reads and writes."""
ENDS_KEY = "meta/episode_ends"
REQUIRED_KEYS = tuple(f"data/{k}" for k in DATA_KEYS) + (ENDS_KEY,)
POINT_DIMS = (3, 6)
"""Allowed point widths C: xyz, or xyz + rgb."""
CHUNK_STEPS = 100
"""Chunk length along time, as DP3 writes."""
ENDS_CHUNK = 1000
EXTRA_CHUNK_BYTES = 16 << 20
"""Upper bound on the size of one chunk of an extra array (e.g. depth images): fewer steps per chunk."""
ZARR_FORMATS = (2, 3)


@dataclass
class Episode:
    """One demonstration.

    Attributes:
        point_cloud: (T, P, C) float32, C = 3 (xyz) or 6 (xyz + rgb).
        state: (T, S) float32, the robot's proprioceptive state.
        action: (T, A) float32, the commanded action at each step.
        extras: other per-step arrays by name, each (T, ...) of any numeric
            or bool dtype (kept as is; NaN allowed), stored as ``data/<name>``.
    """

    point_cloud: np.ndarray
    state: np.ndarray
    action: np.ndarray
    extras: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def n_steps(self) -> int:
        """T, the number of steps."""
        return int(np.shape(self.state)[0])


# --------------------------------------------------------------------------- checks


def check_data_structure(point_cloud, state, action, where: str, prefix: str = "data/") -> None:
    """Check ranks, widths and dtypes of the three per-step arrays (zarr or numpy)."""
    pc_shape = tuple(np.shape(point_cloud))
    if len(pc_shape) != 3 or pc_shape[2] not in POINT_DIMS or pc_shape[1] == 0:
        raise DatasetError(
            f"{where}: {prefix}point_cloud has shape {pc_shape}; expected (T, P, C) with P >= 1 "
            f"and C = 3 (xyz) or 6 (xyz+rgb): rewrite the point clouds in that layout"
        )
    for name, array, letter in (("state", state, "S"), ("action", action, "A")):
        shape = tuple(np.shape(array))
        if len(shape) != 2 or shape[1] == 0:
            raise DatasetError(
                f"{where}: {prefix}{name} has shape {shape}; expected 2-D (T, {letter}) with {letter} >= 1: "
                f"store one flat vector per step"
            )
    for name, array in zip(DATA_KEYS, (point_cloud, state, action)):
        dtype = np.dtype(array.dtype)
        if not (np.issubdtype(dtype, np.floating) or np.issubdtype(dtype, np.integer)):
            raise DatasetError(
                f"{where}: {prefix}{name} has dtype {dtype}; expected a float array: rewrite it as float32"
            )


def check_ends_structure(ends, where: str) -> None:
    """Check that episode_ends (zarr or numpy) is a non-empty 1-D integer array."""
    if len(ends.shape) != 1:
        raise DatasetError(
            f"{where}: {ENDS_KEY} has shape {tuple(ends.shape)}; expected 1-D (E,): "
            f"store one cumulative end index per episode"
        )
    if not np.issubdtype(np.dtype(ends.dtype), np.integer):
        raise DatasetError(
            f"{where}: {ENDS_KEY} has dtype {np.dtype(ends.dtype)}; expected an integer array (int64): rewrite it"
        )
    if ends.shape[0] == 0:
        raise DatasetError(f"{where}: {ENDS_KEY} is empty, so the dataset holds no episode: write at least one")


def check_episode_ends(ends: np.ndarray, where: str) -> None:
    """Check that (E,) int64 ``ends`` is positive and strictly increasing."""
    if ends[0] <= 0:
        problem = "episode 0 is empty" if ends[0] == 0 else "a negative index is out of range"
        raise DatasetError(f"{where}: {ENDS_KEY}[0] = {ends[0]}: {problem}; remove it or fix the episode ends")
    bad = np.flatnonzero(np.diff(ends) <= 0)
    if bad.size:
        k = int(bad[0]) + 1
        raise DatasetError(
            f"{where}: {ENDS_KEY} is not strictly increasing ({ENDS_KEY}[{k - 1}] = {ends[k - 1]}, "
            f"[{k}] = {ends[k]}): episode {k} is empty; remove it or fix the episode ends"
        )


REPAIR_REMEDY = "cut them off with dssp-data repair PATH (or load with allow_incomplete_tail=True)"
SHAPE_REMEDY = "dssp-data repair PATH sets it back to the last episode end (nothing stored is lost)"


def resolve_length(
    lengths: Mapping[str, int],
    last_end: int,
    allow_incomplete_tail: bool,
    where: str,
    remedy: str = REPAIR_REMEDY,
    unbacked: Mapping[str, tuple[int, int, str]] | None = None,
    shape_remedy: str = SHAPE_REMEDY,
) -> tuple[int, int]:
    """Return (number of steps to keep, number of trailing steps dropped).

    ``lengths`` maps each data key to its length along time. Steps after
    ``last_end`` are dropped only when ``allow_incomplete_tail`` is true;
    otherwise the error suggests ``remedy``. ``unbacked``: {key: (first step without a stored chunk,
    length, metadata file)} of arrays whose metadata gives steps that no chunk holds — reported as a
    shape that does not match the data (``shape_remedy``), not as an interrupted write.
    """
    listing = ", ".join(f"{k}: {n}" for k, n in lengths.items())
    shortest, longest = min(lengths.values()), max(lengths.values())
    if shortest >= last_end and longest > last_end:
        tail = longest - last_end
        if allow_incomplete_tail:
            return last_end, tail
        if unbacked:
            key, (start, length, meta) = next(iter(unbacked.items()))
            raise DatasetError(
                f"{where}: {key} has {length} steps in its metadata ({meta}) but no chunk is stored for steps "
                f"{start}..{length - 1}, and the episodes end at step {last_end} ({ENDS_KEY}[-1]): its shape does not "
                f"match the stored data (an edited {meta.rsplit('/', 1)[-1]}, or a write that stopped right after "
                f"growing the array): {shape_remedy}"
            )
        raise DatasetError(
            f"{where}: data has {tail} steps after the last episode end ({ENDS_KEY}[-1] = {last_end}; {listing}) "
            f"(an incomplete episode?): {remedy}, or rewrite the dataset"
        )
    if shortest != longest:
        raise DatasetError(
            f"{where}: data arrays differ in length along time ({listing}); every array under data/ "
            f"needs one entry per step: rewrite the dataset"
        )
    if last_end > longest:
        raise DatasetError(
            f"{where}: {ENDS_KEY}[-1] = {last_end} is out of range: the data arrays hold only {longest} steps "
            f"(data shorter than the episodes claim): fix {ENDS_KEY} or rewrite the dataset"
        )
    return last_end, 0


FLOAT32_MAX = float(np.finfo(np.float32).max)
"""The largest magnitude a dataset's float32 arrays hold (3.4e38)."""


def as_float32(values, what: str, remedy: str = "fix the episode", step: str = "step") -> np.ndarray:
    """``values`` (T, ...) of numbers as float32, or one DatasetError line naming ``what`` (where the values come
    from: a file, an episode, a key), the ``step`` (what the first axis counts: step, frame), the index and the
    value: NaN, inf, or a number beyond float32's range, which would become inf (checked before the cast: no numpy
    warning)."""
    array = np.asarray(values)
    if array.dtype != np.float32:
        with np.errstate(all="ignore"):
            big = (array > FLOAT32_MAX) | (array < -FLOAT32_MAX)
        bad = np.argwhere(big)
        if bad.size:
            at = tuple(int(i) for i in bad[0])
            index = f", index {list(at[1:]) if len(at) > 2 else at[1]}" if len(at) > 1 else ""
            raise DatasetError(
                f"{what} holds {array[at].item()!r} at {step} {at[0]}{index}, beyond the range of float32 "
                f"(±{FLOAT32_MAX:.3g}), the number type of a dataset: {remedy}"
            )
        with np.errstate(all="ignore"):
            array = array.astype(np.float32)
    if not np.issubdtype(array.dtype, np.floating):
        return array
    bad = np.argwhere(~np.isfinite(array))
    if bad.size:
        at = tuple(int(i) for i in bad[0])
        index = f", index {list(at[1:]) if len(at) > 2 else at[1]}" if len(at) > 1 else ""
        raise DatasetError(f"{what} holds NaN or inf (first at {step} {at[0]}{index}: {array[at].item()!r}): {remedy}")
    return array


def first_bad_steps(values: np.ndarray) -> np.ndarray:
    """Indices of the steps (first axis) of ``values`` that hold NaN or inf."""
    return np.flatnonzero(~np.isfinite(values.reshape(values.shape[0], -1)).all(axis=1))


def check_finite_values(key: str, values: np.ndarray, ends: np.ndarray, where: str) -> None:
    """Raise if ``values`` (T, ...) holds NaN or inf; name the first bad step and its episode."""
    bad_steps = first_bad_steps(values)
    if bad_steps.size:
        step = int(bad_steps[0])
        episode = int(np.searchsorted(ends, step, side="right"))
        raise DatasetError(
            f"{where}: {key} holds NaN or inf at {bad_steps.size} step(s), first at step {step} "
            f"(episode {episode}): fix or remove that episode and rewrite the dataset"
        )


def check_extra_name(name: str, where: str) -> None:
    """An extra's name is one path component that is not a required key."""
    if not isinstance(name, str) or not name or "/" in name or name.startswith(".") or name in DATA_KEYS:
        raise DatasetError(
            f"{where}: {name!r} cannot name an extra per-step array: use a plain name other than {', '.join(DATA_KEYS)}"
        )


def check_extra_array(name: str, array: np.ndarray, n_steps: int, where: str) -> np.ndarray:
    """Check that an extra is (n_steps, ...) and numeric or bool; return it unchanged."""
    dtype = np.dtype(array.dtype)
    if array.ndim == 0 or array.shape[0] != n_steps:
        raise DatasetError(
            f"{where}: extra {name} has shape {tuple(array.shape)}; expected ({n_steps}, ...) with one entry per step"
        )
    if not (np.issubdtype(dtype, np.number) or dtype == np.bool_):
        raise DatasetError(f"{where}: extra {name} has dtype {dtype}; store numbers or booleans")
    return array


def extras_layout(extras: Mapping[str, np.ndarray]) -> dict[str, tuple[str, tuple[int, ...]]]:
    """{name: (dtype string, trailing shape)} of extra arrays (numpy or zarr)."""
    return {name: (np.dtype(a.dtype).str, tuple(a.shape[1:])) for name, a in sorted(extras.items())}


def describe_extras_layout(layout: Mapping[str, tuple[str, tuple[int, ...]]]) -> str:
    if not layout:
        return "none"
    return ", ".join(
        f"{name} {np.dtype(dt).name}{list(shape) if shape else ''}" for name, (dt, shape) in layout.items()
    )

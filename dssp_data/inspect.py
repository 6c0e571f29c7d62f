"""What is in a dataset, and what is wrong with it: the facts ``dssp-data info`` prints.

    report = inspect_dataset("demo.zarr")     # a JSON-ready dict
    print(format_report(report))

The report holds: the number of episodes and their lengths; the control rate (attribute) and the
measured rate of recorded episodes; every array under ``data/`` and ``meta/`` with shape and dtype;
per-channel value ranges of state and action and the point clouds' coordinate ranges; the root
attributes; per-episode recording metadata (``dssp_data.recording``); and ``problems`` (must be
looked at: NaN, an interrupted write, marked episodes, missing CAN logs, timestamp gaps, ...) and
``notes`` (worth knowing). An attribute whose value has the wrong type (a ``control_rate_hz`` that is not a
number > 0, an ``episode_info`` that is not a list, ...: :mod:`dssp_data.attributes`) is a problem
that names it, never read as "not recorded". The dataset is read one episode at a time, through the dataset reader's checked
path; first every chunk of every array is checked without decoding (stored, and a whole Blosc frame), so a
missing or corrupt chunk anywhere, also in arrays the report does not read, raises DatasetError naming the
key and the chunk (``dssp-data info``: exit 2) instead of reading as zeros. CAN-log names in
``episode_info`` are resolved only inside the dataset's CAN-log folder; a name that points elsewhere is a
problem, and that file is not looked at.
"""

from __future__ import annotations

import json
import math
import os
import warnings
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from dssp_core.errors import DatasetError
from dssp_data import attributes
from dssp_data.dataset_layout import DATA_KEYS
from dssp_data.recording import (
    FLAGS_KEY,
    PROBLEM_TEXT,
    STEP_PROBLEMS,
    can_log_dir,
    episode_can_logs,
    episode_infos,
)
from dssp_data.replay_buffer import ReplayBufferReader

MAX_JOINT_JUMP = 0.5
"""rad: a recorded joint action changing more than this in one step is reported (a teleoperation glitch)."""
GAP_PERIODS = 1.5
"""A step more than this many periods after the previous one is a gap in the recording."""


def _range_rows(lo: np.ndarray, hi: np.ndarray) -> list[list[float]]:
    return [[float(a), float(b)] for a, b in zip(lo, hi)]


def _episode_list(indices: list[int], limit: int = 12) -> str:
    shown = ", ".join(str(i) for i in indices[:limit])
    return shown + (f", ... ({len(indices)} in all)" if len(indices) > limit else "")


def _generators(attrs: Mapping) -> set:
    """The programs that made the dataset: its ``generator`` and those of the inputs merge/split recorded."""
    found = {attrs.get("generator")}
    sources = attrs.get("merged_from")
    sources = (sources if isinstance(sources, list) else []) + [attrs.get("split_from")]
    found |= {s.get("generator") for s in sources if isinstance(s, Mapping)}
    return {g for g in found if isinstance(g, str)}


def _is_recorded(attrs: Mapping) -> bool:
    return "dssp-record" in _generators(attrs) or isinstance(attrs.get("episode_info"), list)


def _checked(read, attrs: Mapping, where, problems: list[str]):
    """``read(attrs, where)``, or None with its message added to ``problems``."""
    try:
        return read(attrs, where)
    except DatasetError as exc:
        problems.append(str(exc).removeprefix(f"{where}: "))
        return None


def inspect_dataset(path: str | os.PathLike) -> dict:
    """Read ``path`` episode by episode and return the report (see the module docstring).

    Raises DatasetError when the dataset cannot be opened or read (missing keys, a missing or corrupt chunk:
    lost data); problems with its values are listed in the report instead.
    """
    path = Path(path)
    reader = ReplayBufferReader(path, allow_incomplete_tail=True)
    unstored = reader.check_chunks()
    attrs = reader.attrs
    lengths = reader.episode_lengths()
    problems: list[str] = []
    notes: list[str] = []
    for key, n in unstored.items():
        notes.append(
            f"{key}: {n} chunk(s) are not stored and read as the fill value (zarr 3 leaves out chunks that "
            f"hold only it); this array does not record that every chunk was written"
        )
    recorded = _is_recorded(attrs)
    where = str(path)
    for name in (
        "action_convention",
        "pointcloud",
        "camera_intrinsics",
        "camera_to_base",
        "camera_depth_unit",
        "recording_sessions",
    ):
        _checked(attributes.READERS[name], attrs, where, problems)

    state_lo = state_hi = action_lo = action_hi = cloud_lo = cloud_hi = None
    nonfinite: dict[str, list[int]] = {k: [] for k in DATA_KEYS}
    zero_clouds: dict[int, int] = {}
    jumps: list[tuple[int, int, float]] = []
    gaps: dict[int, int] = {}
    backwards: list[int] = []
    flagged_steps: dict[str, int] = {}
    rate = _checked(attributes.control_rate, attrs, where, problems)
    time_keys = [k for k in ("timestamp",) if k in reader.extra_keys]
    want_extras = time_keys + ([FLAGS_KEY] if FLAGS_KEY in reader.extra_keys else [])
    n_arms = None
    if recorded and reader.arrays["data/state"][0][1] % 7 == 0:
        n_arms = reader.arrays["data/state"][0][1] // 7

    def fold(lo, hi, values, axes):
        finite = np.where(np.isfinite(values), values, np.nan)
        with warnings.catch_warnings():  # an all-NaN channel gives NaN, said by the problems list
            warnings.simplefilter("ignore", RuntimeWarning)
            a, b = np.nanmin(finite, axis=axes), np.nanmax(finite, axis=axes)
        if lo is None:
            return a, b
        return np.fmin(lo, a), np.fmax(hi, b)

    for i in range(reader.n_episodes):
        ep = reader.episode(i, extras=want_extras, check_finite=False)
        for key in DATA_KEYS:
            if not np.all(np.isfinite(getattr(ep, key))):
                nonfinite[key].append(i)
        state_lo, state_hi = fold(state_lo, state_hi, ep.state, 0)
        action_lo, action_hi = fold(action_lo, action_hi, ep.action, 0)
        cloud_lo, cloud_hi = fold(cloud_lo, cloud_hi, ep.point_cloud, (0, 1))
        zero = int(np.count_nonzero(np.all(ep.point_cloud[..., :3] == 0, axis=(1, 2))))
        if zero:
            zero_clouds[i] = zero
        if n_arms is not None and ep.n_steps > 1:
            joints = np.concatenate([np.arange(6) + 7 * a for a in range(n_arms)])
            step = np.abs(np.diff(ep.action[:, joints], axis=0))
            if np.isfinite(step).all() and step.max() > MAX_JOINT_JUMP:
                s = int(np.argmax(step.max(axis=1)))
                jumps.append((i, s + 1, float(step.max())))
        if "timestamp" in ep.extras and ep.n_steps > 1:
            dt = np.diff(ep.extras["timestamp"])
            if np.any(dt <= 0):
                backwards.append(i)
            if rate is not None:
                n_gaps = int(np.count_nonzero(dt > GAP_PERIODS / rate))
                if n_gaps:
                    gaps[i] = n_gaps
        if FLAGS_KEY in ep.extras:
            for name, bit in STEP_PROBLEMS.items():
                n = int(np.count_nonzero(ep.extras[FLAGS_KEY] & bit))
                if n:
                    flagged_steps[name] = flagged_steps.get(name, 0) + n

    # ---- problems with the values --------------------------------------------------------------------
    for key, (start, length, meta) in reader.unbacked_steps.items():
        problems.append(
            f"{key} has {length} steps in its metadata ({meta}) but no chunk is stored for steps "
            f"{start}..{length - 1}, after the last episode end ({reader.n_steps}): its shape does not match "
            f"the stored data (edited metadata, or a write that stopped right after growing the array); "
            f"`dssp-data repair` sets it back to {reader.n_steps} steps (nothing stored is lost)"
        )
    tail = max(
        [
            shape[0] - reader.n_steps
            for key, (shape, _) in reader.arrays.items()
            if key.startswith("data/") and key not in reader.unbacked_steps
        ]
        + [0]
    )
    if tail:
        problems.append(
            f"{tail} steps after the last episode end: a write was interrupted; they "
            f"are ignored (remove them with `dssp-data repair`; the next dssp-record session also does)"
        )
    for key, episodes in nonfinite.items():
        if episodes:
            problems.append(f"data/{key} holds NaN or inf in episode(s) {_episode_list(episodes)}: training refuses it")
    short = [i for i, n in enumerate(lengths) if n < 2]
    if short:
        problems.append(f"episode(s) {_episode_list(short)} have a single step")
    if zero_clouds:
        problems.append(
            f"all-zero point clouds in episode(s) {_episode_list(sorted(zero_clouds))} "
            f"({sum(zero_clouds.values())} steps)"
        )
    for i, s, size in jumps:
        problems.append(
            f"episode {i}: the action jumps by {size:.2f} rad at step {s} (more than {MAX_JOINT_JUMP} rad "
            f"in one step: a teleoperation glitch?)"
        )
    if backwards:
        problems.append(f"timestamps do not increase in episode(s) {_episode_list(backwards)}")
    for i, n in gaps.items():
        problems.append(f"episode {i}: {n} gap(s) longer than {GAP_PERIODS:g} periods between steps")
    if attrs.get("control_rate_hz") is None:
        (problems if recorded else notes).append(
            "the control rate is not recorded (attribute control_rate_hz): pass --control-rate to dssp-train"
        )
    if attrs.get("action_convention") is None:
        notes.append("the action convention is not recorded (attribute action_convention)")
    for key in ("point_cloud", "state", "action"):
        dtype = reader.arrays[f"data/{key}"][1]
        if dtype != np.float32:
            notes.append(f"data/{key} is stored as {dtype}; it is read as float32")

    # ---- recording metadata ---------------------------------------------------------------------------
    try:
        infos = episode_infos(attrs, reader.n_episodes, where)
    except DatasetError as exc:
        problems.append(str(exc).removeprefix(f"{where}: ") + " (the recording metadata is not looked at)")
        infos = [None] * reader.n_episodes
    episodes = []
    marked = []
    log_dir = can_log_dir(path)
    referenced = set()
    missing_logs = []
    for i, info in enumerate(infos):
        entry = {"index": i, "steps": int(lengths[i])}
        if info is not None:
            entry.update({k: info.get(k) for k in ("started", "rate_hz", "duration_s", "ended_by", "session", "task")})
            entry["problems"] = info.get("problems") or []
            entry["clean"] = not entry["problems"]
            if isinstance(info.get("sim"), dict):
                entry["sim"] = info["sim"]
            entry["can_logs"] = info.get("can_logs") or {}
            try:
                logs = episode_can_logs(path, info, i)
            except DatasetError as exc:
                problems.append(f"{exc} (not looked at)")
                logs = {}
            for log in logs.values():
                name = log.relative_to(log_dir).as_posix()
                referenced.add(name)
                if not log.is_file():
                    missing_logs.append(f"{name} (episode {i})")
            if info.get("can_log_errors"):
                problems.append(f"episode {i}: its CAN log stopped early ({info['can_log_errors']})")
            if entry["problems"]:
                marked.append(i)
                what = "; ".join(_problem_text(p) for p in entry["problems"])
                problems.append(f"episode {i} was recorded with problems: {what}")
        episodes.append(entry)
    if recorded and any(info is None for info in infos):
        missing = [i for i, info in enumerate(infos) if info is None]
        notes.append(f"no recording metadata for episode(s) {_episode_list(missing)} (added by merge or another tool)")
    if missing_logs:
        problems.append(f"CAN logs missing: {', '.join(missing_logs[:6])}" + (" ..." if len(missing_logs) > 6 else ""))
    if log_dir.is_dir():
        files = sorted(p.name for p in log_dir.iterdir() if p.is_file() and not p.name.startswith("."))
        partial = [f for f in files if ".partial-" in f]
        if partial:
            notes.append(
                f"CAN logs of {len(partial)} unfinished episode(s) (a crash or kill while recording): "
                f"{', '.join(partial[:4])}" + (" ..." if len(partial) > 4 else "")
            )
        orphans = [f for f in files if ".partial-" not in f and f not in referenced]
        if orphans and recorded:
            notes.append(
                f"CAN logs that belong to no episode (an append interrupted after the log was renamed): "
                f"{', '.join(orphans[:4])}" + (" ..." if len(orphans) > 4 else "")
            )
    sessions = attrs.get("recording_sessions")
    if isinstance(sessions, list) and len(sessions) > 1 and all(isinstance(x, Mapping) for x in sessions):
        keys = ("camera_to_base", "camera_intrinsics", "camera_depth_unit")
        first = sessions[0] if isinstance(sessions[0], dict) else {}
        changed = [
            k for k, s in enumerate(sessions) if isinstance(s, dict) and any(s.get(x) != first.get(x) for x in keys)
        ]
        if changed:
            notes.append(
                f"the camera calibration differs between recording sessions ({_episode_list(changed)} vs 0): "
                f"each session's calibration is in recording_sessions"
            )

    measured = [info["rate_hz"] for info in infos if info and isinstance(info.get("rate_hz"), (int, float))]
    return {
        "path": str(path),
        "zarr_format": reader.zarr_format,
        "n_episodes": reader.n_episodes,
        "n_steps": reader.n_steps,
        "episode_lengths": [int(n) for n in lengths],
        "control_rate_hz": rate,
        "measured_rate_hz": (
            {"mean": float(np.mean(measured)), "min": float(np.min(measured)), "max": float(np.max(measured))}
            if measured
            else None
        ),
        "action_convention": attrs.get("action_convention")
        if isinstance(attrs.get("action_convention"), str)
        else None,
        "arrays": {k: {"shape": list(shape), "dtype": str(dtype)} for k, (shape, dtype) in reader.arrays.items()},
        "ranges": {
            "state": _range_rows(state_lo, state_hi),
            "action": _range_rows(action_lo, action_hi),
            "point_cloud": _range_rows(cloud_lo, cloud_hi),
        },
        "attributes": {k: v for k, v in attrs.items() if k not in ("episode_info",)},
        "episodes": episodes,
        "marked_episodes": marked,
        "step_problems": flagged_steps,
        "problems": problems,
        "notes": notes,
    }


def _problem_text(problem: dict) -> str:
    if not isinstance(problem, dict):
        return str(problem)
    what = problem.get("what") or PROBLEM_TEXT.get(problem.get("kind"), str(problem.get("kind")))
    if problem.get("kind") == "rate":
        return f"{what} ({problem.get('measured_hz')} Hz)"
    if "steps" in problem:
        return f"{what} at {problem['steps']} step(s) from step {problem.get('first_step')}"
    return what


# ---- text -----------------------------------------------------------------------------------------------
def _fmt(x: float) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "nan"
    return f"{x:.4g}"


def _short(value, limit: int = 110) -> str:
    text = json.dumps(value, separators=(", ", ": "))
    return text if len(text) <= limit else text[: limit - 4] + " ..."


def format_report(report: dict) -> str:
    """The report as text for a terminal."""
    out = []
    lengths = report["episode_lengths"]
    out.append(f"dataset     {report['path']} (zarr format {report['zarr_format']})")
    out.append(
        f"episodes    {report['n_episodes']}, {report['n_steps']} steps; length min {min(lengths)} / median "
        f"{int(np.median(lengths))} / max {max(lengths)}"
    )
    if len(lengths) <= 30:
        out.append(f"lengths     {lengths}")
    rate = report["control_rate_hz"]
    invalid = rate is None and report["attributes"].get("control_rate_hz") is not None
    out.append(
        "rate        "
        f"{f'{rate:g} Hz (control_rate_hz)' if rate else 'control_rate_hz is not a rate (see problems)' if invalid else 'not recorded'}"
        + (
            f"; measured {report['measured_rate_hz']['mean']:.3f} Hz (min {report['measured_rate_hz']['min']:.3f}, "
            f"max {report['measured_rate_hz']['max']:.3f})"
            if report["measured_rate_hz"]
            else ""
        )
    )
    out.append(f"action      {report['action_convention'] or 'convention not recorded'}")
    out.append("arrays")
    for key, a in report["arrays"].items():
        out.append(f"  {key:28s} {str(tuple(a['shape'])):22s} {a['dtype']}")
    out.append("ranges      (min .. max per channel)")
    state, action = report["ranges"]["state"], report["ranges"]["action"]
    out.append(f"  {'dim':>4s}  {'state':>23s}  {'action':>23s}")
    for d in range(max(len(state), len(action))):
        s = f"{_fmt(state[d][0]):>10s} .. {_fmt(state[d][1]):<10s}" if d < len(state) else " " * 24
        a = f"{_fmt(action[d][0]):>10s} .. {_fmt(action[d][1]):<10s}" if d < len(action) else ""
        out.append(f"  {d:4d}  {s}  {a}")
    names = ["x", "y", "z", "r", "g", "b"]
    cloud = report["ranges"]["point_cloud"]
    out.append(
        "  point_cloud "
        + ", ".join(f"{names[c] if c < 6 else c} {_fmt(lo)} .. {_fmt(hi)}" for c, (lo, hi) in enumerate(cloud))
    )
    if report["attributes"]:
        out.append("attributes")
        for key, value in report["attributes"].items():
            if key == "recording_sessions" and isinstance(value, list):
                out.append(f"  {key}: {len(value)} session(s)")
                for k, s in enumerate(value):
                    if isinstance(s, dict):
                        out.append(
                            f"    {k}: {s.get('started')} camera {s.get('camera')} can {s.get('can')} "
                            f"{s.get('rate_hz')} Hz, host {s.get('host')}"
                        )
            else:
                out.append(f"  {key}: {_short(value)}")
    recorded = [e for e in report["episodes"] if "started" in e]
    if recorded:
        out.append("recorded episodes")
        for e in recorded:
            state_text = "clean" if e["clean"] else "PROBLEMS"
            sim = e.get("sim")
            sim_text = f"  seed {sim.get('seed')}" if sim else ""
            rate_text = f"{e['rate_hz']:.2f} Hz" if isinstance(e.get("rate_hz"), (int, float)) else "- Hz"
            out.append(
                f"  {e['index']:4d}  {e['steps']:5d} steps  {rate_text:>9s}  {state_text:8s} {e.get('started')}  "
                f"{e.get('ended_by')}{sim_text}"
            )
    if report["step_problems"]:
        out.append(
            "flagged steps  " + ", ".join(f"{PROBLEM_TEXT.get(k, k)}: {v}" for k, v in report["step_problems"].items())
        )
    out.append(f"problems    {len(report['problems']) or 'none found'}")
    out.extend(f"  - {p}" for p in report["problems"])
    if report["notes"]:
        out.append("notes")
        out.extend(f"  - {n}" for n in report["notes"])
    return "\n".join(out)

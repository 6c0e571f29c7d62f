"""Files a user names that are not files: the one read helper (dssp_core.files.read_input_bytes) and every reader
of a settings-like file standing on it. A FIFO never blocks, a device never fills memory, a directory, a socket, an
oversized file, text that is not UTF-8, nesting deeper than the parser's bound and a key given twice are each one
line naming the file — never a traceback, never a wait."""

from __future__ import annotations

import importlib
import json
import os
import socket
import threading
from pathlib import Path

import pytest
from conftest import one_line_message
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dssp_core.errors import DSSPError
from dssp_core.files import SETTINGS_LIMIT, read_input_bytes
from dssp_core.schema import JSON_MAX_DEPTH, Settings, all_schemas, json_depth, parse_json, read_json_object

SETTINGS = {
    "deadline": None,
    "derandomize": True,
    "database": None,
    "max_examples": 40,
    "suppress_health_check": [HealthCheck.function_scoped_fixture],
}
# Every module that defines a settings file kind (their Settings subclasses register when imported).
SCHEMA_MODULES = (
    "hardware.safety",
    "dssp_data.observation",
    "dssp_data.pointcloud.extrinsics",
    "hardware.recorder",
    "hardware.camera.profiles",
    "hardware.calibration.charuco",
    "dssp_deploy.manifest",
)


def returns_within(call, seconds: float = 20.0):
    """``call()``'s outcome, as ("ok", value) or ("error", exception); ("blocked", None) when it has not returned
    within ``seconds`` (the thread is left behind as a daemon; the caller unblocks it)."""
    box: list = []

    def run():
        try:
            box.append(("ok", call()))
        except BaseException as exc:  # noqa: BLE001 - the outcome is the test's subject
            box.append(("error", exc))

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    thread.join(seconds)
    return box[0] if box else ("blocked", None)


def unblock(fifo: Path) -> None:
    """Open the FIFO's other end once, so a reader blocked on it (a failing test) returns."""
    try:
        fd = os.open(fifo, os.O_WRONLY | os.O_NONBLOCK)
    except OSError:
        return
    os.close(fd)


def one_line(outcome, *fragments) -> str:
    """The refusal an ``outcome`` (kind, value) holds: a DSSPError whose :func:`conftest.one_line_message` holds each
    of ``fragments`` and is short."""
    kind, value = outcome
    assert kind == "error", f"expected a refusal, got {kind}: {value!r}"
    assert isinstance(value, DSSPError), f"{type(value).__name__}: {value}"
    message = one_line_message(value, *fragments)
    assert len(message) < 400, message
    return message


def make(kind: str, folder: Path, payload: bytes = b"{}") -> Path:
    """A path of the given kind in ``folder``."""
    path = folder / f"input-{kind}"
    if kind == "fifo":
        os.mkfifo(path)
    elif kind == "directory":
        path.mkdir()
    elif kind == "socket":
        path = Path("/tmp") / f"dssp-{os.getpid()}-{threading.get_ident()}.sock"  # AF_UNIX paths are short
        with socket.socket(socket.AF_UNIX) as sock:
            sock.bind(str(path))
    elif kind == "link-to-device":
        path.symlink_to("/dev/zero")
    elif kind == "device":
        return Path("/dev/zero")
    else:
        path.write_bytes(payload)
    return path


NOT_FILES = {
    "fifo": "FIFO",
    "directory": "directory",
    "socket": "socket",
    "device": "device",
    "link-to-device": "device",
}


@settings(**SETTINGS)
@given(kind=st.sampled_from(sorted(NOT_FILES) + ["file"]), size=st.integers(0, 3000), limit=st.integers(1, 2000))
def test_the_read_helper_reads_regular_files_within_the_limit_and_refuses_the_rest(tmp_path_factory, kind, size, limit):
    folder = tmp_path_factory.mktemp("input")
    payload = os.urandom(size)
    path = make(kind, folder, payload)
    try:
        outcome = returns_within(lambda: read_input_bytes(path, f"input {path}", limit=limit))
        if kind in NOT_FILES:
            one_line(outcome, str(path), NOT_FILES[kind], "regular file")
        elif size > limit:
            one_line(outcome, str(path), f"{size} bytes", str(limit))
        else:
            assert outcome == ("ok", payload)
    finally:
        if kind == "fifo":
            unblock(path)
        if kind == "socket":
            path.unlink()


def test_a_missing_or_unreadable_file_is_one_line(tmp_path):
    one_line(returns_within(lambda: read_input_bytes(tmp_path / "none.json", "settings file")), "does not exist")
    if os.geteuid() != 0:  # root reads whatever the mode says
        path = tmp_path / "secret.json"
        path.write_text("{}")
        path.chmod(0)
        one_line(returns_within(lambda: read_input_bytes(path, "settings file")), "cannot be read")


@settings(**SETTINGS)
@given(depth=st.integers(1, 3 * JSON_MAX_DEPTH), kind=st.sampled_from("[{"), noise=st.text(max_size=20))
def test_nesting_is_bounded_before_the_parser_recurses(depth, kind, noise):
    """json_depth counts brackets outside strings only; parse_json refuses nesting beyond JSON_MAX_DEPTH with a
    ValueError (read_json_object turns it into one line), never a RecursionError."""
    text = json.dumps(noise)
    for _ in range(depth):
        text = f"[{text}]" if kind == "[" else f'{{"k": {text}}}'
    assert json_depth(text) == min(depth, JSON_MAX_DEPTH + 1)
    if depth > JSON_MAX_DEPTH:
        with pytest.raises(ValueError, match="nested more than"):
            parse_json(text)
    else:
        assert parse_json(text) is not None


def test_a_deep_file_far_beyond_the_recursion_limit_is_one_line(tmp_path):
    path = tmp_path / "deep.json"
    path.write_text("[" * 200_000 + "]" * 200_000)
    one_line(returns_within(lambda: read_json_object(path, "safety")), "nested more than")


def schemas() -> list[type[Settings]]:
    for module in SCHEMA_MODULES:
        importlib.import_module(module)
    found = all_schemas()
    assert len(found) >= 8, [c.__name__ for c in found]
    return found


HOSTILE = {
    "fifo": ("FIFO",),
    "device": ("device",),
    "directory": ("directory",),
    "large": ("bytes",),
    "not-utf8": ("not a text file",),
    "deep": ("nested more than",),
    "twice": ("twice",),
}


def hostile(kind: str, folder: Path) -> Path:
    if kind in ("fifo", "device", "directory"):
        return make(kind, folder)
    payload = {
        "large": b" " * (SETTINGS_LIMIT + 1) + b"{}",
        "not-utf8": b'{"a": "\xff"}',
        "deep": b"[" * 10_000 + b"]" * 10_000,
        "twice": b'{"a": 1, "a": 2}',
    }[kind]
    return make("file", folder, payload)


@pytest.mark.parametrize("kind", sorted(HOSTILE))
def test_every_settings_file_kind_refuses_what_is_not_a_settings_file(tmp_path, kind):
    """Settings.load of every schema (safety, point cloud, calibration, thresholds, board, camera profiles, the
    model's facts, ...) reads through the one helper: each hostile input is one line naming the file."""
    path = hostile(kind, tmp_path)
    try:
        for cls in schemas():
            one_line(returns_within(lambda: cls.load(path)), str(path), *HOSTILE[kind])
    finally:
        if kind == "fifo":
            unblock(path)


LOADERS = {
    "extrinsics": ("dssp_data.pointcloud.extrinsics", "load_extrinsics"),
    "wrist extrinsics": ("dssp_data.pointcloud.extrinsics", "load_camera_to_gripper"),
    "calibration poses": ("hardware.calibration.pose_plan", "load_poses"),
    "board": ("hardware.calibration.charuco", "load_board"),
}


@pytest.mark.parametrize("name", sorted(LOADERS))
@pytest.mark.parametrize("kind", ["fifo", "device", "deep", "twice"])
def test_every_file_loader_of_the_robot_commands_refuses_what_is_not_its_file(tmp_path, name, kind):
    module, function = LOADERS[name]
    load = getattr(importlib.import_module(module), function)
    path = hostile(kind, tmp_path)
    try:
        one_line(returns_within(lambda: load(path)), str(path), *HOSTILE[kind])
    finally:
        if kind == "fifo":
            unblock(path)

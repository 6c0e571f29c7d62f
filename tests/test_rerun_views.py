"""Rerun views of runs, recordings and datasets: saved with ``--rerun-save``, read back with Rerun's own loader,
checked entity by entity and tick by tick against the run's own log; the queue that keeps logging off the
control loop drops (and counts) instead of blocking; a missing rerun-sdk, and every bad --rerun / --rerun-save
value, is one line before anything opens; a recording is never written through a link."""

import os
import signal
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
from conftest import one_error_line
from rrd import read_rrd, text_rows

from dssp_core.errors import ConfigError
from dssp_data.arm_kinematics import ARM_VALUES, flange_pose, tool_points
from dssp_data.data_cli import main as data_main
from dssp_data.rerun_views import height_colors, open_views
from dssp_sim.teleop import record_main
from hardware.cli.run import main as run_main
from hardware.run_log import read_ticks


def test_dssp_run_views_match_its_tick_log(arm_export, tmp_path, capsys):
    rrd, log_dir = tmp_path / "run.rrd", tmp_path / "log"
    code = run_main(
        [
            "--model",
            str(arm_export),
            "--camera",
            "tabletop",
            "--can",
            "sim",
            "--max-steps",
            "30",
            "--log-dir",
            str(log_dir),
            "--seed",
            "0",
            "--threads",
            "1",
            "--quiet",
            "--rerun-save",
            str(rrd),
        ]
    )
    out = capsys.readouterr().out
    assert code == 0, out
    assert "rerun views: 30 ticks logged, 0 dropped; saved to" in out and not rrd.with_name("run.rrd.partial").exists()
    ticks, static, components = read_rrd(rrd)
    log = read_ticks(log_dir)
    assert ticks["safety/held"] == list(range(30))  # one step of the timeline per control tick
    assert ticks["latency/tick"] == list(range(30))
    assert ticks["world/cloud"] == [t["tick"] for t in log if t["cloud_index"] is not None]
    assert ticks["joints/arm0/state"] == [t["tick"] for t in log if t["state"] is not None]
    assert ticks["joints/arm0/command"] == [t["tick"] for t in log if t["command"] is not None]
    assert ticks["world/arm0/chunk"] == [
        t["tick"] for t in log if t.get("chunk_ms") is not None
    ]  # a ghost per new chunk
    assert ticks["world/arm0/chunk"] and ticks["world/camera/depth"] == list(range(30))
    assert {"world/camera", "world/camera/depth", "world"} <= static
    assert "Pinhole:image_from_camera" in components["world/camera/depth"]
    assert "DepthImage:buffer" in components["world/camera/depth"]
    assert {"Points3D:positions", "Points3D:colors"} <= components["world/cloud"]


def test_a_recording_and_its_dataset_in_rerun(tmp_path, capsys):
    data, rec_rrd, view_rrd = tmp_path / "rec.zarr", tmp_path / "rec.rrd", tmp_path / "view.rrd"
    assert (
        record_main(
            [
                "--out",
                str(data),
                "--auto",
                "--episodes",
                "1",
                "--max-steps",
                "12",
                "--quiet",
                "--rerun-save",
                str(rec_rrd),
            ]
        )
        == 0
    )
    assert "rerun views: 12 steps logged, 0 dropped" in capsys.readouterr().out
    ticks, static, _ = read_rrd(rec_rrd)
    assert ticks["world/cloud"] == ticks["world/camera/depth"] == ticks["joints/arm0/state"] == list(range(12))
    assert "world/camera" in static and text_rows(rec_rrd, "episode") == ["episode started"]

    assert data_main(["view", str(data), "--episode", "0", "--rerun-save", str(view_rrd)]) == 0
    assert "rerun views: 12 steps logged" in capsys.readouterr().out
    ticks, static, _ = read_rrd(view_rrd)
    for entity in (
        "world/cloud",
        "world/camera/depth",
        "joints/arm0/state",
        "joints/arm0/command",
        "world/arm0/chunk",
        "world/arm0/gripper",
    ):
        assert ticks[entity] == list(range(12)), entity
    assert "world/camera" in static and text_rows(view_rrd, "episode") == ["rec.zarr episode 0: 12 steps"]
    # the PNGs stay the default; a saved view is never replaced
    assert data_main(["view", str(data), "--episode", "0", "--rerun-save", str(view_rrd)]) == 2
    assert "view.rrd exists" in one_error_line(capsys.readouterr().err)


def test_a_full_queue_drops_and_counts_instead_of_blocking(tmp_path):
    views = open_views("test", None, tmp_path / "q.rrd", queue_size=2)
    gate = threading.Event()
    original = views._log_tick
    views._log_tick = lambda *a, **k: (gate.wait(10), original(*a, **k))  # a worker stuck behind a slow sink
    results = [views.tick(t, held=False) for t in range(6)]
    assert results[:2] == [True, True] and not all(results) and views.dropped == results.count(False)
    gate.set()
    counts = views.close()
    assert counts["logged"] + counts["dropped"] == 6 and counts["dropped"] >= 3
    ticks, _, _ = read_rrd(tmp_path / "q.rrd")
    assert len(ticks["safety/held"]) == counts["logged"]


def test_flags_are_checked_before_anything_runs(arm_export, tmp_path, capsys, monkeypatch):
    (tmp_path / "old.rrd").write_bytes(b"")
    assert run_main(["--model", str(arm_export), "--max-steps", "1", "--rerun-save", str(tmp_path / "old.rrd")]) == 2
    assert "old.rrd exists; choose a new file name" in one_error_line(capsys.readouterr().err)
    assert run_main(["--model", str(arm_export), "--max-steps", "1", "--rerun-save", str(tmp_path / "x.txt")]) == 2
    assert "a Rerun recording is a .rrd file" in one_error_line(capsys.readouterr().err)
    monkeypatch.setitem(sys.modules, "rerun", None)  # rerun-sdk not installed
    assert (
        run_main(
            [
                "--model",
                str(arm_export),
                "--max-steps",
                "1",
                "--log-dir",
                str(tmp_path / "log"),
                "--rerun-save",
                str(tmp_path / "new.rrd"),
            ]
        )
        == 2
    )
    line = one_error_line(capsys.readouterr().err)
    assert "--rerun-save needs rerun-sdk" in line and 'pip install -e ".[viz]"' in line
    assert not (tmp_path / "log").exists()  # nothing ran
    with pytest.raises(ConfigError, match="--rerun needs rerun-sdk"):
        open_views("test", "spawn", None)


def test_the_ghost_follows_the_simulated_gripper():
    """tool_points (the viewers' forward kinematics) lands on the MuJoCo model's tool centre point."""
    import mujoco

    from dssp_sim.env import PiperEnv  # first: it picks MuJoCo's headless renderer
    from hardware.piper.limits import JOINT_LOWER, JOINT_UPPER

    env = PiperEnv("tap", seed=0)
    m, d, arm = env.model, env.data, env.arm
    rng = np.random.default_rng(1)
    qs = np.array([[*rng.uniform(JOINT_LOWER, JOINT_UPPER), 0.5] for _ in range(4)])
    points = tool_points(np.concatenate([qs, qs], axis=1))  # two arms, each in its own base frame
    assert points.shape == (4, 2, 3) and np.allclose(points[:, 0], points[:, 1])
    for q, p in zip(qs, points[:, 0]):
        d.qpos[arm.qpos] = q[:6]
        mujoco.mj_kinematics(m, d)
        np.testing.assert_allclose(d.site_xpos[arm.tcp_site], p, atol=1e-9)
        assert np.allclose(flange_pose(q[:6])[:3, 3], d.xpos[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "link6")])
    with pytest.raises(ValueError, match=f"not {ARM_VALUES} per arm"):
        tool_points(np.zeros(6))


def test_height_colours_run_from_the_lowest_to_the_highest_point():
    colors = height_colors(np.array([0.0, 0.5, 1.0]))
    assert colors.dtype == np.uint8 and colors.shape == (3, 3)
    assert tuple(colors[0]) == (68, 1, 84) and tuple(colors[2]) == (253, 231, 37) and tuple(colors[1]) == (33, 145, 140)


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _group_alive(pgid: int) -> bool:
    """Whether a process of group ``pgid`` still runs (a zombie, exited and not yet reaped, does not)."""
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:  # it ended while the folder was read
            continue
        if fields[0] != "Z" and int(fields[2]) == pgid:
            return True
    return False


def test_rerun_url_connects_to_a_running_viewer_or_server(tmp_path):
    """--rerun URL streams to a Rerun server (here the rerun CLI, headless, saving what it receives)."""
    import shutil
    import subprocess

    from waiting import wait_for

    received, port = tmp_path / "received.rrd", _free_port()
    server = subprocess.Popen(  # its own process group: the rerun script runs the viewer binary as its child
        [shutil.which("rerun") or "rerun", "--port", str(port), "--save", str(received)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    try:
        wait_for(lambda: received.exists() or server.poll() is not None, timeout=30)
        views = open_views("test", f"rerun+http://127.0.0.1:{port}/proxy", None)
        for t in range(5):
            views.tick(t, held=t == 3, state=np.zeros(7))
        assert views.close() == {"logged": 5, "dropped": 0}

        def all_received():
            try:
                return len(read_rrd(received)[0].get("safety/held", [])) == 5
            except ValueError:  # nothing arrived yet
                return False
            except RuntimeError as exc:  # the server is mid-way through writing a message: read again
                if "exceeds file size" not in str(exc):
                    raise
                return False

        wait_for(all_received, timeout=30, what="the 5 ticks at the server")
    finally:
        os.killpg(server.pid, signal.SIGTERM)  # the script and the binary it started: none outlives the test
        server.wait(10)
    wait_for(lambda: not _group_alive(server.pid), timeout=10, what="the rerun server's processes to end", poll=0.05)
    ticks, _, _ = read_rrd(received)
    assert ticks["safety/held"] == ticks["joints/arm0/state"] == list(range(5))


def test_a_crash_leaves_a_readable_partial_recording(tmp_path):
    """A process that dies mid-run leaves PATH.rrd.partial, readable up to the ticks it flushed."""
    import subprocess
    import textwrap

    save = tmp_path / "crash.rrd"
    code = textwrap.dedent(f"""
        import os, numpy as np
        from pathlib import Path
        from dssp_data.rerun_views import open_views
        views = open_views("crash", None, Path({str(save)!r}))
        for t in range(8):
            views.tick(t, held=False, state=np.zeros(7))
        while views.logged < 8:
            pass
        views.stream.flush()
        os._exit(9)  # no close(): a crash
        """)
    assert subprocess.run([sys.executable, "-c", code], timeout=60).returncode == 9
    assert not save.exists() and save.with_name("crash.rrd.partial").is_file()
    ticks, _, _ = read_rrd(save.with_name("crash.rrd.partial"))
    assert ticks["safety/held"] == list(range(8))


# ------------------------------------------------------------------------------------------------ bad flags
BAD_VIEWS = {  # flag values → the words of their one line
    "not a URL": (["--rerun", "not a url"], "is not a Rerun viewer's address"),
    "a bad port": (["--rerun", "rerun+http://127.0.0.1:notaport/proxy"], "is not a Rerun viewer's address"),
    "no such folder": (["--rerun-save", "{tmp}/missing/v.rrd"], "does not exist; create it first"),
    "a folder": (["--rerun-save", "{tmp}/folder.rrd"], "is a folder; give a new .rrd file name"),
    "an existing file": (["--rerun-save", "{tmp}/old.rrd"], "exists; choose a new file name"),
    "a planted link": (["--rerun-save", "{tmp}/new.rrd"], "new.rrd.partial is a symbolic link"),
}


def _dssp_run(tmp, flags):
    return run_main(["--model", str(tmp / "model"), "--log-dir", str(tmp / "log"), "--quiet", *flags])


def _dssp_record(tmp, flags):
    return record_main(["--out", str(tmp / "rec.zarr"), "--auto", "--episodes", "1", "--quiet", *flags])


def _dssp_sim_eval(tmp, flags):
    from dssp_sim.sim_cli import main as sim_main

    return sim_main(
        ["eval", "--model", str(tmp / "model"), "--task", "tap", "--episodes", "1", "--no-progress", *flags]
    )


def _dssp_data_view(tmp, flags):
    return data_main(["view", str(tmp / "data" / "d.zarr"), "--episode", "0", *flags])


@pytest.mark.parametrize(
    "command",
    [_dssp_run, _dssp_record, _dssp_sim_eval, _dssp_data_view],
    ids=["dssp-run", "dssp-record", "dssp-sim eval", "dssp-data view"],
)
def test_bad_view_flags_are_one_line_before_anything_opens(command, tmp_path, capsys):
    """Each command that takes --rerun / --rerun-save refuses a bad value with one line (exit 2) before it opens
    anything: nothing is written, the target of a planted link is untouched."""
    from conftest import snapshot, write_arm_dataset

    (tmp_path / "data").mkdir()
    write_arm_dataset(tmp_path / "data" / "d.zarr", n_episodes=1, steps=4)
    (tmp_path / "folder.rrd").mkdir()
    (tmp_path / "old.rrd").write_bytes(b"an earlier recording")
    (tmp_path / "victim.txt").write_text("not yours")
    (tmp_path / "new.rrd.partial").symlink_to(tmp_path / "victim.txt")
    before = snapshot(tmp_path)
    for name, (flags, words) in BAD_VIEWS.items():
        flags = [f.format(tmp=tmp_path) for f in flags]
        assert command(tmp_path, flags) == 2, name
        line = one_error_line(capsys.readouterr().err)
        assert words in line and line.startswith("error: "), (name, line)
        assert snapshot(tmp_path) == before, name


def test_a_recording_is_never_written_through_a_link(tmp_path, monkeypatch):
    """The partial file is created new (a link planted after the check is refused), and the recording is written
    through its own descriptor: a name swapped for a link meanwhile gets nothing, and is not put in place."""
    victim = tmp_path / "victim.txt"
    victim.write_text("not yours")
    save = tmp_path / "late.rrd"
    with monkeypatch.context() as patch:
        patch.setattr("dssp_data.rerun_views.check_views", lambda connect, save: None)  # the link comes after the check
        save.with_name("late.rrd.partial").symlink_to(victim)
        with pytest.raises(ConfigError, match="appeared meanwhile"):
            open_views("test", None, save)
    assert victim.read_text() == "not yours" and not save.exists()

    save = tmp_path / "swapped.rrd"
    views = open_views("test", None, save)
    partial = save.with_name("swapped.rrd.partial")
    moved = tmp_path / "moved.rrd"
    partial.rename(moved)
    partial.symlink_to(victim)
    for t in range(4):
        views.tick(t, held=False, state=np.zeros(7))
    with pytest.raises(ConfigError, match="was moved or replaced"):
        views.close()
    assert victim.read_text() == "not yours" and not save.exists()
    ticks, _, _ = read_rrd(moved)  # every tick went to the file the views created
    assert ticks["safety/held"] == list(range(4))

"""No command destroys data it did not create: every command that writes checks its outputs first.

(a) a foreign folder, a folder holding a zarr dataset, a file or a recorded dataset at a command's output
    path: exit 2, one ``error:`` line, and not one byte changed on disk — with and without ``--force``;
(b) a previous output of the same command: refused without ``--force``, replaced with it (the expensive
    work is replaced by a stand-in: these tests check where the command writes, not what);
(c) the guard itself (``dssp_core.output_guard``), property-based over random folder contents.
The refusals come before any work: nothing here trains, collects or evaluates.
"""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from conftest import ROOT, one_error_line, snapshot
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from dssp_core.errors import DSSPError, OutputError
from dssp_core.files import replace_dir
from dssp_core.output_guard import (
    MARKER,
    NEW,
    OWN,
    OutputDir,
    OutputKind,
    check_append,
    check_output,
    check_output_file,
    claim_dir,
    write_output_file,
    write_output_text,
)
from dssp_data.attributes import zarr_attrs, zarr_generator
from dssp_data.dataset_layout import Episode
from dssp_data.replay_buffer import ReplayBuffer
from dssp_data.replay_buffer_writer import write_replay_buffer
from dssp_deploy.profile import main as profile_main
from dssp_sim.collect import SIM_DATASET
from dssp_sim.sim_cli import main as sim_main
from dssp_train.cli.synth import SYNTH_DATASET
from dssp_train.cli.synth import main as synth_main
from dssp_train.cli.train import RUN_DIR
from dssp_train.cli.train import main as train_main
from export.to_onnx import main as export_main
from studies.sim_study import REPORT_NAME
from studies.sim_study import main as study_main


# ------------------------------------------------------------------------------------------------ helpers
def load_script(name: str):
    spec = importlib.util.spec_from_file_location(f"bench_{name}", ROOT / "benchmarks" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def tiny_episodes(n: int) -> list[Episode]:
    rng = np.random.default_rng(0)
    return [
        Episode(
            point_cloud=rng.random((3, 4, 3), dtype=np.float32),
            state=rng.random((3, 2), dtype=np.float32),
            action=rng.random((3, 2), dtype=np.float32),
        )
        for _ in range(n)
    ]


def write_dataset(path: Path, generator: str, n: int = 2, **attrs) -> Path:
    write_replay_buffer(path, tiny_episodes(n), attrs={"generator": generator, **attrs})
    return path


# Foreign things at an output path: a folder with a file, a folder holding a zarr dataset (``mkdir -p
# D/rec.zarr``), a file, and a recorded dataset (what ``dssp-record`` writes).
def folder_with_file(path: Path) -> None:
    path.mkdir()
    (path / "notes.txt").write_text("keep me")


def folder_with_zarr(path: Path) -> None:
    (path / "rec.zarr").mkdir(parents=True)
    (path / "rec.zarr" / ".zgroup").write_text('{"zarr_format": 2}')


def a_file(path: Path) -> None:
    path.write_text("not yours")


def recorded_dataset(path: Path) -> None:
    write_dataset(path, "dssp-record", n=28)


FOLDERS = {"folder": folder_with_file, "zarr-inside": folder_with_zarr}
DIR_FOREIGN = {**FOLDERS, "file": a_file, "recorded": recorded_dataset}


def flag(force: bool) -> list[str]:
    return ["--force"] if force else []


# Each command with its output at ``out`` (a missing model or dataset elsewhere: the refusal must come first).
def demo(out, force):
    from studies.demo import main as demo_main

    return demo_main(["--out", str(out), "--steps", "1", "--demos", "1", "--episodes", "1", *flag(force)])


def synth(out, force, episodes=2):
    return synth_main(["--out", str(out), "--episodes", str(episodes), "--points", "24", *flag(force)])


def train(out, force):
    return train_main(
        ["--data", str(out.parent / "missing.zarr"), "--out", str(out), "--steps", "1", "--no-progress", *flag(force)]
    )


def collect(out, force):
    assert not force  # collect appends; it has no --force
    return sim_main(["collect", "--task", "tap", "--episodes", "1", "--out", str(out), "--no-progress"])


def eval_strips(out, force):
    return sim_main(
        [
            "eval",
            "--model",
            str(out.parent / "missing_model"),
            "--task",
            "tap",
            "--episodes",
            "1",
            "--strips",
            str(out),
            "--no-progress",
            *flag(force),
        ]
    )


def eval_json(out, force):
    return sim_main(
        [
            "eval",
            "--model",
            str(out.parent / "missing_model"),
            "--task",
            "tap",
            "--episodes",
            "1",
            "--json",
            str(out),
            "--no-progress",
            *flag(force),
        ]
    )


def profile_json(out, force):
    return profile_main([str(out.parent / "missing_model"), "--quick", "--json", str(out), *flag(force)])


def profile_plot(out, force):
    return profile_main([str(out.parent / "missing_model"), "--quick", "--plot", str(out), *flag(force)])


def study_work(out, force):
    return study_main(["--work", str(out), "--report", str(out.parent / "report"), "--quick", *flag(force)])


def study_report(out, force):  # out: REPORT_NAME.md in the report folder
    return study_main(["--work", str(out.parent.parent / "work"), "--report", str(out.parent), "--quick", *flag(force)])


def export(out, force):
    return export_main([str(out.parent / "missing_run"), "-o", str(out), *flag(force)])


def export_report(out, force):
    return load_script("export_report").main(
        ["--out", str(out), "--preset", "tiny", "--verify-steps", "1", "--repeats", "1", *flag(force)]
    )


def export_report_json(out, force):
    return load_script("export_report").main(
        ["--out", str(out.parent / "report_dir"), "--json", str(out), "--preset", "tiny", *flag(force)]
    )


def pointcloud_json(out, force):
    return load_script("pointcloud_time").main(["--repeats", "1", "--warmup", "0", "--json", str(out), *flag(force)])


def train_step_json(out, force):
    return load_script("train_step_time").main(["--repeats", "1", "--json", str(out), *flag(force)])


DIR_COMMANDS = {
    "dssp-demo --out": (demo, True),
    "dssp-synth --out": (synth, True),
    "dssp-train --out": (train, True),
    "dssp-sim collect --out": (collect, False),
    "dssp-sim eval --strips": (eval_strips, True),
    "sim_study --work": (study_work, True),
    "export.to_onnx -o": (export, True),
    "export_report.py --out": (export_report, True),
}
FILE_COMMANDS = {
    "dssp-sim eval --json": eval_json,
    "dssp-profile --json": profile_json,
    "dssp-profile --plot": profile_plot,
    "sim_study --report": study_report,
    "export_report.py --json": export_report_json,
    "pointcloud_time.py --json": pointcloud_json,
    "train_step_time.py --json": train_step_json,
}


def refused_unchanged(capsys, root: Path, run, out: Path, force: bool) -> str:
    before = snapshot(root)
    assert run(out, force) == 2
    line = one_error_line(capsys.readouterr().err)
    assert snapshot(root) == before, line
    return line


# ---------------------------------------------------------------------- (a) foreign outputs are refused
@pytest.mark.parametrize("command", DIR_COMMANDS)
def test_a_foreign_output_folder_is_never_touched(command, tmp_path, capsys):
    run, has_force = DIR_COMMANDS[command]
    for name, make in DIR_FOREIGN.items():
        root = tmp_path / name
        root.mkdir()
        out = root / "target"
        make(out)
        for force in (False, True) if has_force else (False,):
            line = refused_unchanged(capsys, root, run, out, force)
            assert str(out) in line and "choose another" in line, line
            assert "nothing is deleted" in line, line


@pytest.mark.parametrize("command", FILE_COMMANDS)
def test_a_folder_where_a_file_goes_is_never_touched(command, tmp_path, capsys):
    run = FILE_COMMANDS[command]
    name = f"{REPORT_NAME}.md" if command == "sim_study --report" else "out.json"
    for case, make in FOLDERS.items():
        root = tmp_path / case
        (root / "report").mkdir(parents=True)
        out = root / "report" / name
        make(out)
        for force in (False, True):
            line = refused_unchanged(capsys, root, run, out, force)
            assert "is not a file" in line and "nothing is deleted" in line, line


@pytest.mark.parametrize("command", FILE_COMMANDS)
def test_an_existing_file_is_replaced_only_with_force(command, tmp_path, capsys):
    run = FILE_COMMANDS[command]
    (tmp_path / "report").mkdir()
    out = tmp_path / "report" / (f"{REPORT_NAME}.md" if command == "sim_study --report" else "out.json")
    out.write_text("an earlier result")
    line = refused_unchanged(capsys, tmp_path, run, out, False)
    assert "pass --force" in line, line


def test_synth_never_replaces_a_recorded_dataset(tmp_path, capsys):
    """The reported loss: 28 recorded episodes replaced by 2 synthetic ones."""
    out = tmp_path / "rec.zarr"
    recorded_dataset(out)
    for force in (False, True):
        line = refused_unchanged(capsys, tmp_path, synth, out, force)
        assert "is not a synthetic dataset made by dssp-synth" in line
    assert ReplayBuffer.load(out).n_episodes == 28


def test_collect_appends_only_to_its_own_dataset_of_the_same_task(tmp_path, capsys):
    out = tmp_path / "swap.zarr"
    write_dataset(out, "dssp_sim.collect", task="swap")
    line = refused_unchanged(capsys, tmp_path, collect, out, False)
    assert "holds 'swap' demonstrations, not 'tap'" in line
    assert check_append(out, kind=SIM_DATASET) == OWN  # appending to it is fine: it is the task that differs


# ------------------------------------------------------------- (b) a previous output of the same command
def replaced(capsys, root: Path, run, out: Path) -> None:
    """``out`` holds the command's previous output: refused without --force, replaced with it."""
    line = refused_unchanged(capsys, root, run, out, False)
    assert "already holds" in line or "exists;" in line, line
    assert "pass --force" in line, line
    before = snapshot(out) if out.is_dir() else out.read_bytes()
    assert run(out, True) == 0
    capsys.readouterr()
    assert (snapshot(out) if out.is_dir() else out.read_bytes()) != before
    assert not [p for p in root.rglob("*") if ".partial-" in p.name or ".old-" in p.name]


def test_synth_replaces_its_own_dataset_with_force(tmp_path, capsys):
    out = tmp_path / "synth.zarr"
    assert synth(out, False) == 0
    capsys.readouterr()
    replaced(capsys, tmp_path, lambda o, f: synth(o, f, episodes=3), out)
    assert ReplayBuffer.load(out).n_episodes == 3


def test_the_demo_replaces_its_own_output_with_force_and_restores_it_on_failure(tmp_path, capsys, monkeypatch):
    import studies.demo as module

    calls = []

    def fake(out, steps, demos, episodes, seed):
        calls.append(out)
        (out / "tap.zarr").mkdir()
        (out / "results.json").write_text(json.dumps({"run": len(calls)}))
        return {}

    monkeypatch.setattr(module, "_run_demo", fake)
    out = tmp_path / "demo"
    assert demo(out, False) == 0 and (out / MARKER).is_file()
    replaced(capsys, tmp_path, demo, out)
    assert json.loads((out / "results.json").read_text()) == {"run": 2}

    def failing(out, *args):
        (out / "results.json").write_text("half")
        raise DSSPError("training dssp failed (exit 1)")

    monkeypatch.setattr(module, "_run_demo", failing)
    before = snapshot(tmp_path)
    assert demo(out, True) == 2
    assert "training dssp failed" in one_error_line(capsys.readouterr().err)
    assert snapshot(tmp_path) == before  # the previous demo is back, untouched


def test_train_replaces_a_previous_run_only_with_force(tmp_path, capsys, monkeypatch):
    import dssp_train.cli.train as cli

    runs = []

    def fake(args, out, make_config):
        runs.append(1)
        (out / "config.json").write_text(json.dumps({"model": {}, "train": {}, "run": len(runs)}))
        (out / "model.safetensors").write_bytes(b"weights %d" % len(runs))
        (out / "checkpoint").mkdir()
        return {"step": 1}

    monkeypatch.setattr(cli, "_train", fake)
    out = tmp_path / "run"
    assert train(out, False) == 0
    capsys.readouterr()
    line = refused_unchanged(capsys, tmp_path, train, out, False)
    assert "continue it with --resume, pass --force to replace it or choose another --out" in line
    replaced(capsys, tmp_path, train, out)
    assert json.loads((out / "config.json").read_text())["run"] == 2

    def interrupted(args, out, make_config):
        (out / "config.json").write_text("{}")
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "_train", interrupted)
    before = snapshot(tmp_path)
    assert train(out, True) == 130
    capsys.readouterr()
    assert snapshot(tmp_path) == before  # the previous run is back
    # a run folder with anything else in it is not the run's to delete
    (out / "notes.txt").write_text("mine")
    assert "nothing is deleted" in refused_unchanged(capsys, tmp_path, train, out, True)


def test_eval_replaces_its_strips_and_json_only_with_force(tmp_path, capsys, monkeypatch):
    import dssp_sim.evaluate as evaluate
    from dssp_sim.evaluate import EvalResult

    runs = []

    class Fake:
        env = SimpleNamespace(close=lambda: None)

        def __init__(self, model, task, n, **settings):
            self.model, self.task = model, task

        def run(self, strips_dir=None, progress=True, views=None):
            runs.append(1)
            (Path(strips_dir) / "tap_seed1.png").write_bytes(b"png %d" % len(runs))
            return EvalResult(str(self.model), self.task, state_token_noise=len(runs))

    monkeypatch.setattr(evaluate, "prepare_evaluation", Fake)

    def run(out, force):
        return sim_main(
            [
                "eval",
                "--model",
                "m",
                "--task",
                "tap",
                "--episodes",
                "1",
                "--strips",
                str(out),
                "--json",
                str(out.parent / "eval.json"),
                "--no-progress",
                *flag(force),
            ]
        )

    out = tmp_path / "strips"
    assert run(out, False) == 0
    replaced(capsys, tmp_path, run, out)
    assert json.loads((tmp_path / "eval.json").read_text())["state_token_noise"] == 2
    assert sorted(p.name for p in out.iterdir()) == [MARKER, "tap_seed1.png"]


def test_profile_replaces_its_files_only_with_force(tmp_path, capsys, monkeypatch):
    import dssp_deploy.profile as profile

    runs = []

    def fake(*args):
        runs.append(1)
        return {
            "history_sweep": [{"length": 1, "p50_ms": 1.0}, {"length": 10, "p50_ms": 2.0 + len(runs)}],
            "torch": {},
            "samples_ms": {"history_step": [1.0, 2.0], "denoiser_chunk": [3.0, 4.0]},
        }

    monkeypatch.setattr(profile, "run_profile", fake)
    monkeypatch.setattr(profile, "markdown", lambda report: "table")

    def run(out, force):
        return profile_main(["model", "--json", str(out), "--plot", str(out.with_suffix(".png")), *flag(force)])

    out = tmp_path / "profile.json"
    assert run(out, False) == 0
    png = (tmp_path / "profile.png").read_bytes()
    assert png.startswith(b"\x89PNG")
    replaced(capsys, tmp_path, run, out)
    assert (tmp_path / "profile.png").read_bytes() != png


def test_study_continues_its_work_and_replaces_its_report_only_with_force(tmp_path, capsys, monkeypatch):
    import studies.sim_study as sim_study

    calls: list[list[str]] = []

    def fake_run_and_keep(work, record, stage_list, workers, what, seconds=False):
        """As if the study were stopped after its first evaluation: that one is kept in the record."""
        calls.append([s.name for s in stage_list])
        first = next(s for s in stage_list if s.outputs)
        (record / "evals").mkdir(parents=True, exist_ok=True)
        (record / first.outputs[0]).write_text(
            json.dumps({"successes": len(calls) % 2, "n": 1, "failure_reasons": {}, "episodes": []})
        )

    monkeypatch.setattr(sim_study, "run_and_keep", fake_run_and_keep)
    work, report = tmp_path / "work", tmp_path / "report"

    def run(out, force):
        return study_main(["--work", str(work), "--report", str(out.parent), "--quick", *flag(force)])

    md = report / f"{REPORT_NAME}.md"
    assert run(md, False) == 0 and (work / MARKER).is_file()
    assert "train_tap_dssp_s0" in calls[0]
    capsys.readouterr()
    replaced(capsys, tmp_path, run, report / f"{REPORT_NAME}.json")
    # the refused run stopped before any stage; the forced one continued the work (what the first kept is not run again)
    assert len(calls) == 2 and calls[1] and "eval_tap_dssp_s0" in calls[0] and "eval_tap_dssp_s0" not in calls[1]
    assert (report / f"{REPORT_NAME}.png").read_bytes().startswith(b"\x89PNG")


def test_export_report_replaces_its_own_folder_only_with_force(tmp_path, capsys, monkeypatch):
    module = load_script("export_report")
    runs = []

    def fake_export(run_dir, model_dir, **kwargs):
        runs.append(1)
        model_dir.mkdir()
        (model_dir / "dssp_model.json").write_text(str(len(runs)))
        return {"model_dir": str(model_dir)}

    monkeypatch.setattr(module, "make_untrained_run", lambda name, run_dir, overrides=(): run_dir.mkdir() or run_dir)
    monkeypatch.setattr(module, "export_model", fake_export)
    monkeypatch.setattr(module, "format_summary", lambda summary: "")
    monkeypatch.setattr(module, "latency", lambda *args: {})

    def run(out, force):
        return module.main(["--out", str(out), "--preset", "tiny", *flag(force)])

    out = tmp_path / "report"
    assert run(out, False) == 0
    assert sorted(p.name for p in out.iterdir()) == [MARKER, "report.json", "tiny_model", "tiny_run"]
    replaced(capsys, tmp_path, run, out)
    assert (out / "tiny_model" / "dssp_model.json").read_text() == "2"


def test_benchmark_json_files_are_replaced_only_with_force(tmp_path, capsys, monkeypatch):
    out = tmp_path / "pointcloud.json"
    assert pointcloud_json(out, False) == 0
    replaced(capsys, tmp_path, pointcloud_json, out)

    module = load_script("train_step_time")
    monkeypatch.setattr(module, "train_step_fn", lambda *a: (lambda: None, f"step {a[0]}"))
    monkeypatch.setattr(module, "history_fwd_bwd_fn", lambda *a: (lambda: None, "history"))
    monkeypatch.setattr(module, "time_calls", lambda fn, n, warmup=0: [float(len(str(tmp_path)))])
    out = tmp_path / "train_step.json"
    assert module.main(["--json", str(out)]) == 0
    assert refused_unchanged(capsys, tmp_path, lambda o, f: module.main(["--json", str(o)]), out, False)
    assert module.main(["--json", str(out), "--force"]) == 0


# ----------------------------------------------------------------------------------------- (c) the guard
KIND = OutputKind("a test output", "test-cmd", entries=("a.json", "b", "*.png"))
NAMES = ["a.json", "b", "x.png", ".a.json.1234.tmp", ".b.partial-xy", "notes.txt", "c", ".hidden", MARKER]


def build(path: Path, names: list[str], dirs: set[str], marker: str | None) -> None:
    path.mkdir()
    for name in names:
        if name == MARKER:
            continue
        if name in dirs:
            (path / name).mkdir()
            (path / name / "inner").write_text(name)
        else:
            (path / name).write_text(name)
    if marker is not None:
        (path / MARKER).write_text(marker)


MARKERS = st.sampled_from(
    [
        None,
        json.dumps({"command": "test-cmd", "output": "a test output"}),
        json.dumps({"command": "other", "output": "a test output"}),
        "not json",
    ]
)


OWN_MARKER = json.dumps({"command": "test-cmd", "output": "a test output"})


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    names=st.lists(st.sampled_from(NAMES), unique=True),
    dirs=st.sets(st.sampled_from(NAMES)),
    marker=MARKERS,
    force=st.booleans(),
    staged=st.booleans(),
)
@example(names=["a.json", "x.png", ".b.partial-xy"], dirs={"b"}, marker=OWN_MARKER, force=True, staged=False)
@example(names=["a.json", "x.png"], dirs=set(), marker=OWN_MARKER, force=True, staged=True)
@example(names=["a.json", "notes.txt"], dirs=set(), marker=OWN_MARKER, force=True, staged=True)
@example(names=[], dirs=set(), marker="not json", force=False, staged=False)
def test_guard_replaces_only_its_own_folders(names, dirs, marker, force, staged):
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        out = root / "out"
        build(out, names, dirs, marker)
        content = [n for n in os.listdir(out) if n != MARKER]
        own_marker = marker is not None and "test-cmd" in marker
        expected = NEW if not content else OWN if own_marker and all(KIND.expected(n) for n in content) else "refused"
        before = snapshot(root)
        try:
            found = check_output(out, force=force, kind=KIND)
        except OutputError as exc:
            found = "refused"
            assert str(exc).count("\n") == 0
            assert ("pass --force" in str(exc)) == (expected == OWN and not force)
        assert found == (expected if expected != OWN or force else "refused")
        assert snapshot(root) == before
        if found == "refused":
            with pytest.raises(OutputError):
                with OutputDir(out, KIND, force=force, staged=staged):
                    pass
            assert snapshot(root) == before
            return
        with OutputDir(out, KIND, force=force, staged=staged) as target:
            (target.path / "a.json").write_text("new")
            target.commit()
        assert sorted(os.listdir(out)) == [MARKER, "a.json"] and (out / "a.json").read_text() == "new"
        assert KIND.owns(out) and os.listdir(root) == ["out"]


def test_file_rules(tmp_path):
    new = tmp_path / "sub" / "r.json"
    assert check_output_file(new, force=False) == new
    write_output_text(new, "1", force=False)
    with pytest.raises(OutputError, match="exists; pass --force to replace it or choose another --json"):
        write_output_text(new, "2", force=False, flag="--json")
    write_output_text(new, "2", force=True)
    assert new.read_text() == "2" and os.listdir(new.parent) == ["r.json"]
    gif = tmp_path / "a.gif"  # a writer that takes the format from the name sees the suffix it needs
    write_output_file(gif, lambda tmp: Path(tmp).write_text(Path(tmp).suffix), force=False, suffix=".tmp.gif")
    assert gif.read_text() == ".gif" and sorted(os.listdir(tmp_path)) == ["a.gif", "sub"]
    (tmp_path / "d").mkdir()
    (tmp_path / "link").symlink_to(new)
    for path in (tmp_path / "d", tmp_path / "link"):
        with pytest.raises(OutputError, match="is not a file"):
            check_output_file(path, force=True)


def test_output_dir_rolls_back_and_removes_only_what_it_created(tmp_path):
    out = tmp_path / "a" / "b" / "out"
    with pytest.raises(RuntimeError):
        with OutputDir(out, KIND) as target:
            (target.path / "a.json").write_text("x")
            raise RuntimeError
    assert os.listdir(tmp_path) == []  # the staging folder and the parents it made are gone
    for staged in (True, False):
        with OutputDir(out, KIND, staged=staged) as target:
            (target.path / "a.json").write_text("old")
            target.commit()
        before = snapshot(tmp_path)
        with pytest.raises(RuntimeError):
            with OutputDir(out, KIND, force=True, staged=staged) as target:
                (target.path / "a.json").write_text("new")
                raise RuntimeError
        assert snapshot(tmp_path) == before
        claim = out.parent / "claimed"
        claim_dir(claim, kind=KIND)
        with pytest.raises(OutputError, match="already holds a test output from test-cmd; choose another --out"):
            (claim / "b").mkdir()
            claim_dir(claim, kind=KIND)
        assert claim_dir(claim, kind=KIND, resume=True) == claim
        shutil.rmtree(out.parent)
    # keep_partial: an unfinished output that replaced nothing stays (a run to --resume) ...
    with pytest.raises(KeyboardInterrupt):
        with OutputDir(out, KIND, staged=False, keep_partial=True) as target:
            (target.path / "a.json").write_text("partial")
            raise KeyboardInterrupt
    assert (out / "a.json").read_text() == "partial"
    # ... but not an empty one, and an empty folder that was there stays an empty folder
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(KeyboardInterrupt):
        with OutputDir(empty, KIND, staged=False, keep_partial=True):
            raise KeyboardInterrupt
    assert empty.is_dir() and os.listdir(empty) == []


def test_replace_dir_puts_the_old_folder_back_when_the_swap_fails(tmp_path, monkeypatch):
    old, new = tmp_path / "out", tmp_path / ".out.partial"
    old.mkdir()
    (old / "f").write_text("old")
    new.mkdir()
    real = os.replace

    def fail_second(src, dst):
        if Path(src) == new:
            raise OSError("disk full")
        real(src, dst)

    monkeypatch.setattr(os, "replace", fail_second)
    with pytest.raises(OSError):
        replace_dir(new, old)
    assert (old / "f").read_text() == "old" and sorted(os.listdir(tmp_path)) == [".out.partial", "out"]


def test_a_previous_output_that_cannot_be_moved_aside_stays(tmp_path, monkeypatch):
    out = claim_dir(tmp_path / "out", kind=KIND)
    (out / "a.json").write_text("old")
    before = snapshot(tmp_path)

    def refuse(src, dst):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(os, "replace", refuse)
    with pytest.raises(OutputError, match="cannot write to .*Permission denied"):
        with OutputDir(out, KIND, force=True, staged=False):
            pass
    assert snapshot(tmp_path) == before


def test_known_kinds_are_recognised_by_their_own_signature(tmp_path):
    synth_zarr = write_dataset(tmp_path / "s.zarr", "dssp_train.data.synthetic")
    assert zarr_generator(synth_zarr) == "dssp_train.data.synthetic" and SYNTH_DATASET.owns(synth_zarr)
    v3 = tmp_path / "v3"
    write_replay_buffer(v3, tiny_episodes(1), attrs={"generator": "x"}, zarr_format=3)
    assert zarr_attrs(v3)["generator"] == "x" and not SYNTH_DATASET.owns(v3)
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text(json.dumps({"model": {}, "train": {}}))
    (run / ".checkpoint.old").mkdir()
    assert RUN_DIR.owns(run)
    (run / "data.csv").write_text("x")
    assert not RUN_DIR.owns(run)


def test_the_guard_imports_neither_torch_nor_zarr():
    code = "import sys; import dssp_core.output_guard; assert 'torch' not in sys.modules and 'zarr' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT)


def test_two_writers_making_the_same_parent_folder_both_go_on(tmp_path, monkeypatch):
    """Two commands side by side (two trainings into runs/a and runs/b) create runs/ at the same moment: the
    one whose mkdir comes second finds it made, goes on, and does not count it as its own."""
    from dssp_core.files import make_dirs

    real = Path.mkdir

    def the_other_writer_was_first(self, *args, **kwargs):
        if self.name == "runs":
            real(self)  # the other process, just before this one
        return real(self, *args, **kwargs)

    monkeypatch.setattr(Path, "mkdir", the_other_writer_was_first)
    created = make_dirs(tmp_path / "runs" / "a")
    assert created == [tmp_path / "runs" / "a"] and (tmp_path / "runs" / "a").is_dir()
    (tmp_path / "file").write_text("x")
    monkeypatch.setattr(Path, "mkdir", lambda self, *a, **k: (_ for _ in ()).throw(FileExistsError(17, "File exists")))
    with pytest.raises(OutputError, match="File exists"):  # what is there is not a folder: still refused
        make_dirs(tmp_path / "new" / "b")


# ---------------------------------------------------------------------- the robot's commands and dssp-data view
def run_log(out, force):
    from hardware.cli.run import main as run_main

    return run_main(["--model", "no-such-model", "--log-dir", str(out), "--quiet"])


def record_out(out, force):
    from dssp_sim.teleop import record_main

    return record_main(["--out", str(out), "--quiet", "--auto", "--episodes", "1"])


@pytest.mark.parametrize("run", [run_log, record_out], ids=["dssp-run --log-dir", "dssp-record --out"])
def test_the_robot_commands_never_touch_a_foreign_output(run, tmp_path, capsys):
    foreign = {**FOLDERS, "file": a_file, "synthetic": lambda p: write_dataset(p, "dssp_train.data.synthetic")}
    for name, make in foreign.items():
        root = tmp_path / name
        root.mkdir()
        out = root / "target"
        make(out)
        line = refused_unchanged(capsys, root, run, out, False)
        assert str(out) in line and "nothing is deleted" in line, line


def test_dssp_run_never_reuses_a_log(tmp_path, capsys):
    from dssp_core.output_guard import claim_dir
    from hardware.cli.run import RUN_LOG

    out = claim_dir(tmp_path / "log", kind=RUN_LOG, flag="--log-dir")
    (out / "run.json").write_text("{}")
    line = refused_unchanged(capsys, tmp_path, run_log, out, False)
    assert "already holds an episode log" in line and "choose another --log-dir" in line, line


def test_dssp_data_view_replaces_its_pictures_only_with_force(tmp_path, capsys):
    from dssp_data.data_cli import main as data_main

    data = write_dataset(tmp_path / "d.zarr", "dssp-record")
    pictures = tmp_path / "pictures"
    pictures.mkdir()
    (pictures / "d_ep0_trajectories.png").write_text("someone's picture")
    before = snapshot(tmp_path)
    assert data_main(["view", str(data), "--episode", "0", "--out", str(pictures)]) == 2
    line = one_error_line(capsys.readouterr().err)
    assert "d_ep0_trajectories.png exists; pass --force" in line, line
    assert snapshot(tmp_path) == before  # checked before drawing: not even the clouds picture was written
    assert data_main(["view", str(data), "--episode", "0", "--out", str(pictures), "--force"]) == 0
    assert (pictures / "d_ep0_trajectories.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert sorted(p.name for p in pictures.iterdir()) == ["d_ep0_clouds.png", "d_ep0_trajectories.png"]


# ---------------------------------------------------------------------- staging, interruptions, where outputs go
def test_staging_is_removed_on_any_exit_with_the_parents_it_made(tmp_path):
    from dssp_core.staging import Staging

    out = tmp_path / "a" / "b" / "out.zarr"
    with pytest.raises(KeyboardInterrupt):
        with Staging() as staging:
            tmp = staging.make(staging.reserve(out))
            (tmp / "data").mkdir()
            staging.make(tmp.with_name(tmp.name + ".can"))
            raise KeyboardInterrupt
    assert os.listdir(tmp_path) == []
    (tmp_path / "keep").mkdir()
    before = snapshot(tmp_path)
    with pytest.raises(OutputError, match="is a file, not a folder; choose another --out"):
        with Staging() as staging:
            (tmp_path / "keep" / "f").write_text("x")
            before = snapshot(tmp_path)
            staging.reserve(tmp_path / "keep" / "f" / "out.zarr")
    assert snapshot(tmp_path) == before
    with Staging() as staging:
        tmp = staging.make(staging.reserve(out))
        (tmp / "x").write_text("new")
        staging.commit([(tmp, out)])
    assert os.listdir(out) == ["x"] and sorted(os.listdir(out.parent)) == ["out.zarr"]


def test_only_stale_staging_folders_of_the_same_output_are_swept(tmp_path):
    from dssp_core.staging import Staging, sweep_stale

    out = tmp_path / "m.zarr"
    stale = [
        ".m.zarr.tmp-0123abcd",
        ".m.zarr.partial-89abcdef",
        "..m.zarr.tmp-0123abcd.tmp-4567cdef",
        ".m.zarr.tmp-0123abcd.can",
    ]
    kept = [
        ".m.zarr.old-0123abcd",
        ".m.zarr.tmp-nothex00",
        ".m.zarr.tmp-0123abc",
        "..m.zarr.tmp-0123abcd",
        ".x.zarr.tmp-0123abcd",
        ".m.zarr.tmp-0123abcd.can.bak",
        "m.zarr.tmp-0123abcd",
    ]
    for name in stale + kept:
        (tmp_path / name).mkdir()
        (tmp_path / name / "chunk").write_text(name)
    (tmp_path / ".m.zarr.tmp-fedcba98").write_text("a file")
    os.symlink(tmp_path / kept[0], tmp_path / ".m.zarr.tmp-fedcba99")
    with Staging() as live:  # a staging folder of a live writer (this process) is left alone
        held = live.make(live.reserve(out))
        assert sorted(p.name for p in sweep_stale(out)) == []  # reserve swept the stale ones already
        assert held.is_dir()
        for name in stale:
            (tmp_path / name).mkdir()
        assert sorted(p.name for p in sweep_stale(out)) == sorted(stale)
        assert held.is_dir()
    remaining = sorted(os.listdir(tmp_path))
    assert remaining == sorted(kept + [".m.zarr.tmp-fedcba98", ".m.zarr.tmp-fedcba99"])
    assert all((tmp_path / name / "chunk").read_text() == name for name in kept)


def test_replace_dirs_puts_everything_back_when_a_rename_fails(tmp_path, monkeypatch):
    from dssp_core.files import replace_dirs

    for name in ("out", "out.can", "new", "new.can"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "f").write_text(name)
    before = snapshot(tmp_path)
    real = os.replace

    def fail_second_new(src, dst):
        if Path(src).name == "new.can":
            raise OSError("disk full")
        real(src, dst)

    monkeypatch.setattr(os, "replace", fail_second_new)
    with pytest.raises(OSError):
        replace_dirs([(tmp_path / "new", tmp_path / "out"), (tmp_path / "new.can", tmp_path / "out.can")])
    assert snapshot(tmp_path) == before
    monkeypatch.setattr(os, "replace", real)
    replace_dirs([(tmp_path / "new", tmp_path / "out"), (None, tmp_path / "out.can")])
    assert sorted(os.listdir(tmp_path)) == ["new.can", "out"] and (tmp_path / "out" / "f").read_text() == "new"


def test_ctrl_c_is_held_back_inside_interrupts_deferred():
    import signal

    from dssp_core.staging import interrupts_deferred

    done = []
    with pytest.raises(KeyboardInterrupt):
        with interrupts_deferred():
            os.kill(os.getpid(), signal.SIGINT)
            done.append("after the signal")
    assert done == ["after the signal"]
    with interrupts_deferred(reraise=False):
        os.kill(os.getpid(), signal.SIGINT)
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_a_ctrl_c_stops_a_commit_before_its_renames_and_comes_too_late_during_them(tmp_path, monkeypatch):
    """Never "interrupted" with the outputs in place: a Ctrl-C while the output is checked again stops the commit
    (nothing in place, the staging removed); one during the renames lets the commit finish and raises nothing."""
    import signal

    from dssp_core import staging as staging_module
    from dssp_core.staging import Staging

    def ctrl_c():
        os.kill(os.getpid(), signal.SIGINT)

    out = tmp_path / "out"
    with pytest.raises(KeyboardInterrupt):
        with Staging() as staging:
            tmp = staging.make(staging.reserve(out))
            (tmp / "f").write_text("new")
            staging.commit([(tmp, out)], check=ctrl_c)
    assert os.listdir(tmp_path) == []

    real = staging_module.replace_dirs
    monkeypatch.setattr(staging_module, "replace_dirs", lambda moves: (ctrl_c(), real(moves)))
    with Staging() as staging:
        tmp = staging.make(staging.reserve(out))
        (tmp / "f").write_text("new")
        staging.commit([(tmp, out)], check=lambda: None)
    assert os.listdir(tmp_path) == ["out"] and (out / "f").read_text() == "new"
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_a_command_interrupted_after_its_outputs_were_in_place_names_them(tmp_path, capsys):
    from dssp_core.cli_runner import run_cli
    from dssp_core.staging import Staging

    out = tmp_path / "out"

    def writes_then_is_interrupted():
        with Staging() as staging:
            tmp = staging.make(staging.reserve(out))
            (tmp / "f").write_text("new")
            staging.commit([(tmp, out)])
        raise KeyboardInterrupt  # a Ctrl-C while the command prints its summary

    def is_interrupted():
        raise KeyboardInterrupt

    assert run_cli(writes_then_is_interrupted) == 130
    assert capsys.readouterr().err.strip() == f"interrupted after writing {out} (complete)"
    assert (out / "f").read_text() == "new"
    assert run_cli(is_interrupted) == 130  # an earlier command's outputs are not this one's
    assert capsys.readouterr().err.strip() == "interrupted"


def test_datasets_made_by_dssp_data_are_recognised_with_their_can_logs(tmp_path):
    from dssp_data.edit import DATA_DATASET

    for generator in (
        "dssp-data merge",
        "dssp-data split",
        "dssp-data convert",
        "dssp-data convert (RoboTwin raw HDF5)",
    ):
        path = write_dataset(tmp_path / f"{generator}.zarr", generator)
        assert DATA_DATASET.owns(path) and check_output(path, force=True, kind=DATA_DATASET) == OWN
    for generator in ("dssp-record", "dssp_train.data.synthetic", "dssp_sim.collect", "dssp-data"):
        path = write_dataset(tmp_path / f"other-{generator}.zarr", generator)
        assert not DATA_DATASET.owns(path)
        with pytest.raises(OutputError, match="is not a dataset made by dssp-data merge, split or convert"):
            check_output(path, force=True, kind=DATA_DATASET)
    old_merge = write_dataset(tmp_path / "old.zarr", "dssp_train.data.synthetic", merged_from=[{"path": "a"}])
    assert not SYNTH_DATASET.owns(old_merge)  # an older merge copied its input's generator: never replaced

    own = write_dataset(tmp_path / "own.zarr", "dssp-data merge")
    logs = tmp_path / "own.zarr.can"
    logs.mkdir()
    (logs / "episode_000000.can0.blf").write_bytes(b"log")
    assert check_output(own, force=True, kind=DATA_DATASET) == OWN
    (logs / ".recording.lock").write_text("pid 1")
    with pytest.raises(OutputError, match=r"own.zarr.can holds files .* \(nothing is deleted\)"):
        check_output(own, force=True, kind=DATA_DATASET)
    lone = tmp_path / "lone.zarr.can"
    lone.mkdir()
    assert check_output(tmp_path / "lone.zarr", force=False, kind=DATA_DATASET) == NEW  # empty: nothing to lose
    (lone / "episode_000000.can0.blf").write_bytes(b"log")
    with pytest.raises(OutputError, match="lone.zarr.can exists without lone.zarr"):
        check_output(tmp_path / "lone.zarr", force=True, kind=DATA_DATASET)


def test_paths_under_a_file_and_outputs_inside_inputs_are_one_line(tmp_path):
    from dssp_core.files import make_dirs
    from dssp_core.output_guard import check_not_inside

    a_file = tmp_path / "f"
    a_file.write_text("x")
    before = snapshot(tmp_path)
    for check in (
        lambda: check_output_file(a_file / "r.json", force=True),
        lambda: check_output(a_file / "sub" / "out", force=True, kind=KIND),
        lambda: make_dirs(a_file / "sub"),
        lambda: make_dirs(a_file),
        lambda: write_output_text(a_file / "r.json", "x", force=True),
        lambda: check_not_inside(tmp_path / "in" / "x", [tmp_path / "in"]),
        lambda: check_not_inside(tmp_path / "in", [tmp_path / "in" / "."]),
        lambda: check_not_inside(tmp_path, [tmp_path / "in"]),
    ):
        with pytest.raises(OutputError) as info:
            check()
        assert "\n" not in str(info.value) and "choose" in str(info.value)
    assert snapshot(tmp_path) == before
    check_not_inside(tmp_path, [tmp_path / "in"], contains=False)  # pictures beside a dataset are fine
    assert make_dirs(tmp_path / "a" / "b") == [tmp_path / "a", tmp_path / "a" / "b"]


@settings(
    deadline=None,
    derandomize=True,
    database=None,
    max_examples=30,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(length=st.integers(1, 400), depth=st.integers(0, 2), kind=st.sampled_from(["file", "folder"]))
def test_a_name_the_file_system_cannot_take_is_one_line_before_any_work(tmp_path, length, depth, kind):
    """Every output check measures the names against the file system's limit, with the longest name a write puts
    beside the output (a staging folder): a name that passes can be written with it, one that does not is one
    OutputError line — never an OSError from the check itself, nor a failure only at the end of the work."""
    from dssp_core.files import LONGEST_SIBLING

    root = Path(tempfile.mkdtemp(dir=tmp_path))  # one folder per example
    path = root.joinpath(*(["f" * length] * depth), "o" * length)
    kind_of = OutputKind("a test output", "test", entries=("*.txt",))
    try:
        if kind == "file":
            check_output_file(path, force=False, flag="--out")
        else:
            check_output(path, force=False, kind=kind_of, flag="--out")
    except OutputError as exc:
        assert "\n" not in str(exc) and "is longer than the" in str(exc) and "choose a shorter --out" in str(exc)
        assert length + len(LONGEST_SIBLING.format(name="")) > os.pathconf(tmp_path, "PC_NAME_MAX")
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    (path.parent / LONGEST_SIBLING.format(name=path.name)).mkdir()

"""One writer per output: a second dssp-train, dssp-distill or export into an output another one is writing is
refused with one line (exit code 2) before it reads, moves or writes anything there."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

from conftest import FAST_EXPORT, SET_SMALL, one_error_line, snapshot

from dssp_core.staging import WriterLock, writer_lock_path
from dssp_train.cli.distill import main as distill_main
from dssp_train.cli.train import main as train_main
from dssp_train.training.train_log import read_log
from dssp_train.training.trainer import Trainer
from export.to_onnx import main as export_main


def held_by_me(line: str, out: Path, what: str, flag: str) -> None:
    assert line == (
        f"error: {out} is being written by pid {os.getpid()} on {os.uname().nodename}: one writer per {what} "
        f"at a time; wait for it to finish or choose another {flag}"
    ), line


def test_a_second_dssp_train_into_a_run_being_trained_is_refused(data, tmp_path, capsys, monkeypatch):
    """While the first run trains (past its first checkpoint), a --resume, a --force and a plain second run into
    the same directory are each refused and change nothing; the first then completes as if alone."""
    out = tmp_path / "run"
    first = ["--data", str(data), "--out", str(out), "--steps", "4", "--no-progress", *SET_SMALL]
    seconds = {
        "resume": ["--data", str(data), "--out", str(out), "--resume", "--no-progress"],
        "force": ["--data", str(data), "--out", str(out), "--steps", "2", "--force", "--no-progress", *SET_SMALL],
        "new": ["--data", str(data), "--out", str(out), "--steps", "2", "--no-progress", *SET_SMALL],
    }
    real_step, results = Trainer.train_step, {}

    def step(trainer):
        if trainer.step == 3 and not results:  # the checkpoint of step 2 is on disk, the log has 3 steps
            capsys.readouterr()
            before = snapshot(out)
            for name, argv in seconds.items():
                code = train_main(argv)
                results[name] = (code, capsys.readouterr(), snapshot(out) == before)
        return real_step(trainer)

    monkeypatch.setattr(Trainer, "train_step", step)
    assert train_main(first) == 0
    assert set(results) == set(seconds)
    for name, (code, captured, unchanged) in results.items():
        assert code == 2, (name, captured.err)
        held_by_me(one_error_line(captured.err), out, "run directory", "--out")
        assert captured.out == "" and unchanged, name
    assert [r["step"] for r in read_log(out / "log.jsonl") if r["kind"] == "train"] == [1, 2, 3, 4]
    assert json.loads((out / "checkpoint" / "trainer_state.json").read_text())["step"] == 4
    assert not writer_lock_path(out).exists()  # let go once the run ended


def test_a_second_dssp_train_process_is_refused(trained, data, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(trained, run)
    before = snapshot(run)
    with WriterLock(run, what="run directory"):
        done = subprocess.run(
            [
                sys.executable,
                "-m",
                "dssp_train.cli.train",
                "--data",
                str(data),
                "--out",
                str(run),
                "--resume",
                "--steps",
                "4",
                "--no-progress",
            ],
            capture_output=True,
            text=True,
            timeout=300,
            env={**os.environ, "OMP_NUM_THREADS": "1"},
        )
    assert done.returncode == 2, done.stderr
    line = one_error_line(done.stderr)
    assert (
        line.startswith(f"error: {run} is being written by pid {os.getpid()} ")
        and "one writer per run directory" in line
    )
    assert done.stdout == "" and snapshot(run) == before


def test_a_second_dssp_distill_is_refused(trained, tmp_path, capsys):
    out = tmp_path / "student"
    shutil.copytree(trained, out)  # a previous run there, which --force would replace
    argv = [
        "--teacher",
        str(trained),
        "--steps",
        "1",
        "--out",
        str(out),
        "--force",
        "--train-steps",
        "2",
        "--no-progress",
    ]
    before = snapshot(out)
    with WriterLock(out, what="run directory"):
        assert distill_main(argv) == 2
        captured = capsys.readouterr()
    held_by_me(one_error_line(captured.err), out, "run directory", "--out")
    assert captured.out == "" and snapshot(out) == before
    # Once the first writer is gone, the same command replaces it: the refusal was the lock's.
    assert distill_main(argv) == 0
    assert json.loads((out / "config.json").read_text())["distill"]["teacher"] == str(trained.resolve())


def test_a_second_export_is_refused(trained, tmp_path, capsys):
    model = tmp_path / "model"
    assert export_main([str(trained), "-o", str(model), *FAST_EXPORT]) == 0
    capsys.readouterr()
    before = snapshot(tmp_path)
    with WriterLock(model, what="model directory", flag="-o"):
        assert export_main([str(trained), "-o", str(model), "--force", *FAST_EXPORT]) == 2
        captured = capsys.readouterr()
        lock = writer_lock_path(model).name
        assert {k: v for k, v in snapshot(tmp_path).items() if k != lock} == before  # no staging folder either
    held_by_me(one_error_line(captured.err), model, "model directory", "-o")
    assert captured.out == ""
    assert snapshot(tmp_path) == before
    assert export_main([str(trained), "-o", str(model), "--force", *FAST_EXPORT]) == 0

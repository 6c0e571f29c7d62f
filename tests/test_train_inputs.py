"""Bad input to dssp-train, dssp-params, dssp-synth: one line naming what the user typed, exit
code 2, nothing written; --resume only continues a run as it was; SIGTERM and Ctrl-C say what was kept."""

import json
import os
import re
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from conftest import SET_SMALL, SMALL, refusal, snapshot, write_arm_dataset
from waiting import wait_for

from dssp_train.cli.params import main as params_main
from dssp_train.cli.synth import main as synth_main
from dssp_train.cli.train import main as train_main
from dssp_train.config import apply_overrides, load_preset
from dssp_train.data.synthetic import write_tap_count_dataset
from dssp_train.model.policy import DSSPPolicy
from dssp_train.training import memory
from dssp_train.training.train_log import read_log
from dssp_train.training.trainer import Trainer


def refused(capsys, main, argv) -> str:
    """Run ``main(argv)``: its :func:`conftest.refusal` (exit code 2, nothing on stdout, one error line), the line
    returned without "error: "."""
    code = main([str(a) for a in argv])
    return refusal((code, *capsys.readouterr()))[len("error: ") :]


def copy_of(run: Path, tmp_path: Path) -> Path:
    dst = tmp_path / "run"
    shutil.copytree(run, dst)
    return dst


# ------------------------------------------------------------------ 1. the control rate
def test_control_rate_that_contradicts_the_dataset_is_refused(data, tmp_path, capsys):
    out = tmp_path / "run"
    line = refused(
        capsys, train_main, ["--data", data, "--out", out, "--control-rate", "20", "--no-progress", *SET_SMALL]
    )
    assert line == (
        f"--control-rate 20 Hz contradicts the 10 Hz that {data} records; "
        "drop --control-rate (the recorded rate is used)"
    )
    assert not out.exists()


def test_control_rate_equal_to_the_dataset_is_accepted(data, tmp_path, capsys):
    out = tmp_path / "run"
    assert (
        train_main(
            [
                "--data",
                str(data),
                "--out",
                str(out),
                "--control-rate",
                "10",
                "--steps",
                "1",
                "--no-progress",
                *SET_SMALL,
            ]
        )
        == 0
    )
    assert "--control-rate" not in capsys.readouterr().err  # no rate warning (the budget and holdout lines only)
    assert json.loads((out / "config.json").read_text())["control_rate_hz"] == 10.0


@pytest.mark.parametrize("value", ["0", "-5", "nan", "2000"])
def test_control_rate_out_of_range_names_the_flag(data, tmp_path, capsys, value):
    line = refused(capsys, train_main, ["--data", data, "--out", tmp_path / "run", "--control-rate", value, *SET_SMALL])
    assert line.startswith("--control-rate must be a ") and "[0.1, 1000] Hz" in line
    assert not (tmp_path / "run").exists()


# ------------------------------------------------------------------ 2. flags name themselves
FLAG_ERRORS = [
    (["--steps", "0"], "--steps must be an integer in [1, 100000000], got 0"),
    (["--batch-size", "0"], "--batch-size must be an integer in [1, 1000000], got 0"),
    (["--lr", "0"], "--lr must be a number in (0, 1], got 0.0"),
    (["--val-ratio", "1"], "--val-ratio must be a number in [0, 1), got 1.0"),
    (["--seed", "-1"], "--seed must be an integer in [0, 9223372036854775807], got -1"),
    (["--history-window", "-1"], "--history-window must be an integer in [0, 1000000], got -1"),
    (
        ["--no-history", "--no-recent-states"],
        "--no-recent-states: model.use_history and model.use_recent_states cannot "
        "both be off: the denoiser would see no observation",
    ),
]


@pytest.mark.parametrize("flags,message", FLAG_ERRORS, ids=[f[0][0] for f in FLAG_ERRORS])
def test_a_bad_flag_value_names_the_flag(data, tmp_path, capsys, flags, message):
    out = tmp_path / "run"
    assert refused(capsys, train_main, ["--data", data, "--out", out, "--no-progress", *flags]) == message
    assert not out.exists()


def test_a_bad_steps_on_resume_names_the_flag(trained, data, capsys):
    before = snapshot(trained)
    line = refused(capsys, train_main, ["--data", data, "--out", trained, "--resume", "--steps", "0"])
    assert line == "--steps must be an integer in [1, 100000000], got 0"
    assert snapshot(trained) == before


# ------------------------------------------------------------------ 3. --set: one source per field, config fields only
@pytest.mark.parametrize(
    "argv,message",
    [
        (["--steps", "2", "--set", "train.steps=6"], "--steps and --set train.steps=6 both set train.steps; keep one"),
        (
            ["--history-window", "3", "--set", "model.history_window=4"],
            "--history-window and --set model.history_window=4 both set model.history_window; keep one",
        ),
        (
            ["--no-history", "--set", "model.use_history=true"],
            "--no-history and --set model.use_history=true both set model.use_history; keep one",
        ),
        (
            ["--set", "train.lr=0.1", "--set", "train.lr=0.2"],
            "--set train.lr=0.1 and --set train.lr=0.2 both set train.lr; keep one",
        ),
    ],
)
def test_one_field_set_twice_is_refused(data, tmp_path, capsys, argv, message):
    assert refused(capsys, train_main, ["--data", data, "--out", tmp_path / "run", *argv]) == message
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize(
    "item", ["preset=robotwin", "dataset=/etc/passwd", "control_rate_hz=20", "model={}", "train=1"]
)
def test_set_takes_only_model_and_train_fields(data, tmp_path, capsys, item):
    line = refused(capsys, train_main, ["--data", data, "--out", tmp_path / "run", "--set", item])
    assert line == (
        f"--set {item}: --set takes model.* and train.* fields, one at a time (e.g. model.d_model=256); "
        "preset comes from --preset, dataset comes from --data, control_rate_hz comes from --control-rate"
    )
    assert not (tmp_path / "run").exists()


# ------------------------------------------------------------------ 4. n_points
def test_set_n_points_that_the_dataset_contradicts_is_refused(data, tmp_path, capsys):
    line = refused(capsys, train_main, ["--data", data, "--out", tmp_path / "run", "--set", "model.n_points=64"])
    assert line == f"--set model.n_points=64 but {data} has 24 points per cloud; drop the override to use the dataset's"
    assert not (tmp_path / "run").exists()


def test_the_presets_n_points_gives_way_to_the_dataset(data, trained):
    assert load_preset("tiny").model.n_points == 64
    assert json.loads((trained / "config.json").read_text())["model"]["n_points"] == 24


# ------------------------------------------------------------------ 5. --resume continues the same run on the same data
def test_resume_on_another_dataset_is_refused(trained, data, tmp_path, capsys):
    run = copy_of(trained, tmp_path)
    same_dims = write_tap_count_dataset(tmp_path / "other.zarr", 4, seed=1, n_points=24)
    other_dims = write_arm_dataset(tmp_path / "arm.zarr", n_episodes=2, steps=10, n_points=24)
    before = snapshot(run)
    for other in (same_dims, other_dims):
        line = refused(capsys, train_main, ["--data", other, "--out", run, "--resume", "--steps", "4", "--no-progress"])
        assert (
            line
            == f"{run} was trained on {os.path.realpath(data)}; --resume continues it on the same --data (got {other})"
        )
        assert "override" not in line
        assert snapshot(run) == before


def test_resume_on_a_dataset_changed_in_place_is_refused(tmp_path, capsys):
    path = write_tap_count_dataset(tmp_path / "grows.zarr", 4, seed=0, n_points=24)
    run = tmp_path / "run"
    assert train_main(["--data", str(path), "--out", str(run), "--steps", "2", "--no-progress", *SET_SMALL]) == 0
    capsys.readouterr()
    shutil.rmtree(path)
    write_tap_count_dataset(path, 6, seed=0, n_points=24)  # two episodes more, same path and dimensions
    before = snapshot(run)
    line = refused(capsys, train_main, ["--data", path, "--out", run, "--resume", "--steps", "4", "--no-progress"])
    assert line.startswith(
        f"{path} changed since {run} was trained on it (4 episodes, 160 steps then; 6 episodes, 240 steps now)"
    )
    assert snapshot(run) == before


def test_resume_through_another_path_to_the_same_dataset_keeps_the_config(trained, data, tmp_path, capsys):
    run = copy_of(trained, tmp_path)
    link = tmp_path / "link.zarr"
    link.symlink_to(data)
    before = json.loads((run / "config.json").read_text())
    assert train_main(["--data", str(link), "--out", str(run), "--resume", "--steps", "4", "--no-progress"]) == 0
    capsys.readouterr()
    after = json.loads((run / "config.json").read_text())
    assert after["train"].pop("steps") == 4 and before["train"].pop("steps") == 2
    assert after == before  # the dataset path, control rate and everything else as the run began
    assert json.loads((run / "checkpoint" / "trainer_state.json").read_text())["step"] == 4


@pytest.mark.parametrize("steps", ["1", "2"])
def test_resume_with_steps_not_past_the_checkpoint_is_refused(trained, data, tmp_path, capsys, steps):
    run = copy_of(trained, tmp_path)
    before = snapshot(run)
    line = refused(capsys, train_main, ["--data", data, "--out", run, "--resume", "--steps", steps, "--no-progress"])
    assert line == f"--steps must be larger than the checkpoint's step 2 to continue (got {steps})"
    assert snapshot(run) == before


def test_resume_with_a_contradicting_control_rate_is_refused(trained, data, tmp_path, capsys):
    run = copy_of(trained, tmp_path)
    line = refused(
        capsys, train_main, ["--data", data, "--out", run, "--resume", "--steps", "3", "--control-rate", "20"]
    )
    assert "--control-rate 20 Hz contradicts the 10 Hz" in line


def test_resume_may_record_a_control_rate_the_run_lacked(tmp_path, capsys):
    from dssp_data.replay_buffer_writer import write_replay_buffer
    from dssp_train.data.synthetic import make_tap_count_episodes

    path = tmp_path / "norate.zarr"
    write_replay_buffer(path, make_tap_count_episodes(3, seed=1, n_points=24))
    run = tmp_path / "run"
    assert train_main(["--data", str(path), "--out", str(run), "--steps", "2", "--no-progress", *SET_SMALL]) == 0
    assert "--control-rate" in capsys.readouterr().err
    assert (
        train_main(
            [
                "--data",
                str(path),
                "--out",
                str(run),
                "--resume",
                "--steps",
                "3",
                "--control-rate",
                "15",
                "--no-progress",
            ]
        )
        == 0
    )
    assert "--control-rate" not in capsys.readouterr().err
    assert json.loads((run / "config.json").read_text())["control_rate_hz"] == 15.0
    line = refused(
        capsys, train_main, ["--data", path, "--out", run, "--resume", "--steps", "4", "--control-rate", "30"]
    )
    assert line == "--control-rate 30 Hz contradicts the run's control rate of 15 Hz; drop --control-rate"


# ------------------------------------------------------------------ 6, 7. SIGTERM and Ctrl-C
def interrupt_at(monkeypatch, at: int) -> None:
    """Trainer.train_step raises KeyboardInterrupt once ``at`` steps are done."""
    real = Trainer.train_step

    def step(self):
        if self.step >= at:
            raise KeyboardInterrupt
        return real(self)

    monkeypatch.setattr(Trainer, "train_step", step)


def test_ctrl_c_after_a_checkpoint_says_where_it_is_and_how_to_continue(data, tmp_path, capsys, monkeypatch):
    out = tmp_path / "run"
    interrupt_at(monkeypatch, 3)
    assert train_main(["--data", str(data), "--out", str(out), "--steps", "6", "--no-progress", *SET_SMALL]) == 130
    monkeypatch.undo()
    err = capsys.readouterr().err.strip().splitlines()[-1]  # after the budget and holdout lines
    command = f"dssp-train --data {data} --out {out} --resume"
    assert (
        err == f"interrupted after step 3; the checkpoint of step 2 is in {out / 'checkpoint'}: continue with {command}"
    )
    # The advice works.
    assert train_main(command.split()[1:] + ["--no-progress"]) == 0
    assert [r["step"] for r in read_log(out / "log.jsonl") if r["kind"] == "train"] == [1, 2, 3, 4, 5, 6]


def test_ctrl_c_before_training_keeps_nothing(data, tmp_path, capsys, monkeypatch):
    from dssp_data.replay_buffer import ReplayBuffer

    def interrupted_load(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(ReplayBuffer, "load", interrupted_load)
    out = tmp_path / "run"
    assert train_main(["--data", str(data), "--out", str(out), "--no-progress", *SET_SMALL]) == 130
    assert capsys.readouterr().err.strip() == "interrupted before training began; nothing was kept"
    assert not out.exists()


def test_ctrl_c_before_the_first_step_says_so(data, tmp_path, capsys, monkeypatch):
    """Interrupted once the run is set up but before any step: not "after step 0", and nothing logged as trained."""
    out = tmp_path / "run"
    interrupt_at(monkeypatch, 0)
    assert train_main(["--data", str(data), "--out", str(out), "--steps", "4", "--no-progress", *SET_SMALL]) == 130
    captured = capsys.readouterr()
    assert captured.out == ""  # no summary
    assert captured.err.strip().splitlines()[-1] == (
        "interrupted before the first step: no checkpoint was kept; start the run over by adding --force"
    )
    assert read_log(out / "log.jsonl") == [] and not (out / "checkpoint").exists()


def test_ctrl_c_of_a_resume_before_its_first_step_changes_nothing(trained, data, tmp_path, capsys, monkeypatch):
    """A --resume interrupted before a step past the checkpoint: the message says where it stopped and repeats the
    --steps asked for (the run's config.json keeps its own until the next checkpoint); the run is as it was."""
    run = copy_of(trained, tmp_path)
    before = snapshot(run)
    interrupt_at(monkeypatch, 2)
    assert train_main(["--data", str(data), "--out", str(run), "--resume", "--steps", "4", "--no-progress"]) == 130
    monkeypatch.undo()
    command = f"dssp-train --data {data} --out {run} --resume --steps 4"
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        f"interrupted before any step past the checkpoint's step 2; the checkpoint of step 2 is in {run / 'checkpoint'}: "
        f"continue with {command}"
    )
    assert snapshot(run) == before
    assert train_main(command.split()[1:] + ["--no-progress"]) == 0
    assert [r["step"] for r in read_log(run / "log.jsonl") if r["kind"] == "train"] == [1, 2, 3, 4]


def test_ctrl_c_of_a_run_replacing_another_puts_the_other_back(trained, data, tmp_path, capsys, monkeypatch):
    run = copy_of(trained, tmp_path)
    before = snapshot(run)
    interrupt_at(monkeypatch, 1)
    assert (
        train_main(["--data", str(data), "--out", str(run), "--steps", "4", "--force", "--no-progress", *SET_SMALL])
        == 130
    )
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        f"interrupted after step 1; this run is discarded and the previous run in {run} is back as it was"
    )
    assert snapshot(run) == before


def test_sigterm_stops_like_ctrl_c_and_keeps_the_checkpoint(data, tmp_path):
    out = tmp_path / "run"
    argv = [
        "--data",
        str(data),
        "--out",
        str(out),
        "--steps",
        "100000",
        "--no-progress",
        *[a for item in SMALL if not item.startswith("train.val_every") for a in ("--set", item)],
        "--set",
        "train.val_every=100000",
    ]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONWARNINGS": "ignore"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "dssp_train.cli.train", *argv],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    try:

        def checkpointed() -> bool:
            assert proc.poll() is None, proc.communicate()
            return (out / "checkpoint" / "trainer_state.json").is_file()

        wait_for(checkpointed, timeout=240, what="a checkpoint", poll=0.2)
        proc.send_signal(signal.SIGTERM)
        stdout, stderr = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, stderr
    assert stdout == ""
    match = re.fullmatch(
        r"interrupted after step (\d+); the checkpoint of step (\d+) is in (.+): continue with "
        r"dssp-train --data (.+) --out (.+) --resume",
        stderr.strip().splitlines()[-1],
    )
    assert match, stderr
    stopped, saved = int(match[1]), int(match[2])
    assert saved % 2 == 0 and 2 <= saved <= stopped and match[3] == str(out / "checkpoint")
    assert (match[4], match[5]) == (str(data), str(out))
    assert json.loads((out / "checkpoint" / "trainer_state.json").read_text())["step"] == saved
    # It continues from there.
    assert (
        train_main(["--data", str(data), "--out", str(out), "--resume", "--steps", str(saved + 2), "--no-progress"])
        == 0
    )


def test_the_sigterm_handler_is_put_back(data, tmp_path, capsys):
    previous = signal.getsignal(signal.SIGTERM)
    refused(capsys, train_main, ["--data", data, "--out", tmp_path / "run", "--steps", "0"])
    assert signal.getsignal(signal.SIGTERM) is previous


# ------------------------------------------------------------------ 8. dssp-params
def test_params_state_dim_zero_names_the_flag(capsys):
    assert (
        refused(capsys, params_main, ["--preset", "tiny", "--state-dim", "0"])
        == "--state-dim must be an integer in [1, 4096], got 0"
    )
    assert refused(capsys, params_main, ["--preset", "tiny", "--set", "model.action_dim=0"]).startswith(
        "--set model.action_dim=0: counting parameters needs model.action_dim of at least 1"
    )


def test_params_counts_a_huge_model_without_allocating_it(capsys):
    assert params_main(["--preset", "tiny", "--set", "model.d_model=65536"]) == 0
    total = [line for line in capsys.readouterr().out.splitlines() if line.startswith("total")][0]
    count = int(total.split()[1].replace(",", ""))
    assert count > 100_000_000_000  # about 1 TB of float32: counted, not allocated
    config = apply_overrides(load_preset("tiny"), ["model.d_model=65536"])
    config.model.state_dim = config.model.action_dim = 14
    assert count == memory.parameter_count(config.model)


def test_params_meta_count_equals_the_real_model(capsys):
    assert params_main(["--preset", "tiny", "--state-dim", "3", "--action-dim", "5"]) == 0
    out = capsys.readouterr().out
    assert "S=3, A=5" in out
    config = load_preset("tiny")
    config.model.state_dim, config.model.action_dim = 3, 5
    total = [line for line in out.splitlines() if line.startswith("total")][0]
    assert int(total.split()[1].replace(",", "")) == sum(p.numel() for p in DSSPPolicy(config.model).parameters())


@pytest.mark.parametrize(
    "damage,message",
    [
        (lambda c: os.urandom(64) + b"\xff\xfe", "config.json is not a text file (damaged?)"),
        (
            lambda c: json.dumps({k: v for k, v in c.items() if k != "model"}).encode(),
            "config.json lacks its model section",
        ),
        (lambda c: b"[1, 2]", "config.json must hold a JSON object, got list"),
        (lambda c: json.dumps({**c, "model": {**c["model"], "state_dim": 0}}).encode(), "has model.state_dim=0"),
    ],
)
def test_params_on_a_damaged_run_config_is_one_line(trained, tmp_path, capsys, damage, message):
    run = copy_of(trained, tmp_path)
    config = json.loads((run / "config.json").read_text())
    (run / "config.json").write_bytes(damage(config))
    line = refused(capsys, params_main, ["--run", run])
    assert line.startswith(str(run / "config.json")) and message in line, line
    assert "restore the run's own config.json, or train the run again" in line


def test_params_run_refuses_dimension_flags_and_run_fields(trained, capsys):
    assert (
        refused(capsys, params_main, ["--run", trained, "--state-dim", "3"])
        == "--state-dim is for --preset; a run's dimensions come from its config.json (drop --state-dim)"
    )
    assert refused(capsys, params_main, ["--preset", "tiny", "--set", "preset=robotwin"]).startswith(
        "--set preset=robotwin: --set takes model.* and train.* fields"
    )


# ------------------------------------------------------------------ 9. dssp-synth
@pytest.mark.parametrize(
    "argv,message",
    [
        (["--seed", "-1"], "--seed must be an integer in [0, 9223372036854775807], got -1"),
        (["--points", "10000000"], "--points must be an integer in [24, 100000], got 10000000"),
        (["--points", "10"], "--points must be an integer in [24, 100000], got 10"),
        (["--episodes", "100000"], "--episodes must be an integer in [1, 10000], got 100000"),
        (["--episodes", "0"], "--episodes must be an integer in [1, 10000], got 0"),
        (
            ["--episodes", "10000", "--points", "10000"],
            "--episodes 10000 x --points 10000 make 48.0 GB of point clouds, "
            "more than the 2 GB the generator holds in memory; lower --episodes or --points",
        ),
    ],
)
def test_synth_bad_flags(tmp_path, capsys, argv, message):
    out = tmp_path / "d.zarr"
    assert refused(capsys, synth_main, ["--out", out, *argv]) == message
    assert not out.exists()


# ------------------------------------------------------------------ 10. memory
@pytest.fixture
def ram_24gb(monkeypatch):
    """A machine with 24 GB of RAM available (whatever this one has: a refusal must not depend on it)."""
    monkeypatch.setattr(memory, "available_bytes", lambda device: 24 * 10**9)


def test_a_step_that_cannot_fit_in_memory_is_refused(data, tmp_path, capsys, ram_24gb):
    line = refused(
        capsys,
        train_main,
        ["--data", data, "--out", tmp_path / "run", "--device", "cpu", "--set", "model.history_window=1000000"],
    )
    assert re.fullmatch(
        r"one training step needs about [\d.]+ [GT]B \([\d,]+ parameters with gradients, AdamW and EMA "
        r"state: [\d.]+ MB; activations for the longest episode, 40 steps: [\d.]+ [GT]B\) but only "
        r"24.0 GB is available in RAM; lower model.d_model, model.expand, model.d_state, "
        r"model.history_window or train.batch_size",
        line,
    ), line
    assert not (tmp_path / "run").exists()


def test_wide_layers_that_cannot_fit_are_refused(data, tmp_path, capsys, ram_24gb):
    line = refused(
        capsys,
        train_main,
        [
            "--data",
            data,
            "--out",
            tmp_path / "run",
            "--device",
            "cpu",
            "--set",
            "model.expand=16",
            "--set",
            "model.d_model=4096",
        ],
    )
    assert re.match(r"one training step needs about 1\d\d\.\d GB \(5,458,\d{3},\d{3} parameters", line), line
    assert "but only 24.0 GB is available in RAM" in line


def test_memory_estimate_parts():
    config = load_preset("tiny")
    m = config.model
    m.state_dim = m.action_dim = 2
    m.n_points = 32
    base = memory.estimate_step_memory(m, 4, 40)
    assert base.parameters == sum(p.numel() for p in DSSPPolicy(m).parameters())
    assert base.state_bytes == 20 * base.parameters
    # The history encoder's scan over T_h-step windows of each of the 40 steps: two tensors per layer plus two.
    windowed = apply_overrides(config, ["model.history_window=1000"]).model
    grown = memory.estimate_step_memory(windowed, 4, 40).activation_bytes - base.activation_bytes
    scan = 40 * 1000 * m.expand * m.d_model * m.d_state * 4
    window_copy = 40 * 1000 * m.d_model * 4
    full_history_scan = 40 * m.expand * m.d_model * m.d_state * 4
    assert grown == (2 * m.n_history_layers + 2) * (scan - full_history_scan) + window_copy
    assert memory.estimate_step_memory(m, 8, 40).activation_bytes > base.activation_bytes  # batch size counts
    assert memory.estimate_step_memory(m, 4, 400).activation_bytes > 5 * base.activation_bytes  # so does T


def test_memory_check_compares_with_what_is_available(monkeypatch):
    config = load_preset("tiny")
    config.model.state_dim = config.model.action_dim = 2
    need = memory.estimate_step_memory(config.model, config.train.batch_size, 40).total
    monkeypatch.setattr(memory, "available_bytes", lambda device: need)
    memory.check_memory(config, 40, torch.device("cpu"))
    monkeypatch.setattr(memory, "available_bytes", lambda device: need - 1)
    with pytest.raises(memory.ConfigError, match="is available in RAM"):
        memory.check_memory(config, 40, torch.device("cpu"))
    monkeypatch.setenv("LOCAL_WORLD_SIZE", "2")  # torchrun: the processes on one machine share it
    monkeypatch.setattr(memory, "available_bytes", lambda device: need + 1)
    with pytest.raises(memory.ConfigError, match="for each of 2 processes"):
        memory.check_memory(config, 40, torch.device("cpu"))
    monkeypatch.setattr(memory, "available_bytes", lambda device: None)  # unknown: not checked
    memory.check_memory(config, 40, torch.device("cpu"))


def test_available_memory_is_known_on_linux():
    if not Path("/proc/meminfo").is_file():
        pytest.skip("no /proc/meminfo")
    available = memory.available_bytes(torch.device("cpu"))
    assert available is not None and 0 < available < 2**50
    if not torch.cuda.is_available():
        assert memory.available_bytes(torch.device("cuda")) is None


MEASURE = """
import json, sys
import numpy as np, torch
from dssp_train.config import load_preset
from dssp_data.dataset_layout import Episode
from dssp_data.replay_buffer_writer import write_replay_buffer
from dssp_train.training.memory import estimate_step_memory
from dssp_train.training.trainer import Trainer

def resident(key):
    return next(int(line.split()[1]) * 1024 for line in open("/proc/self/status") if line.startswith(key + ":"))

torch.set_num_threads(1)
path, run = sys.argv[1:]
rng = np.random.default_rng(0)
f = lambda *shape: rng.normal(size=shape).astype(np.float32)
write_replay_buffer(path, [Episode(f(300, 256, 3), f(300, 7), f(300, 7)) for _ in range(3)], attrs={"control_rate_hz": 10.0})
config = load_preset("tiny")
config.train.val_every = config.train.save_every = 1000
trainer = Trainer(config, path, run, progress=False)
params = sum(p.numel() for p in trainer.policy.parameters())
held = resident("VmRSS")
open("/proc/self/clear_refs", "w").write("5")  # the peak (VmHWM) starts again from here
trainer.train_step()
peak = resident("VmHWM")
# Weights and the EMA copy were allocated before `held` was read: they are part of the step's need.
print(json.dumps({"need": peak - held + 8 * params,
                  "estimate": estimate_step_memory(trainer.config.model, config.train.batch_size, 300).total}))
"""


@pytest.mark.skipif(not Path("/proc/self/clear_refs").is_file(), reason="needs Linux /proc")
def test_the_memory_estimate_stays_below_a_measured_step(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-c", MEASURE, str(tmp_path / "d.zarr"), str(tmp_path / "run")],
        capture_output=True,
        text=True,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert 0.3 * result["need"] < result["estimate"] <= result["need"], result

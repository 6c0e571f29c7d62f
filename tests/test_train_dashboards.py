"""``dssp-train --log tensorboard|wandb``: the dashboards get what log.jsonl records (names, steps, values) and
the validation chunks as images, read back with TensorBoard's and W&B's own formats; a resumed run continues
them; a missing package or an unknown value is one error line before anything is trained."""

import json
import re
import struct
import sys
from pathlib import Path

import pytest
from conftest import PNG_SIGNATURE, SET_SMALL, one_error_line

from dssp_train.cli.distill import main as distill_main
from dssp_train.cli.train import main as train_main
from dssp_train.training.train_log import read_log
from dssp_train.training.trainer import Trainer

INSTALL = 'pip install -e ".[viz]"'


@pytest.fixture(autouse=True)
def offline_wandb(tmp_path, monkeypatch):
    """W&B offline and silent, its own folders in tmp: nothing leaves the machine or lands in the home folder."""
    monkeypatch.setenv("WANDB_SILENT", "true")
    monkeypatch.setenv("WANDB_MODE", "offline")
    for name in ("WANDB_DIR", "WANDB_CONFIG_DIR", "WANDB_CACHE_DIR", "WANDB_DATA_DIR"):
        folder = tmp_path / "wandb_home" / name.lower()
        folder.mkdir(parents=True)
        monkeypatch.setenv(name, str(folder))


def train(data: Path, out: Path, *flags: str) -> None:
    """A small run (validation every 2 steps, a checkpoint every 2) that must succeed."""
    assert train_main(["--data", str(data), "--out", str(out), "--no-progress", *SET_SMALL, *flags]) == 0


def logged_scalars(run: Path) -> dict[str, list[tuple[int, float]]]:
    """log.jsonl's numbers by name: [(step, value), ...] in the log's order (bools and the kind left out)."""
    out: dict[str, list[tuple[int, float]]] = {}
    for row in read_log(run / "log.jsonl"):
        for key, value in row.items():
            if key not in ("kind", "step") and isinstance(value, (int, float)) and not isinstance(value, bool):
                out.setdefault(key, []).append((row["step"], float(value)))
    return out


def val_steps(run: Path) -> list[int]:
    return [row["step"] for row in read_log(run / "log.jsonl") if row["kind"] == "val"]


# ------------------------------------------------------------------ TensorBoard
def tensorboard_events(run: Path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(run / "tensorboard"), size_guidance={"scalars": 0, "images": 0})
    acc.Reload()
    return acc


def assert_same_scalars(acc, run: Path) -> None:
    """Every scalar tag is a name of log.jsonl and vice versa, with the same (step, value) pairs."""
    logged = logged_scalars(run)
    assert set(acc.Tags()["scalars"]) == set(logged)
    for tag, expected in logged.items():
        got = [(event.step, event.value) for event in acc.Scalars(tag)]
        assert [step for step, _ in got] == [step for step, _ in expected], tag
        assert [value for _, value in got] == pytest.approx([value for _, value in expected], rel=1e-6, abs=1e-30), tag


def test_tensorboard_gets_the_logs_scalars_and_the_validation_chunks(data, tmp_path):
    run = tmp_path / "run"
    train(data, run, "--steps", "4", "--log", "tensorboard")
    acc = tensorboard_events(run)
    assert {"loss", "diffusion", "lr", "val_diffusion", "val_action_mse"} <= set(acc.Tags()["scalars"])
    assert_same_scalars(acc, run)
    images = acc.Images("val_chunk")
    assert [image.step for image in images] == val_steps(run) == [2, 4]
    for image in images:
        assert image.encoded_image_string.startswith(PNG_SIGNATURE)
        assert image.width >= 300 and image.height >= 100
    assert not (run / "wandb").exists()


def test_a_resumed_run_continues_its_tensorboard_without_the_steps_after_the_checkpoint(data, tmp_path, monkeypatch):
    run = tmp_path / "run"
    real = Trainer.train_step

    def stop_after_3(self):  # step 3 is logged, then Ctrl-C: the checkpoint is step 2's
        if self.step >= 3:
            raise KeyboardInterrupt
        return real(self)

    monkeypatch.setattr(Trainer, "train_step", stop_after_3)
    assert (
        train_main(
            [
                "--data",
                str(data),
                "--out",
                str(run),
                "--steps",
                "6",
                "--no-progress",
                *SET_SMALL,
                "--log",
                "tensorboard",
            ]
        )
        == 130
    )
    monkeypatch.undo()
    first = tensorboard_events(run)
    assert [event.step for event in first.Scalars("loss")] == [1, 2, 3]
    assert (
        train_main(["--data", str(data), "--out", str(run), "--resume", "--no-progress", "--log", "tensorboard"]) == 0
    )
    assert len(list((run / "tensorboard").glob("events.out.tfevents.*"))) == 2  # appended to the same folder
    acc = tensorboard_events(run)
    assert [event.step for event in acc.Scalars("loss")] == [1, 2, 3, 4, 5, 6]  # the first process's step 3 is purged
    assert_same_scalars(acc, run)
    assert [image.step for image in acc.Images("val_chunk")] == val_steps(run) == [2, 4, 6]


def test_force_replaces_a_run_that_logged_to_a_dashboard(data, tmp_path):
    run = tmp_path / "run"
    train(data, run, "--steps", "2", "--log", "tensorboard")
    assert (run / "tensorboard").is_dir()
    train(data, run, "--steps", "2", "--force")  # --log none: no dashboard folder in the new run
    assert not (run / "tensorboard").exists() and not (run / "wandb").exists()
    assert [row["step"] for row in read_log(run / "log.jsonl") if row["kind"] == "train"] == [1, 2]


# ------------------------------------------------------------------ W&B
def wandb_records(path: Path) -> list:
    """The protobuf records of a W&B ``.wandb`` file: a 7-byte header (``:W&B``, magic, version), then LevelDB's
    log format (32 KiB blocks of chunks: CRC-32C, length, type 1 full / 2 first / 3 middle / 4 last)."""
    from wandb.proto import wandb_internal_pb2

    raw = path.read_bytes()
    ident, _, _ = struct.unpack("<4sHB", raw[:7])
    assert ident == b":W&B"
    block, pos, pending, records = 32768, 7, b"", []
    while pos + 7 <= len(raw):
        left = block - pos % block
        if left < 7:  # the rest of the block is padding
            pos += left
            continue
        _, length, kind = struct.unpack("<IHB", raw[pos : pos + 7])
        if kind == 0:  # zeroed tail of a block
            pos += left
            continue
        pending += raw[pos + 7 : pos + 7 + length]
        pos += 7 + length
        if kind in (1, 4):
            record = wandb_internal_pb2.Record()
            record.ParseFromString(pending)
            records.append(record)
            pending = b""
    return records


def wandb_history(records) -> list[dict]:
    """Each ``run.log`` call as {key: value} (W&B's own _step, _runtime, _timestamp left out)."""
    rows = []
    for record in records:
        if record.WhichOneof("record_type") == "history":
            row = {"/".join(item.nested_key) or item.key: json.loads(item.value_json) for item in record.history.item}
            rows.append({k: v for k, v in row.items() if k not in ("_step", "_runtime", "_timestamp")})
    return rows


def the_run_record(records):
    runs = [record.run for record in records if record.WhichOneof("record_type") == "run"]
    assert len(runs) == 1
    return runs[0]


def offline_runs(run: Path) -> list[Path]:
    return sorted((run / "wandb").glob("offline-run-*"))


def test_wandb_offline_run_gets_the_logs_scalars_and_the_validation_chunks(data, tmp_path):
    run = tmp_path / "run"
    train(data, run, "--steps", "4", "--log", "wandb")
    (folder,) = offline_runs(run)
    run_id = (run / "wandb" / "run_id").read_text().strip()
    assert folder.name.endswith(f"-{run_id}")
    records = wandb_records(folder / f"run-{run_id}.wandb")
    meta = the_run_record(records)
    assert (meta.run_id, meta.project, meta.display_name) == (run_id, "dssp", "run")
    config = {item.key: json.loads(item.value_json) for item in meta.config.update}
    assert config["model"] == json.loads((run / "config.json").read_text())["model"]

    history = wandb_history(records)
    scalars = [row for row in history if "val_chunk/_type" not in row]
    logged: dict[str, list[tuple[int, float]]] = {}
    for row in scalars:
        for key, value in row.items():
            if key != "step":
                logged.setdefault(key, []).append((row["step"], value))
    expected = logged_scalars(run)
    assert set(logged) == set(expected)
    for key, pairs in expected.items():
        assert [step for step, _ in logged[key]] == [step for step, _ in pairs], key
        assert [value for _, value in logged[key]] == pytest.approx([value for _, value in pairs], rel=1e-12), key

    images = [row for row in history if "val_chunk/_type" in row]
    assert [row["step"] for row in images] == val_steps(run) == [2, 4]
    for row in images:
        assert row["val_chunk/_type"] == "image-file"
        assert (folder / "files" / row["val_chunk/path"]).read_bytes().startswith(PNG_SIGNATURE)
    assert not (run / "tensorboard").exists()


def test_a_resumed_run_logs_to_the_same_wandb_id(data, tmp_path):
    run = tmp_path / "run"
    train(data, run, "--steps", "2", "--log", "wandb")
    run_id = (run / "wandb" / "run_id").read_text().strip()
    assert (
        train_main(
            ["--data", str(data), "--out", str(run), "--resume", "--steps", "4", "--no-progress", "--log", "wandb"]
        )
        == 0
    )
    assert (run / "wandb" / "run_id").read_text().strip() == run_id
    folders = offline_runs(run)  # W&B names a second folder of the same id in the same second with a "-1" suffix
    assert len(folders) == 2 and all(
        re.fullmatch(rf"offline-run-\d{{8}}_\d{{6}}-{run_id}(-\d+)?", f.name) for f in folders
    ), folders
    resumed = wandb_history(wandb_records(folders[1] / f"run-{run_id}.wandb"))
    assert sorted({row["step"] for row in resumed}) == [3, 4]


# ------------------------------------------------------------------ refusals
@pytest.mark.parametrize("dashboard", ["tensorboard", "wandb"])
@pytest.mark.parametrize("command", ["dssp-train", "dssp-distill"])
def test_a_missing_package_is_one_line_before_anything_is_trained(
    dashboard, command, data, tmp_path, capsys, monkeypatch
):
    monkeypatch.setitem(sys.modules, dashboard, None)  # import fails as if not installed

    def no_training(*args, **kwargs):
        raise AssertionError("training started")

    monkeypatch.setattr(Trainer, "__init__", no_training)
    out = tmp_path / "run"
    if command == "dssp-train":
        code = train_main(["--data", str(data), "--out", str(out), "--steps", "2", "--no-progress", "--log", dashboard])
    else:
        code = distill_main(
            ["--teacher", str(tmp_path / "teacher"), "--steps", "1", "--out", str(out), "--log", dashboard]
        )
    assert code == 2
    assert (
        one_error_line(capsys.readouterr().err) == f"error: --log {dashboard} needs the {dashboard} package: {INSTALL}"
    )
    assert not out.exists()


@pytest.mark.parametrize("main", [train_main, distill_main], ids=["dssp-train", "dssp-distill"])
def test_an_unknown_dashboard_is_one_line_naming_the_choices(main, data, tmp_path, capsys):
    out = tmp_path / "run"
    argv = (
        ["--data", str(data), "--out", str(out), "--steps", "2"]
        if main is train_main
        else ["--teacher", str(tmp_path / "teacher"), "--steps", "1", "--out", str(out)]
    )
    assert main([*argv, "--no-progress", "--log", "tensorbored"]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert one_error_line(captured.err) == "error: --log tensorbored: choose one of tensorboard, wandb, none"
    assert not out.exists()


def test_the_log_flag_is_not_part_of_the_run_config_and_a_resume_may_change_it(data, tmp_path):
    run = tmp_path / "run"
    train(data, run, "--steps", "2")
    config = (run / "config.json").read_text()
    assert not (run / "tensorboard").exists()
    assert (
        train_main(
            [
                "--data",
                str(data),
                "--out",
                str(run),
                "--resume",
                "--steps",
                "4",
                "--no-progress",
                "--log",
                "tensorboard",
            ]
        )
        == 0
    )
    assert (run / "config.json").read_text().replace('"steps": 4', '"steps": 2') == config  # only --steps changed
    acc = tensorboard_events(run)
    assert [event.step for event in acc.Scalars("loss")] == [3, 4]  # the dashboard starts where the resume does
    assert [event.value for event in acc.Scalars("loss")] == pytest.approx(
        [value for step, value in logged_scalars(run)["loss"] if step > 2], rel=1e-6
    )

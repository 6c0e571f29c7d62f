"""Run directories and checkpoints: exact resume, load_policy, clear errors, no pickles, crash safety."""

import json
import shutil
import struct
from pathlib import Path

import pytest
import torch
from conftest import FAST_EXPORT, SMALL, one_error_line
from safetensors.torch import load_file

from dssp_core.errors import CheckpointError, DSSPError
from dssp_train.cli.train import main as train_main
from dssp_train.config import apply_overrides, load_preset
from dssp_train.data.synthetic import write_tap_count_dataset
from dssp_train.training import checkpoint as ckpt
from dssp_train.training.checkpoint import load_policy
from dssp_train.training.train_log import read_log
from dssp_train.training.trainer import Trainer

K = 3  # the interrupted run stops after K steps; the full run has 2 K
# conftest's SMALL model and batch, checkpointing every K steps
OVERRIDES = [
    *[
        o
        for o in SMALL
        if o.startswith("model.") or o.startswith("train.batch_size") or o.startswith("train.val_windows")
    ],
    "train.warmup_steps=2",
    "train.log_every=1",
    f"train.val_every={K}",
    f"train.save_every={K}",
]
CHECKPOINT_FILES = ("model.safetensors", "ema.safetensors", "optimizer.safetensors", "rng.safetensors")
ALLOWED_SUFFIXES = {".json", ".jsonl", ".png", ".safetensors"}


def train_args(data: Path, out: Path, steps: int = 2 * K) -> list[str]:
    args = ["--data", str(data), "--out", str(out), "--preset", "tiny", "--steps", str(steps), "--no-progress"]
    for item in OVERRIDES:
        args += ["--set", item]
    return args


def resume_args(data: Path, out: Path) -> list[str]:
    return ["--data", str(data), "--out", str(out), "--resume", "--no-progress"]


class Interrupt:
    """Patch Trainer.train_step to raise KeyboardInterrupt before step ``at + 1``."""

    def __init__(self, at: int):
        self.at = at
        self.original = Trainer.train_step

    def __call__(self, trainer):
        if trainer.step >= self.at:
            raise KeyboardInterrupt
        return self.original(trainer)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """A dataset, a straight 2K-step run, and a run of the same config interrupted after step K."""
    root = tmp_path_factory.mktemp("runs")
    data = write_tap_count_dataset(root / "data.zarr", 5, seed=0, n_points=24)
    straight, interrupted = root / "straight", root / "interrupted"
    assert train_main(train_args(data, straight)) == 0
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(Trainer, "train_step", lambda self, _f=Interrupt(K): _f(self))
        assert train_main(train_args(data, interrupted)) == 130
    assert (interrupted / "checkpoint").is_dir()
    assert json.loads((interrupted / "checkpoint" / "trainer_state.json").read_text())["step"] == K
    return {"data": data, "straight": straight, "interrupted": interrupted}


def copy_run(runs, tmp_path: Path, name: str = "run") -> Path:
    dst = tmp_path / name
    shutil.copytree(runs["interrupted"], dst)
    return dst


def assert_same_tensors(a: Path, b: Path) -> None:
    ta, tb = load_file(str(a)), load_file(str(b))
    assert ta.keys() == tb.keys() and len(ta) > 0
    for key in ta:
        assert ta[key].dtype == tb[key].dtype, key
        assert torch.equal(ta[key], tb[key]), f"{a.name}: {key} differs"


def assert_same_final_state(run: Path, reference: Path) -> None:
    assert_same_tensors(run / "model.safetensors", reference / "model.safetensors")
    for name in CHECKPOINT_FILES:
        assert_same_tensors(run / "checkpoint" / name, reference / "checkpoint" / name)
    state = json.loads((run / "checkpoint" / "trainer_state.json").read_text())
    assert state == json.loads((reference / "checkpoint" / "trainer_state.json").read_text())
    assert state["step"] == 2 * K


# ------------------------------------------------------------------- (a) resume
def test_resume_is_exact(runs, tmp_path):
    run = copy_run(runs, tmp_path)
    assert train_main(resume_args(runs["data"], run)) == 0
    assert_same_final_state(run, runs["straight"])
    assert (run / "config.json").read_text() == (runs["straight"] / "config.json").read_text()

    rows = read_log(run / "log.jsonl")
    train_rows = [r for r in rows if r["kind"] == "train"]
    val_rows = [r for r in rows if r["kind"] == "val"]
    assert [r["step"] for r in train_rows] == list(range(1, 2 * K + 1))  # continued, and no step twice
    assert [r["step"] for r in val_rows] == [K, 2 * K]

    # The same losses, learning rates and validation numbers as the uninterrupted run.
    reference = read_log(runs["straight"] / "log.jsonl")
    drop = lambda r: {k: v for k, v in r.items() if k not in ("steps_per_s", "windows_per_s")}  # noqa: E731
    assert [drop(r) for r in rows] == [drop(r) for r in reference]


def test_resume_changes_weights_and_steps_beyond_the_interrupted_run(runs):
    """The exactness check is not vacuous: K more steps changed the weights."""
    a = load_file(str(runs["interrupted"] / "checkpoint" / "model.safetensors"))
    b = load_file(str(runs["straight"] / "checkpoint" / "model.safetensors"))
    assert any(not torch.equal(a[k], b[k]) for k in a)


def test_resume_of_a_finished_run_changes_nothing(runs, tmp_path, capsys):
    from conftest import snapshot

    run = tmp_path / "done"
    shutil.copytree(runs["straight"], run)
    before = snapshot(run)
    assert train_main(resume_args(runs["data"], run)) == 0
    captured = capsys.readouterr()
    assert captured.out == ""  # no summary: nothing was trained
    assert captured.err.strip() == (
        f"{run} has completed its {2 * K} steps: nothing to train; continue it with --resume --steps N (N > {2 * K})"
    )
    assert snapshot(run) == before
    assert_same_final_state(run, runs["straight"])
    assert [r["step"] for r in read_log(run / "log.jsonl") if r["kind"] == "train"] == list(range(1, 2 * K + 1))


def test_resume_with_more_steps_continues(runs, tmp_path):
    run = tmp_path / "longer"
    shutil.copytree(runs["straight"], run)
    assert train_main(resume_args(runs["data"], run) + ["--steps", str(2 * K + 2)]) == 0
    assert json.loads((run / "config.json").read_text())["train"]["steps"] == 2 * K + 2
    assert json.loads((run / "checkpoint" / "trainer_state.json").read_text())["step"] == 2 * K + 2
    steps = [r["step"] for r in read_log(run / "log.jsonl") if r["kind"] == "train"]
    assert steps == list(range(1, 2 * K + 3))


# ----------------------------------------------------------- (b) load_policy
def test_load_policy_matches_trained_ema_model(runs, tmp_path):
    config = apply_overrides(load_preset("tiny"), OVERRIDES + ["train.steps=4"])
    trainer = Trainer(config, runs["data"], tmp_path / "run", device="cpu", progress=False)
    trainer.run()
    policy, loaded_config = load_policy(tmp_path / "run")
    assert loaded_config.to_dict() == trainer.config.to_dict()
    assert not policy.training

    ema = trainer.ema.model
    expected = ema.state_dict()
    got = policy.state_dict()
    assert got.keys() == expected.keys()
    for key in expected:
        assert torch.equal(got[key], expected[key]), key
    # The normaliser statistics travel with the weights.
    assert any(k.startswith("normalizers.") for k in got)

    ep = trainer.val_eps[0]
    starts = torch.tensor([0, 5, 17, ep.length - 1])
    noise = torch.randn((4, config.model.horizon, config.model.action_dim), generator=torch.Generator().manual_seed(0))
    out = policy.sample_trajectory_windows(ep.point_cloud, ep.agent_pos, starts, noise)
    assert torch.equal(out, ema.sample_trajectory_windows(ep.point_cloud, ep.agent_pos, starts, noise))
    with torch.no_grad():
        loss = policy.compute_loss(ep.point_cloud, ep.agent_pos, ep.action, starts, torch.Generator().manual_seed(1))
        ref = ema.compute_loss(ep.point_cloud, ep.agent_pos, ep.action, starts, torch.Generator().manual_seed(1))
    for key in ("loss", "diffusion", "dynamics"):
        assert torch.equal(loss[key], ref[key]), key

    # model.safetensors holds the EMA weights, which after 4 steps differ from the raw ones.
    raw, _ = load_policy(tmp_path / "run", weights="checkpoint/model.safetensors")
    raw_out = raw.sample_trajectory_windows(ep.point_cloud, ep.agent_pos, starts, noise)
    assert not torch.equal(raw_out, out)
    for key, value in raw.state_dict().items():
        assert torch.equal(value, trainer.policy.state_dict()[key]), key


# ----------------------------------------------------------------- (c) errors
def strip_config_record(run: Path) -> None:
    """Make ``run`` look saved by a version from before configs were recorded: no config in its weights'
    metadata or its trainer_state.json (the record must be there to remove)."""
    from safetensors import safe_open
    from safetensors.torch import save_file

    for path in [run / "model.safetensors", *sorted((run / "checkpoint").glob("*.safetensors"))]:
        with safe_open(str(path), "pt") as f:
            meta = dict(f.metadata())
        assert {"config", "config_sha256"} <= set(meta), path
        save_file(
            load_file(str(path)), str(path), metadata={k: v for k, v in meta.items() if not k.startswith("config")}
        )
    state_path = run / "checkpoint" / "trainer_state.json"
    state = json.loads(state_path.read_text())
    del state["config"], state["config_sha256"]
    state_path.write_text(json.dumps(state))


def edit_config(run: Path, section: str, **values) -> None:
    config = json.loads((run / "config.json").read_text())
    (config[section] if section else config).update(values)
    (run / "config.json").write_text(json.dumps(config))


@pytest.mark.parametrize(
    "edit,kind",
    [
        ({"d_model": 48}, "with another shape"),
        ({"n_denoiser_layers": 3}, "missing"),
        ({"n_denoiser_layers": 1}, "unexpected"),
    ],
)
def test_weights_that_do_not_fit_the_config(runs, tmp_path, capsys, edit, kind):
    """config.json edited after training: the recorded config names the field; a run from before configs were
    recorded still gets the tensors' own explanation."""
    run = copy_run(runs, tmp_path, "edited")  # stopped halfway: --resume has steps to train
    edit_config(run, "model", **edit)
    ((field, value),) = edit.items()
    trained = json.loads((runs["straight"] / "config.json").read_text())["model"][field]
    named = f"model.{field} {value} (trained: {trained})"

    with pytest.raises(CheckpointError) as info:
        load_policy(run)
    assert "\n" not in str(info.value) and named in str(info.value)
    assert f"{run / 'config.json'} differs from the config {run / 'model.safetensors'} was trained with" in str(
        info.value
    )
    assert train_main(resume_args(runs["data"], run)) == 2
    line = one_error_line(capsys.readouterr().err)
    assert named in line and str(run / "checkpoint" / "trainer_state.json") in line

    strip_config_record(run)
    tensor_names = set(load_file(str(run / "model.safetensors")))
    with pytest.raises(CheckpointError) as info:
        load_policy(run)
    message = str(info.value)
    assert "\n" not in message
    assert str(run / "model.safetensors") in message
    assert kind in message
    assert "Use the config.json saved with these weights, or retrain" in message
    named = [
        n for n in tensor_names | {f"denoiser.layers.2.{s}" for s in ("norm.weight", "mixer.A_log")} if n in message
    ]
    assert named, message

    # --resume reports it the same way: one line, exit code 2 (after the warning that the config is not recorded).
    assert train_main(resume_args(runs["data"], run)) == 2
    warning, error = capsys.readouterr().err.strip().splitlines()
    assert warning.startswith("warning: ") and "does not record the config it was trained with" in warning
    assert error.startswith("error: ") and kind in error and "checkpoint" in error


def test_every_weights_file_records_the_config_it_was_trained_with(runs):
    from safetensors import safe_open

    run = runs["straight"]
    text = ckpt.canonical_config(ckpt.load_config(run))
    for path in [run / "model.safetensors", *(run / "checkpoint" / n for n in CHECKPOINT_FILES)]:
        with safe_open(str(path), "pt") as f:
            meta = f.metadata()
        assert meta["config"] == text and meta["config_sha256"] == ckpt.config_sha256(text), path
    state = json.loads((run / "checkpoint" / "trainer_state.json").read_text())
    assert state["config_sha256"] == ckpt.config_sha256(text) and state["config"] == json.loads(text)


@pytest.mark.parametrize(
    "section,values,named",
    [
        ("train", {"lr": 0.5}, "train.lr 0.5 (trained: 0.001)"),
        ("train", {"seed": 7, "batch_size": 3}, "train.batch_size 3 (trained: 4), train.seed 7 (trained: 0)"),
        (None, {"control_rate_hz": 30.0}, "control_rate_hz 30.0 (trained: 10.0)"),
        ("model", {"dynamics_weight": 0.0}, "model.dynamics_weight 0.0 (trained: 0.05)"),
    ],
)
def test_resume_refuses_a_config_edited_after_training(runs, tmp_path, capsys, section, values, named):
    """Fields the tensors cannot tell: the checkpoint's recorded config does; nothing in the run changes."""
    from conftest import snapshot

    run = copy_run(runs, tmp_path)
    edit_config(run, section, **values)
    before = snapshot(run)
    assert train_main(resume_args(runs["data"], run)) == 2
    line = one_error_line(capsys.readouterr().err)
    assert named in line, line
    assert line.startswith(
        f"error: {run / 'config.json'} differs from the config {run / 'checkpoint' / 'trainer_state.json'}"
    )
    assert "put the trained values back in config.json" in line
    assert snapshot(run) == before


def test_resume_accepts_config_json_written_another_way(runs, tmp_path, capsys):
    """Only values count: another layout of the same config (keys reordered, no indentation, a default left
    out) continues the run."""
    run = copy_run(runs, tmp_path)
    config = json.loads((run / "config.json").read_text())
    del config["distill"]  # the default
    (run / "config.json").write_text(json.dumps(dict(reversed(list(config.items())))))
    assert train_main(resume_args(runs["data"], run)) == 0
    assert "config" not in capsys.readouterr().err  # no warning about it, no refusal
    assert_same_final_state(run, runs["straight"])


def test_a_checkpoint_without_a_recorded_config_resumes_with_a_warning(runs, tmp_path, capsys):
    run = copy_run(runs, tmp_path)
    strip_config_record(run)
    assert train_main(resume_args(runs["data"], run)) == 0
    warnings = [
        line for line in capsys.readouterr().err.splitlines() if line.startswith("warning: ") and "config" in line
    ]
    assert warnings == [
        f"warning: {run / 'checkpoint' / 'trainer_state.json'} does not record the config it was trained "
        f"with (saved by an older version): {run / 'config.json'} is taken as it is"
    ]
    assert_same_final_state(run, runs["straight"])  # and its next checkpoint records it


def test_export_refuses_a_config_edited_after_training(runs, tmp_path, capsys):
    from export.to_onnx import main as export_main

    run = tmp_path / "run"
    shutil.copytree(runs["straight"], run)
    edit_config(run, "model", n_action_steps=2)
    model = tmp_path / "out" / "model"
    assert export_main([str(run), "-o", str(model), *FAST_EXPORT]) == 2
    line = one_error_line(capsys.readouterr().err)
    assert f"{run / 'config.json'} differs from the config {run / 'model.safetensors'} was trained with" in line
    assert "model.n_action_steps 2 (trained: 3)" in line
    assert not (tmp_path / "out").exists()
    # The raw weights (--no-ema) record it too.
    assert export_main([str(run), "-o", str(model), "--no-ema", *FAST_EXPORT]) == 2
    assert f"differs from the config {run / 'checkpoint' / 'model.safetensors'} was trained" in one_error_line(
        capsys.readouterr().err
    )


def test_export_takes_a_run_without_a_recorded_config_and_says_so(runs, tmp_path, capsys):
    from export.to_onnx import main as export_main

    run = tmp_path / "run"
    shutil.copytree(runs["straight"], run)
    assert export_main([str(run), "-o", str(tmp_path / "recorded"), *FAST_EXPORT]) == 0
    assert "config is not recorded" not in capsys.readouterr().out
    strip_config_record(run)
    assert export_main([str(run), "-o", str(tmp_path / "model"), *FAST_EXPORT]) == 0
    captured = capsys.readouterr()
    loaded = [line for line in captured.out.splitlines() if " loaded " in line]
    assert (
        len(loaded) == 1
        and "its config is not recorded (saved by an older version): config.json taken as it is" in loaded[0]
    )
    assert "error" not in captured.err


def test_missing_config_json(runs, tmp_path, capsys):
    run = tmp_path / "noconfig"
    shutil.copytree(runs["straight"], run)
    (run / "config.json").unlink()
    with pytest.raises(CheckpointError, match="config.json is missing"):
        load_policy(run)
    assert train_main(resume_args(runs["data"], run)) == 2
    assert "config.json is missing" in one_error_line(capsys.readouterr().err)


def test_invalid_config_json(runs, tmp_path):
    run = tmp_path / "badconfig"
    shutil.copytree(runs["straight"], run)
    (run / "config.json").write_text("{not json")
    with pytest.raises(CheckpointError, match="not valid JSON") as info:
        load_policy(run)
    assert "\n" not in str(info.value)
    (run / "config.json").write_text(json.dumps({"model": {"d_model": 0}}))
    with pytest.raises(CheckpointError, match="d_model"):
        load_policy(run)


@pytest.mark.parametrize("damage", ["garbage", "truncated", "empty"])
def test_corrupt_model_safetensors(runs, tmp_path, damage):
    run = tmp_path / "corrupt"
    shutil.copytree(runs["straight"], run)
    path = run / "model.safetensors"
    raw = path.read_bytes()
    path.write_bytes(
        {"garbage": b"this is not a safetensors file", "truncated": raw[: len(raw) // 2], "empty": b""}[damage]
    )
    with pytest.raises(CheckpointError, match="not a readable safetensors file") as info:
        load_policy(run)
    assert "\n" not in str(info.value)


def test_missing_model_safetensors(runs, tmp_path):
    run = tmp_path / "noweights"
    shutil.copytree(runs["straight"], run)
    (run / "model.safetensors").unlink()
    with pytest.raises(CheckpointError, match="model.safetensors is missing"):
        load_policy(run)


@pytest.mark.parametrize("name", ["ema.safetensors", "optimizer.safetensors", "rng.safetensors", "trainer_state.json"])
def test_corrupt_checkpoint_file_on_resume(runs, tmp_path, capsys, name):
    run = copy_run(runs, tmp_path)
    (run / "checkpoint" / name).write_bytes(b"\x00garbage")
    with pytest.raises(CheckpointError) as info:
        Trainer(ckpt.load_config(run), runs["data"], run, device="cpu", resume=True, progress=False)
    assert name in str(info.value) and "\n" not in str(info.value)
    assert train_main(resume_args(runs["data"], run)) == 2
    assert name in one_error_line(capsys.readouterr().err)


def test_resume_without_checkpoint_folder(runs, tmp_path, capsys):
    run = copy_run(runs, tmp_path)
    shutil.rmtree(run / "checkpoint")
    with pytest.raises(CheckpointError, match="has no checkpoint yet .*nothing to resume; start it over with --force"):
        ckpt.load_training_state(run)
    assert ckpt.read_trainer_state(run) is None and ckpt.checkpoint_dir(run) is None
    assert train_main(resume_args(runs["data"], run)) == 2
    line = one_error_line(capsys.readouterr().err)
    assert f"{run / 'checkpoint'} is missing, so the run cannot be continued" in line
    assert "model.safetensors stays usable" in line and "start it over with --force" in line
    # Without model.safetensors either, the run stopped before its first save (step K).
    (run / "model.safetensors").unlink()
    assert train_main(resume_args(runs["data"], run)) == 2
    assert one_error_line(capsys.readouterr().err) == (
        f"error: {run} has no checkpoint yet (stopped before step {K}'s save): start it over with --force"
    )


def test_error_classes_are_user_errors():
    assert issubclass(CheckpointError, DSSPError)


# --------------------------------------------------------------- (d) no pickles
def assert_no_pickles(run: Path) -> None:
    """Every file is JSON, JSON lines, PNG or safetensors, and parses as what its name says."""
    files = [p for p in run.rglob("*") if p.is_file()]
    assert files
    for path in files:
        assert path.suffix in ALLOWED_SUFFIXES, path
        raw = path.read_bytes()
        if path.suffix == ".json":
            json.loads(raw)
        elif path.suffix == ".jsonl":
            assert all(isinstance(json.loads(line), dict) for line in raw.decode().splitlines())
        elif path.suffix == ".png":
            assert raw.startswith(b"\x89PNG\r\n\x1a\n"), path
        else:
            # safetensors: an 8-byte little-endian header length, a JSON header, then raw tensor bytes.
            n = struct.unpack("<Q", raw[:8])[0]
            header = json.loads(raw[8 : 8 + n])
            assert header.get("__metadata__", {}).get("format_version") == ckpt.FORMAT_VERSION, path
            assert load_file(str(path)).keys() == {k for k in header if k != "__metadata__"}
    # Nothing half-written left behind either.
    assert not [p for p in run.rglob("*") if p.name.endswith(".tmp") or p.name.startswith(".checkpoint")]


def test_run_directory_holds_no_pickles(runs, tmp_path):
    assert_no_pickles(runs["straight"])
    names = {str(p.relative_to(runs["straight"])) for p in runs["straight"].rglob("*") if p.is_file()}
    assert names == {
        "config.json",
        "model.safetensors",
        "log.jsonl",
        "loss.png",
        "checkpoint/trainer_state.json",
        *(f"checkpoint/{n}" for n in CHECKPOINT_FILES),
    }
    run = copy_run(runs, tmp_path)
    assert train_main(resume_args(runs["data"], run)) == 0
    assert_no_pickles(run)


# ---------------------------------------------------------- (e) crash mid-swap
def test_crash_mid_swap_still_resumes(runs, tmp_path):
    """A crash between renaming checkpoint/ aside and renaming the new one in leaves only .checkpoint.old."""
    run = copy_run(runs, tmp_path)
    (run / "checkpoint").rename(run / ".checkpoint.old")
    assert train_main(resume_args(runs["data"], run)) == 0
    assert_same_final_state(run, runs["straight"])
    assert not (run / ".checkpoint.old").exists()
    assert_no_pickles(run)


def test_crash_while_clearing_the_old_checkpoint_still_resumes(runs, tmp_path, monkeypatch):
    """Resumed from .checkpoint.old, the next save must not delete it before the new checkpoint is in place.

    Simulated crash: the deletion of .checkpoint.old removes one file and then the process dies.
    """
    run = copy_run(runs, tmp_path)
    (run / "checkpoint").rename(run / ".checkpoint.old")
    real_rmtree = shutil.rmtree

    def crashing_rmtree(path, *args, **kwargs):
        if Path(path).name == ".checkpoint.old" and Path(path).exists():
            sorted(Path(path).iterdir())[0].unlink()
            raise KeyboardInterrupt
        return real_rmtree(path, *args, **kwargs)

    monkeypatch.setattr(ckpt.shutil, "rmtree", crashing_rmtree)
    assert train_main(resume_args(runs["data"], run)) == 130
    monkeypatch.setattr(ckpt.shutil, "rmtree", real_rmtree)

    assert train_main(resume_args(runs["data"], run)) == 0
    assert_same_final_state(run, runs["straight"])


# ---------------------------------------------------------- (f) a log and folders left by a killed run
def test_resume_drops_log_lines_written_after_the_checkpoint(runs, tmp_path):
    """A run killed between checkpoints logged steps past its checkpoint (and maybe half a line): resuming
    from the checkpoint must not log those steps twice."""
    run = copy_run(runs, tmp_path)
    with open(run / "log.jsonl", "a") as f:
        for step in (K + 1, K + 2):
            f.write(json.dumps({"kind": "train", "step": step, "loss": 1.0, "diffusion": 1.0, "dynamics": 0.0}) + "\n")
        f.write('{"kind": "train", "st')  # torn by the kill
    assert train_main(resume_args(runs["data"], run)) == 0
    steps = [r["step"] for r in read_log(run / "log.jsonl") if r["kind"] == "train"]
    assert steps == list(range(1, 2 * K + 1))
    assert all(json.loads(line) for line in (run / "log.jsonl").read_text().splitlines())


def test_an_interrupted_checkpoint_save_leaves_no_partial_folder(runs, tmp_path, monkeypatch):
    run = copy_run(runs, tmp_path)
    (run / ".checkpoint.partial-killed").mkdir()  # what a SIGKILL mid-save leaves
    (run / ".checkpoint.partial-killed" / "model.safetensors").write_bytes(b"half")
    (run / ".model.safetensors.x1y2.tmp").write_bytes(b"half")
    real = ckpt.save_tensors
    calls = {"n": 0}

    def dying_save(path, *args, **kwargs):
        calls["n"] += 1
        if Path(path).parent.name.startswith(".checkpoint.") and calls["n"] >= 3:
            raise KeyboardInterrupt
        return real(path, *args, **kwargs)

    monkeypatch.setattr(ckpt, "save_tensors", dying_save)
    assert train_main(resume_args(runs["data"], run)) == 130
    leftovers = [p.name for p in run.iterdir() if p.name.startswith(".")]
    assert leftovers == [], leftovers
    assert (run / "checkpoint").is_dir()  # the previous complete checkpoint is still there
    monkeypatch.setattr(ckpt, "save_tensors", real)
    assert train_main(resume_args(runs["data"], run)) == 0
    assert_same_final_state(run, runs["straight"])


def test_kept_snapshots_are_run_directories_of_their_step(runs, tmp_path):
    """train.keep_every: the EMA weights every N steps as RUN/snapshots/step_NNNNNNN (what export reads); the last
    one is the run's final weights, and a resumed run keeps the same snapshots as a straight one."""
    straight, resumed = tmp_path / "straight", tmp_path / "resumed"
    assert train_main([*train_args(runs["data"], straight), "--set", f"train.keep_every={K}"]) == 0
    assert sorted(p.name for p in (straight / "snapshots").iterdir()) == [f"step_{K:07d}", f"step_{2 * K:07d}"]
    assert_same_tensors(
        straight / "snapshots" / f"step_{2 * K:07d}" / "model.safetensors", straight / "model.safetensors"
    )
    policy, config = load_policy(straight / "snapshots" / f"step_{K:07d}")
    assert config.train.keep_every == K and ckpt.weights_metadata(
        straight / "snapshots" / f"step_{K:07d}" / "model.safetensors"
    )["step"] == str(K)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(Trainer, "train_step", lambda self, _f=Interrupt(K): _f(self))
        assert train_main([*train_args(runs["data"], resumed), "--set", f"train.keep_every={K}"]) == 130
    assert train_main(resume_args(runs["data"], resumed)) == 0
    for step in (K, 2 * K):
        name = f"step_{step:07d}"
        assert_same_tensors(
            resumed / "snapshots" / name / "model.safetensors", straight / "snapshots" / name / "model.safetensors"
        )

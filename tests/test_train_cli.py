"""``dssp-train`` and ``dssp-params`` from the command line: one-line errors, the happy path, ablation flags."""

import json
import math
import os
import re
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import zarr
from conftest import PNG_SIGNATURE, ROOT, SET_SMALL, one_error_line
from safetensors import safe_open

from dssp_core.schema import DEFAULT_CONTROL_RATE_HZ
from dssp_data.replay_buffer import ReplayBuffer
from dssp_data.replay_buffer_writer import write_replay_buffer
from dssp_train.cli.params import main as params_main
from dssp_train.cli.train import main as train_main
from dssp_train.config import RunConfig, load_preset
from dssp_train.data.synthetic import make_tap_count_episodes, write_tap_count_dataset
from dssp_train.model.policy import DSSPPolicy
from dssp_train.training.train_log import read_log
from dssp_train.training.trainer import Trainer

TRAIN_KEYS = {"kind", "step", "loss", "diffusion", "dynamics", "lr", "steps_per_s", "windows_per_s"}
VAL_KEYS = {"kind", "step", "on_train_episodes", "val_diffusion", "val_action_mse"}
DYNAMICS_KEYS = {"dyn_cos", "dyn_cos_mean", "dyn_cos_prev"}  # the dynamics loss's diagnostics


def subprocess_env() -> dict[str, str]:
    return {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONWARNINGS": "ignore"}


def cli(*args) -> list[str]:
    return [sys.executable, "-m", "dssp_train.cli.train", *map(str, args)]


# ---------------------------------------------------------------------- data
@pytest.fixture(scope="module")
def nan_data(tmp_path_factory) -> Path:
    path = write_tap_count_dataset(tmp_path_factory.mktemp("nan") / "nan.zarr", 3, seed=0, n_points=24)
    step = nan_step(path)
    action = zarr.open_array(str(path / "data" / "action"), mode="r+")
    action[step, 1] = np.nan
    assert np.isnan(np.asarray(action[step, 1]))
    return path


def nan_step(path: Path) -> int:
    """The corrupted step: the sixth step of episode 1."""
    return int(np.asarray(zarr.open_array(str(path / "meta" / "episode_ends"), mode="r")[0])) + 5


@pytest.fixture(scope="module")
def not_zarr(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("plain") / "plain_dir"
    path.mkdir()
    (path / "readme.txt").write_text("not a dataset")
    return path


@pytest.fixture(scope="module")
def happy(tmp_path_factory, data):
    """A real ``python -m dssp_train.cli.train`` run of 4 steps."""
    out = tmp_path_factory.mktemp("happy") / "run"
    proc = subprocess.run(
        cli("--data", data, "--out", out, "--preset", "tiny", "--steps", 4, "--no-progress", *SET_SMALL),
        capture_output=True,
        text=True,
        env=subprocess_env(),
        timeout=300,
    )
    return {"out": out, "proc": proc}


# ---------------------------------------------------------------- error cases
def error_cases(data: Path, nan_data: Path, not_zarr: Path, tmp: Path, happy_out: Path):
    """(name, argv, a phrase the one-line message must contain)."""
    fresh = tmp / "fresh"
    base = ["--preset", "tiny", "--steps", "2", "--no-progress", *SET_SMALL]
    return [
        ("missing dataset", ["--data", tmp / "nope.zarr", "--out", fresh, *base], "does not exist"),
        ("not zarr", ["--data", not_zarr, "--out", fresh, *base], "is not a zarr group"),
        ("nan action", ["--data", nan_data, "--out", fresh, *base], "data/action holds NaN or inf"),
        (
            "unknown preset",
            ["--data", data, "--out", fresh, "--preset", "nosuch", "--no-progress"],
            "unknown preset 'nosuch'",
        ),
        (
            "bad set key",
            ["--data", data, "--out", fresh, *base, "--set", "model.nosuch=3"],
            "unknown field 'model.nosuch'",
        ),
        (
            "bad set section",
            ["--data", data, "--out", fresh, *base, "--set", "optim.lr=3"],
            "'optim' is not a config section",
        ),
        (
            "set without =",
            ["--data", data, "--out", fresh, *base, "--set", "model.d_model"],
            "must look like section.field=value",
        ),
        (
            "bad set value",
            ["--data", data, "--out", fresh, *base, "--set", "model.expand=0"],
            "--set model.expand=0: model.expand must be an integer in [1, 16], got 0",
        ),
        ("out holds a run", ["--data", data, "--out", happy_out, *base], "already holds a run"),
        ("resume without run", ["--data", data, "--out", fresh, "--resume", "--no-progress"], "config.json is missing"),
        ("device cuda", ["--data", data, "--out", fresh, *base, "--device", "cuda"], "CUDA is not available"),
        (
            "point_dim 6 on xyz",
            ["--data", data, "--out", fresh, *base, "--set", "model.point_dim=6"],
            "model.point_dim=6 needs xyz+rgb",
        ),
        ("resume with preset", ["--data", data, "--out", happy_out, "--resume", "--preset", "tiny"], "drop --preset"),
        (
            "resume with set",
            ["--data", data, "--out", happy_out, "--resume", "--set", "model.d_model=64"],
            "only --steps may change",
        ),
    ]


CASE_NAMES = [
    "missing dataset",
    "not zarr",
    "nan action",
    "unknown preset",
    "bad set key",
    "bad set section",
    "set without =",
    "bad set value",
    "out holds a run",
    "resume without run",
    "device cuda",
    "point_dim 6 on xyz",
    "resume with preset",
    "resume with set",
]
SUBPROCESS_CASES = ["missing dataset", "not zarr", "nan action", "device cuda"]


@pytest.mark.parametrize("name", CASE_NAMES)
def test_bad_input_is_one_error_line_and_exit_code_2(name, data, nan_data, not_zarr, happy, tmp_path, capsys):
    cases = {n: (argv, phrase) for n, argv, phrase in error_cases(data, nan_data, not_zarr, tmp_path, happy["out"])}
    argv, phrase = cases[name]
    before = sorted(p.name for p in happy["out"].rglob("*"))
    assert train_main([str(a) for a in argv]) == 2
    captured = capsys.readouterr()
    line = one_error_line(captured.err)
    assert phrase in line, line
    assert captured.out == ""
    assert not (tmp_path / "fresh").exists()  # nothing half-made on disk
    assert sorted(p.name for p in happy["out"].rglob("*")) == before  # an existing run is left alone


def test_bad_input_via_subprocess(data, nan_data, not_zarr, happy, tmp_path):
    cases = {}
    for name in SUBPROCESS_CASES:  # each into its own --out: they run at the same time (one writer per run directory)
        (tmp_path / name).mkdir()
        cases[name] = {
            n: (argv, phrase)
            for n, argv, phrase in error_cases(data, nan_data, not_zarr, tmp_path / name, happy["out"])
        }[name]
    procs = {
        name: subprocess.Popen(
            cli(*cases[name][0]), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=subprocess_env()
        )
        for name in SUBPROCESS_CASES
    }
    for name, proc in procs.items():
        out, err = proc.communicate(timeout=300)
        assert proc.returncode == 2, (name, err)
        assert cases[name][1] in one_error_line(err), name
        assert out == ""


def test_nan_message_names_the_step_and_episode(nan_data, tmp_path, capsys):
    assert train_main(["--data", str(nan_data), "--out", str(tmp_path / "x"), "--no-progress"]) == 2
    line = one_error_line(capsys.readouterr().err)
    assert f"first at step {nan_step(nan_data)} (episode 1)" in line


def test_a_run_stopped_before_its_first_checkpoint_is_started_over_with_force(data, tmp_path, capsys, monkeypatch):
    """config.json exists but no checkpoint: every message says the same thing (start it over with --force),
    and --force does replace it."""
    out = tmp_path / "early"
    real_step = Trainer.train_step

    def interrupt_after_one_step(self):
        if self.step >= 1:
            raise KeyboardInterrupt
        return real_step(self)

    monkeypatch.setattr(Trainer, "train_step", interrupt_after_one_step)
    assert train_main(["--data", str(data), "--out", str(out), "--steps", "4", "--no-progress", *SET_SMALL]) == 130
    monkeypatch.undo()
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        "interrupted after step 1, before step 2's save: no checkpoint was kept; start the run over by adding --force"
    )
    assert (out / "config.json").is_file() and (out / "log.jsonl").is_file() and not (out / "checkpoint").exists()

    no_checkpoint = f"error: {out} has no checkpoint yet (stopped before step 2's save): start it over with --force"
    assert train_main(["--data", str(data), "--out", str(out), "--resume", "--no-progress"]) == 2
    assert one_error_line(capsys.readouterr().err) == no_checkpoint
    assert train_main(["--data", str(data), "--out", str(out), "--no-progress", *SET_SMALL]) == 2
    assert one_error_line(capsys.readouterr().err) == no_checkpoint + ", or choose another --out"

    assert (
        train_main(["--data", str(data), "--out", str(out), "--steps", "2", "--force", "--no-progress", *SET_SMALL])
        == 0
    )
    capsys.readouterr()
    assert json.loads((out / "checkpoint" / "trainer_state.json").read_text())["step"] == 2
    assert json.loads((out / "config.json").read_text())["train"]["steps"] == 2
    assert [r["step"] for r in read_log(out / "log.jsonl") if r["kind"] == "train"] == [1, 2]


# ---------------------------------------------------------------- happy path
def test_happy_path_exit_code_and_summary(happy):
    proc, out = happy["proc"], happy["out"]
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr and "error" not in proc.stderr
    assert "--control-rate" not in proc.stderr  # the tap-count dataset records its control rate
    assert proc.stderr.startswith("budget: 4 steps (train.steps, 1.333 epochs of 3 training episodes)")
    summary = json.loads(proc.stdout)
    assert summary["step"] == 4
    assert Path(summary["run_dir"]) == out
    for key in ("val_diffusion", "val_action_mse"):
        assert math.isfinite(summary[key]) and summary[key] > 0


def test_happy_path_run_directory(happy, data):
    out = happy["out"]
    assert happy["proc"].returncode == 0, happy["proc"].stderr
    config = json.loads((out / "config.json").read_text())
    assert config["preset"] == "tiny"
    assert config["control_rate_hz"] == DEFAULT_CONTROL_RATE_HZ
    assert config["dataset"] == str(data)
    assert config["train"]["steps"] == 4
    m = config["model"]
    assert (m["d_model"], m["state_dim"], m["action_dim"], m["n_points"], m["point_dim"]) == (32, 2, 2, 24, 3)

    with safe_open(str(out / "model.safetensors"), "pt") as f:
        assert f.metadata()["step"] == "4"
        keys = set(f.keys())
    assert keys == set(DSSPPolicy(RunConfig.from_dict(config).model).state_dict())

    rows = read_log(out / "log.jsonl")
    train = [r for r in rows if r["kind"] == "train"]
    val = [r for r in rows if r["kind"] == "val"]
    assert [r["step"] for r in train] == [1, 2, 3, 4]
    assert [r["step"] for r in val] == [2, 4]
    for r in train:
        assert set(r) == TRAIN_KEYS | DYNAMICS_KEYS
        assert all(math.isfinite(r[k]) for k in (TRAIN_KEYS | DYNAMICS_KEYS) - {"kind", "step"})
        assert all(-1 <= r[k] <= 1 for k in DYNAMICS_KEYS) and r["dyn_cos"] == pytest.approx(
            1 - r["dynamics"], abs=1e-5
        )
        assert r["steps_per_s"] > 0 and r["lr"] >= 0
        assert r["loss"] == pytest.approx(r["diffusion"] + m["dynamics_weight"] * r["dynamics"], rel=1e-5)
        assert r["windows_per_s"] == pytest.approx(r["steps_per_s"] * config["train"]["batch_size"], rel=1e-9)
    assert train[0]["lr"] == pytest.approx(config["train"]["lr"])  # after one warm-up step: the peak
    assert train[-1]["lr"] == pytest.approx(0.0, abs=1e-12)  # cosine ends at 0
    for r in val:
        assert set(r) == VAL_KEYS
        assert r["on_train_episodes"] is False
        assert math.isfinite(r["val_diffusion"]) and math.isfinite(r["val_action_mse"])


def test_happy_path_loss_png(happy):
    png = (happy["out"] / "loss.png").read_bytes()
    assert png.startswith(PNG_SIGNATURE)
    assert png[12:16] == b"IHDR"
    width, height = struct.unpack(">II", png[16:24])
    assert (width, height) == (1650, 400)  # losses, validation, and the dynamics predictor against trivial ones
    assert len(png) > 10_000  # three axes with curves, not an empty canvas
    assert png.rstrip(b"\x00").endswith(b"IEND\xaeB`\x82")


def test_missing_control_rate_warns_and_flag_sets_it(tmp_path, capsys):
    path = tmp_path / "norate.zarr"
    write_replay_buffer(path, make_tap_count_episodes(3, seed=1, n_points=24))
    assert "control_rate_hz" not in ReplayBuffer.load(path).attrs
    common = ["--data", str(path), "--steps", "1", "--no-progress", *SET_SMALL]

    assert train_main([*common, "--out", str(tmp_path / "a")]) == 0
    err = capsys.readouterr().err
    assert any(line.startswith("warning: ") and "--control-rate" in line for line in err.splitlines())
    assert json.loads((tmp_path / "a" / "config.json").read_text())["control_rate_hz"] is None

    assert train_main([*common, "--out", str(tmp_path / "b"), "--control-rate", "20"]) == 0
    assert "--control-rate" not in capsys.readouterr().err
    assert json.loads((tmp_path / "b" / "config.json").read_text())["control_rate_hz"] == 20.0


# ------------------------------------------------------ the training budget
def test_epochs_are_passes_over_the_training_trajectories(data, tmp_path, capsys):
    """--epochs E: E x (training episodes) steps, one trajectory per step; printed at the start and recorded."""
    common = ["--data", str(data), "--no-progress", *SET_SMALL]
    assert train_main([*common, "--out", str(tmp_path / "a"), "--epochs", "2", "--val-ratio", "0.25"]) == 0
    captured = capsys.readouterr()
    assert json.loads(captured.out)["step"] == 6  # 4 episodes, 1 held out: 2 x 3
    train = json.loads((tmp_path / "a" / "config.json").read_text())["train"]
    assert train["steps"] == 6 and train["epochs"] == 2
    lines = captured.err.splitlines()
    assert "budget: 6 steps (2 epochs x 3 training episodes), 4 windows per step" in lines
    warning = [line for line in lines if "validation holdout" in line]
    assert (
        len(warning) == 1
        and warning[0].startswith("warning: ")
        and "takes 1 of 4 episodes" in warning[0]
        and "--no-holdout" in warning[0]
    )

    assert train_main([*common, "--out", str(tmp_path / "b"), "--epochs", "1", "--no-holdout"]) == 0
    captured = capsys.readouterr()
    assert json.loads(captured.out)["step"] == 4 and "validation holdout" not in captured.err
    assert json.loads((tmp_path / "b" / "config.json").read_text())["train"]["val_ratio"] == 0.0


def test_the_paper_cost_table_is_each_presets_step_times_its_budget(tmp_path, capsys, monkeypatch):
    """``benchmarks/train_step_time.py --paper``: one task's cost = the step's median x (the preset's epochs x
    the task's demonstrations), every demonstration trained on; each step built at its task's shapes."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("bench_train_step_time", ROOT / "benchmarks" / "train_step_time.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    built = []
    monkeypatch.setattr(bench, "train_step_fn", lambda *a: (built.append(a), (lambda: None, f"step {a[0]}"))[1])
    median = {"metaworld": 1000.0, "adroit": 2000.0, "robotwin": 3600.0}  # ms
    monkeypatch.setattr(bench, "time_calls", lambda fn, n, warmup=0: [median[built[-1][0]]] * n)
    assert bench.main(["--paper", "--repeats", "2", "--json", str(tmp_path / "cost.json")]) == 0
    report = json.loads((tmp_path / "cost.json").read_text())
    assert report["paper"] and report["device"] == "cpu" and report["repeats"] == 2 and report["machine"]["cpu"]
    rows = {r["preset"]: r for r in report["rows"]}
    assert [a[:4] for a in built] == [(preset, *bench.PAPER_TASKS[preset][:3]) for preset in rows]
    for preset, (_, _, _, demos) in bench.PAPER_TASKS.items():
        epochs = load_preset(preset).train.epochs
        assert rows[preset]["steps"] == epochs * demos and rows[preset]["epochs"] == epochs
        assert rows[preset]["hours"] == pytest.approx(median[preset] * epochs * demos / 3.6e6)
    assert rows["robotwin"]["steps"] == 150_000 and rows["robotwin"]["hours"] == pytest.approx(150.0)
    out = capsys.readouterr().out
    assert "| step robotwin | 3600.0 (3600.0-3600.0) | 3000 epochs x 50 demos | 150,000 | 150.0 h (6.2 days) |" in out
    assert bench.markdown(report) in out  # the record renders to what was printed (the README's table comes from it)


def test_the_step_time_benchmark_needs_only_torch_numpy_and_tqdm():
    """On a GPU machine the benchmark runs from a checkout (``PYTHONPATH=.``) with no dataset or runtime stack."""
    script = ROOT / "benchmarks" / "train_step_time.py"
    code = (
        "import runpy, sys\n"
        "for name in ('zarr', 'numcodecs', 'onnx', 'onnxruntime', 'safetensors', 'matplotlib', 'mujoco', 'can'):\n"
        "    sys.modules[name] = None  # importing any of these now fails\n"
        f"sys.argv = ['train_step_time.py', '--help']\nrunpy.run_path({str(script)!r}, run_name='__main__')\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0 and "--paper" in proc.stdout, proc.stderr


@pytest.mark.parametrize(
    "flags,message",
    [
        (
            ["--steps", "3", "--epochs", "2"],
            "--steps and --epochs (or their --set) both set the training budget; keep one",
        ),
        (
            ["--epochs", "2", "--set", "train.steps=3"],
            "--steps and --epochs (or their --set) both set the training budget; keep one",
        ),
        (["--no-holdout", "--val-ratio", "0.2"], "both set train.val_ratio; keep one"),
        (["--epochs", "-1"], "--epochs"),
    ],
)
def test_budget_flags_that_contradict_are_one_error_line(flags, message, data, tmp_path, capsys):
    assert train_main(["--data", str(data), "--out", str(tmp_path / "run"), "--no-progress", *SET_SMALL, *flags]) == 2
    assert message in one_error_line(capsys.readouterr().err)
    assert not (tmp_path / "run" / "config.json").exists()


def test_the_paper_presets_follow_the_papers_budget_and_steps_give_way():
    from dssp_train.cli.train import build_parser, config_from_args

    for preset, epochs in (("metaworld", 1000), ("adroit", 3000), ("robotwin", 3000)):
        config = config_from_args(build_parser().parse_args(["--data", "d", "--out", "o", "--preset", preset]))
        assert config.train.epochs == epochs and config.train.val_ratio == 0.0 and config.model.denoiser_mlp == "gated"
        assert (
            config.model.action_alignment == "dp3"
            and config.model.n_action_steps == config.model.horizon - config.model.n_obs_steps + 1
        )
    config = config_from_args(
        build_parser().parse_args(["--data", "d", "--out", "o", "--preset", "adroit", "--steps", "50"])
    )
    assert config.train.steps == 50 and config.train.epochs == 0  # asked-for steps replace the preset's epochs


# ----------------------------------------------------------------- ablations
ABLATIONS = [
    (["--no-history"], "use_history", False),
    (["--no-timestep-decoupling"], "timestep_decoupled", False),
    (["--no-recent-states"], "use_recent_states", False),
    (["--no-dynamics-loss"], "dynamics_weight", 0.0),
    (["--history-backbone", "transformer"], "history_backbone", "transformer"),
    (["--history-window", "5"], "history_window", 5),
]


@pytest.mark.parametrize("flags,field,value", ABLATIONS, ids=[a[0][0] for a in ABLATIONS])
def test_ablation_flags_train_and_land_in_config(flags, field, value, data, tmp_path, capsys):
    out = tmp_path / "run"
    assert (
        train_main(["--data", str(data), "--out", str(out), "--steps", "3", "--no-progress", *SET_SMALL, *flags]) == 0
    )
    summary = json.loads(capsys.readouterr().out)
    assert summary["step"] == 3 and math.isfinite(summary["val_action_mse"])
    model = json.loads((out / "config.json").read_text())["model"]
    assert model[field] == value
    defaults = load_preset("tiny").model
    for name, default in (
        ("use_history", True),
        ("timestep_decoupled", True),
        ("use_recent_states", True),
        ("history_backbone", "mamba"),
        ("history_window", 0),
        ("dynamics_weight", defaults.dynamics_weight),
    ):
        if name != field:
            assert model[name] == default, name

    with safe_open(str(out / "model.safetensors"), "pt") as f:
        keys = set(f.keys())
    history = {k for k in keys if k.startswith("history_encoder.")}
    dynamics = {k for k in keys if k.startswith("dynamics.")}
    assert bool(history) == (field != "use_history")
    assert bool(dynamics) == (field not in ("use_history", "dynamics_weight"))
    if field == "history_backbone":
        assert any("self_attn" in k for k in history) and not any("A_log" in k for k in history)
    elif history:
        assert any("A_log" in k for k in history)
    rows = read_log(out / "log.jsonl")
    train = [r for r in rows if r["kind"] == "train"]
    assert [r["step"] for r in train] == [1, 2, 3]
    if field in ("use_history", "dynamics_weight"):
        assert all(r["dynamics"] == 0 and r["loss"] == r["diffusion"] for r in train)
        assert not any(DYNAMICS_KEYS & set(r) for r in train)
    else:
        assert all(r["dynamics"] > 0 and DYNAMICS_KEYS <= set(r) for r in train)


# ---------------------------------------------------------------- dssp-params
def test_params_total_equals_the_models_parameter_count(capsys):
    assert params_main(["--preset", "robotwin"]) == 0
    out = capsys.readouterr().out
    assert "S=14, A=14" in out.splitlines()[0]
    totals = [line for line in out.splitlines() if line.split() and line.split()[0] == "total"]
    assert len(totals) == 1
    printed = int(totals[0].split()[1].replace(",", ""))

    config = load_preset("robotwin")
    config.model.state_dim = config.model.action_dim = 14
    expected = sum(p.numel() for p in DSSPPolicy(config.model).parameters())
    assert printed == expected
    assert re.search(rf"{expected / 1e6:.2f}\s*$", totals[0])
    lines = out.splitlines()
    end = lines.index(totals[0])
    rows = [line for line in lines[2:end] if line.split()]
    assert sum(int(re.findall(r"([\d,]+)\s+[\d.]+\s*$", r)[0].replace(",", "")) for r in rows) == expected
    # the paper's size: the preset's block (Mamba + GatedMLP) lands within 3 % of 44.3 M; every alternative is listed
    variants = {tuple(line.split()[:2]): line for line in lines[end + 2 :]}
    assert set(variants) == {(b, m) for b in ("mamba", "transformer") for m in ("none", "gated", "dit")}
    own = variants[("mamba", "gated")]
    assert own.endswith("<- this config") and abs(expected / 44.3e6 - 1) <= 0.03
    assert float(own.split()[2]) == pytest.approx(expected / 1e6, abs=0.006)


def test_params_unknown_preset_is_one_error_line(capsys):
    assert params_main(["--preset", "nosuch"]) == 2
    assert "unknown preset" in one_error_line(capsys.readouterr().err)

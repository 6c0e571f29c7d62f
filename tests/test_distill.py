"""dssp-distill: a few-step student of a trained run — its objectives, its run directory, its export and its refusals."""

import json

import pytest
import torch
from conftest import one_error_line

from dssp_train.cli.distill import main as distill_main
from dssp_train.config import DiffusionConfig
from dssp_train.model.scheduler import DiffusionSchedule
from dssp_train.training.checkpoint import load_policy
from dssp_train.training.distillation import ENCODER_PARTS

FAST = ["--batch-size", "8", "--no-progress"]


@pytest.fixture(scope="module")
def teacher(tmp_path_factory):
    """A tiny teacher trained a little longer than the shared one, so that its 10-step sampler is not the noise."""
    from dssp_train.cli.train import main as train_main
    from dssp_train.data.synthetic import write_tap_count_dataset

    root = tmp_path_factory.mktemp("teacher")
    data = write_tap_count_dataset(root / "tap.zarr", 6, seed=0, n_points=32)
    assert (
        train_main(
            [
                "--data",
                str(data),
                "--out",
                str(root / "run"),
                "--preset",
                "tiny",
                "--steps",
                "60",
                "--set",
                "train.val_every=60",
                "--set",
                "model.d_model=32",
                "--no-progress",
            ]
        )
        == 0
    )
    return root / "run", data


def teacher_gap(policy, teacher, data, steps: int) -> float:
    """MSE (normalised units) of ``policy``'s chunks against the teacher's 10-step chunks, same windows and noise."""
    from dssp_data.replay_buffer import ReplayBuffer

    ep = ReplayBuffer.load(data).episode(0)
    pc, pos = torch.from_numpy(ep.point_cloud), torch.from_numpy(ep.state)
    starts = torch.arange(0, 36, 3)
    noise = torch.randn(
        (len(starts), policy.cfg.horizon, policy.cfg.action_dim), generator=torch.Generator().manual_seed(3)
    )
    with torch.no_grad():
        prefix, _ = teacher.window_prefix(*teacher.encode_trajectory(pc, pos), starts)
        want = teacher.sample_normalized(prefix, noise)
        got = policy.sample_normalized(
            policy.window_prefix(*policy.encode_trajectory(pc, pos), starts)[0], noise, steps
        )
    return float((got - want).pow(2).mean())


@pytest.mark.parametrize("num_steps", [1, 2, 10])
def test_per_sample_steps_are_the_ddim_step(num_steps):
    """predicted_x0_eps + ddim_jump, batched over timesteps, is the scheduler's DDIM step at every timestep."""
    for prediction_type in ("sample", "epsilon"):
        schedule = DiffusionSchedule(DiffusionConfig(prediction_type=prediction_type, timestep_spacing="trailing"))
        gen = torch.Generator().manual_seed(num_steps)
        ts = schedule.inference_timesteps(num_steps)
        x, out = torch.randn((len(ts), 4, 3), generator=gen), 1.5 * torch.randn((len(ts), 4, 3), generator=gen)
        t = torch.tensor(ts)
        prev = t - schedule.cfg.num_train_timesteps // num_steps
        batched = schedule.ddim_jump(*schedule.predicted_x0_eps(out, x, t), prev.clamp(min=-1))
        for i, ti in enumerate(ts):
            one = schedule.ddim_step(out[i : i + 1], ti, x[i : i + 1], num_steps)
            assert torch.allclose(batched[i : i + 1], one, atol=1e-6)


@pytest.mark.parametrize("method", ["consistency", "trajectory"])
def test_a_student_is_an_ordinary_run_of_the_teacher_sampling_in_k_steps(method, teacher, tmp_path, capsys):
    run, data = teacher
    out = tmp_path / "student"
    assert (
        distill_main(
            ["--teacher", str(run), "--steps", "1", "--out", str(out), "--method", method, "--train-steps", "6", *FAST]
        )
        == 0
    )
    config = json.loads((out / "config.json").read_text())
    assert config["distill"] == {
        "teacher": str(run.resolve()),
        "method": method,
        "teacher_steps": 10,
        "freeze_encoders": True,
    }
    assert (
        config["model"]["diffusion"]["num_inference_steps"] == 1
        and config["model"]["diffusion"]["timestep_spacing"] == "trailing"
    )
    assert config["dataset"] == str(data) and config["train"]["steps"] == 6
    rows = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    assert {"distill", "teacher_mse"} <= set(rows[0]) and (out / "loss.png").read_bytes()[:4] == b"\x89PNG"
    student, _ = load_policy(out)
    theirs, _ = load_policy(run)
    mine_sd, their_sd = student.state_dict(), theirs.state_dict()
    frozen = [k for k in mine_sd if k.split(".")[0] in ENCODER_PARTS or k.startswith("normalizers")]
    assert frozen and all(torch.equal(mine_sd[k], their_sd[k]) for k in frozen)  # the teacher's encoders, unchanged
    assert any(
        not torch.equal(mine_sd[k], their_sd[k]) for k in mine_sd if k.startswith("denoiser")
    )  # its denoiser trained
    assert student.schedule.inference_timesteps() == [99]


def test_trajectory_distillation_brings_one_step_to_the_teachers_chunks(teacher, tmp_path):
    run, data = teacher
    theirs, _ = load_policy(run)
    out = tmp_path / "k1"
    assert (
        distill_main(
            [
                "--teacher",
                str(run),
                "--steps",
                "1",
                "--out",
                str(out),
                "--method",
                "trajectory",
                "--train-steps",
                "60",
                "--lr",
                "1e-3",
                "--batch-size",
                "16",
                "--no-progress",
            ]
        )
        == 0
    )
    student, _ = load_policy(out)
    untrained = load_policy(run)[0]
    untrained.cfg.diffusion.timestep_spacing = "trailing"  # the teacher itself, sampled in one trailing step
    before = teacher_gap(untrained, theirs, data, 1)
    after = teacher_gap(student, theirs, data, 1)
    assert after < 0.5 * before, (before, after)


def test_the_student_exports_with_parity_and_its_k_in_the_manifest(teacher, tmp_path):
    from dssp_deploy.onnx_policy import OnnxPolicy
    from export.to_onnx import main as export_main

    run, _ = teacher
    out, model = tmp_path / "k2", tmp_path / "k2_model"
    assert distill_main(["--teacher", str(run), "--steps", "2", "--out", str(out), "--train-steps", "4", *FAST]) == 0
    export = [str(out), "-o", str(model), "--quantize", "none", "--no-fused"]
    assert export_main(export) == 0  # parity is proven, as on every export
    manifest = json.loads((model / "dssp_model.json").read_text())
    assert manifest["contract"]["ddim_timesteps"] == [99, 49]  # K = 2
    policy = OnnxPolicy(model, threads=1)
    assert policy.contract.denoise_steps == 2


def test_the_teacher_exports_at_k_1_from_the_noise_level_with_parity(teacher, tmp_path):
    """The undistilled baseline: the teacher's own weights at one trailing step ([99]); leading spacing would give [0]."""
    from export.to_onnx import main as export_main

    run, _ = teacher
    model = tmp_path / "k1"
    assert (
        export_main(
            [
                str(run),
                "-o",
                str(model),
                "--denoise-steps",
                "1",
                "--timestep-spacing",
                "trailing",
                "--quantize",
                "none",
                "--no-fused",
            ]
        )
        == 0
    )
    manifest = json.loads((model / "dssp_model.json").read_text())
    assert (
        manifest["contract"]["ddim_timesteps"] == [99]
        and manifest["model_config"]["diffusion"]["timestep_spacing"] == "trailing"
    )
    assert (
        json.loads((run / "config.json").read_text())["model"]["diffusion"]["timestep_spacing"] == "leading"
    )  # run untouched


def test_a_stopped_student_resumes_with_its_own_config(teacher, tmp_path):
    run, _ = teacher
    out = tmp_path / "student"
    assert distill_main(["--teacher", str(run), "--steps", "1", "--out", str(out), "--train-steps", "4", *FAST]) == 0
    assert distill_main(["--out", str(out), "--resume", "--train-steps", "6", "--no-progress"]) == 0
    state = json.loads((out / "checkpoint" / "trainer_state.json").read_text())
    assert state["step"] == 6
    assert json.loads((out / "config.json").read_text())["distill"]["teacher"] == str(run.resolve())


@pytest.mark.parametrize(
    "args,message",
    [
        (lambda run, out: ["--teacher", str(run), "--steps", "10", "--out", out], "not fewer than the teacher's 10"),
        (lambda run, out: ["--teacher", str(run) + "_missing", "--steps", "1", "--out", out], "_missing"),
        (lambda run, out: ["--steps", "1", "--out", out], "needs --teacher RUN_DIR and --steps K"),
        (lambda run, out: ["--teacher", str(run), "--steps", "0", "--out", out], "num_inference_steps"),
    ],
)
def test_bad_requests_are_one_error_line(args, message, teacher, tmp_path, capsys):
    run, _ = teacher
    assert distill_main(args(run, str(tmp_path / "s")) + FAST) == 2
    assert message in one_error_line(capsys.readouterr().err)
    assert not (tmp_path / "s").exists()


def test_a_student_is_not_a_teacher_and_resume_keeps_its_config(teacher, tmp_path, capsys):
    run, _ = teacher
    out = tmp_path / "student"
    assert distill_main(["--teacher", str(run), "--steps", "1", "--out", str(out), "--train-steps", "2", *FAST]) == 0
    capsys.readouterr()
    assert distill_main(["--teacher", str(out), "--steps", "1", "--out", str(tmp_path / "s2"), *FAST]) == 2
    assert "is itself a distilled student" in one_error_line(capsys.readouterr().err)
    assert (
        distill_main(["--out", str(out), "--resume", "--method", "trajectory", "--train-steps", "4", "--no-progress"])
        == 2
    )
    assert "only --train-steps may change (got --method)" in one_error_line(capsys.readouterr().err)
    assert distill_main(["--out", str(run), "--resume", "--train-steps", "100", "--no-progress"]) == 2
    assert "not a distilled student" in one_error_line(capsys.readouterr().err)


@pytest.mark.slow
def test_the_distillation_study_writes_its_report(tmp_path, capsys):
    from studies.distill_study import REPORT_NAME
    from studies.distill_study import main as study_main

    work, report = tmp_path / "work", tmp_path / "report"
    assert study_main(["--work", str(work), "--report", str(report), "--quick", "--workers", "2"]) == 0
    md = (report / f"{REPORT_NAME}.md").read_text()
    assert "| teacher (DDIM, 10 steps) | 10 |" in md and "| student: trajectory distillation | 1 |" in md
    assert "| teacher, DDIM at K trailing steps (no distillation) | 1 |" in md
    data = json.loads((report / f"{REPORT_NAME}.json").read_text())
    assert set(data["evals"]) == {"tap_teacher_k10", "tap_ddim_k1", "tap_trajectory_k1"}
    latency = data["summary"]["latency"]
    assert set(latency) == {"10", "1"} and latency["10"]["of_k10"] == 1.0 and latency["1"]["chunk_ms"] > 0
    assert "## The chunk on the `tiny` preset" in md and (report / f"{REPORT_NAME}.png").read_bytes()[:4] == b"\x89PNG"
    manifest = json.loads((work / "models" / "tap_trajectory_k1" / "dssp_model.json").read_text())
    assert manifest["contract"]["ddim_timesteps"] == [99]
    seconds = {f.stem for f in (report / "record" / "seconds").glob("*.seconds")}
    assert seconds == {p.stem for p in (work / "done").glob("*.json")} and "latency_profile_k1" in seconds
    capsys.readouterr()
    assert study_main(["--work", str(work), "--report", str(report), "--quick", "--force"]) == 0  # resumes: all done
    assert "every cell recorded" in capsys.readouterr().out
    assert {f.stem for f in (report / "record" / "evals").glob("*.json")} == {
        *data["evals"],
        "latency_k10",
        "latency_k1",
    }
    # another machine without the work directory trains nothing: the report's record holds every evaluation
    assert study_main(["--work", str(tmp_path / "elsewhere"), "--report", str(report), "--quick", "--force"]) == 0
    assert not (tmp_path / "elsewhere" / "runs").exists()
    assert json.loads((report / f"{REPORT_NAME}.json").read_text())["evals"] == data["evals"]
    # the report from the record alone: a cell not run yet is listed as pending
    (report / "record" / "evals" / "tap_ddim_k1.json").unlink()
    assert (
        study_main(
            ["--work", str(tmp_path / "elsewhere"), "--report", str(report), "--quick", "--force", "--report-only"]
        )
        == 0
    )
    assert (
        "**Partial report**: 1 cell(s) of the plan are pending (not run yet): `tap_ddim_k1`"
        in (report / f"{REPORT_NAME}.md").read_text()
    )
    assert json.loads((report / f"{REPORT_NAME}.json").read_text())["pending"] == ["tap_ddim_k1"]


def test_the_study_takes_its_teachers_from_a_simulation_study(tmp_path, monkeypatch):
    import studies.distill_study as study
    from dssp_core.errors import DSSPError

    seen = []

    def fake_run_and_keep(work, record, stage_list, workers, what, seconds=False):
        """Keeps a stand-in evaluation of every stage that makes one, as if each had run."""
        seen.extend(stage_list)
        for s in stage_list:
            for output in s.outputs:
                (record / output).parent.mkdir(parents=True, exist_ok=True)
                (record / output).write_text("{}")

    monkeypatch.setattr(study, "run_and_keep", fake_run_and_keep)
    sim_work = tmp_path / "sim"
    with pytest.raises(DSSPError, match="is not a finished training of the study"):
        study.run_study(study.QUICK_PLAN, ["tap"], tmp_path / "work", tmp_path / "record", 1, teachers=sim_work)
    assert not (tmp_path / "work").exists()  # refused before anything was written
    teacher = sim_work / "runs" / "tap_dssp_s0"
    teacher.mkdir(parents=True)
    (teacher / "model.safetensors").write_bytes(b"")
    (sim_work / "done").mkdir()
    (sim_work / "done" / "train_tap_dssp_s0.json").write_text('{"seconds": 1.0}')
    study.run_study(study.QUICK_PLAN, ["tap"], tmp_path / "work2", tmp_path / "record", 1, teachers=sim_work)
    evals, latency, _ = study.recorded_results(study.QUICK_PLAN, tmp_path / "record")
    assert set(evals) == {"tap_teacher_k10", "tap_ddim_k1", "tap_trajectory_k1"} and latency == {}
    assert not any(s.name.startswith(("collect", "train")) for s in seen)  # nothing collected or trained again
    distill = next(s for s in seen if s.name.startswith("distill"))
    assert distill.entry == "dssp_train.cli.distill:main" and distill.argv[distill.argv.index("--teacher") + 1] == str(
        teacher.resolve()
    )
    exports = {s.name: s.argv[0] for s in seen if s.name.startswith("export")}
    assert exports["export_tap_teacher_k10"] == exports["export_tap_ddim_k1"] == str(teacher.resolve())
    assert not (tmp_path / "work2" / "data").exists()


def test_the_profiles_run_alone_after_every_other_stage(tmp_path):
    import studies.distill_study as study

    stages = study.stages(study.QUICK_PLAN, ["tap", "latency"], tmp_path / "record")
    names = [s.name for s in stages]
    first, second = (next(s for s in stages if s.name == f"latency_profile_k{k}") for k in (10, 1))
    assert set(first.after) == set(names) - {first.name, second.name} and second.after == (first.name,)
    assert first.entry == "dssp_deploy.profile:main" and first.outputs == ("evals/latency_k10.json",)

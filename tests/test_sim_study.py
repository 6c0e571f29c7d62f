"""The first simulation study (``python -m studies.sim_study``): its stages on the stage runner, its record and the
report rebuilt from it, resuming on another machine, and splitting the study across processes."""

import dataclasses
import json
import shutil

import pytest
from conftest import FIXTURES, STUDY_ENTRIES

from studies import sim_study
from studies.runner import Runner


@pytest.mark.slow
def test_the_study_command_writes_its_report(tmp_path, capsys):
    from studies.sim_study import REPORT_NAME
    from studies.sim_study import main as study_main

    work, report = tmp_path / "work", tmp_path / "report"
    assert study_main(["--work", str(work), "--report", str(report), "--quick", "--workers", "2"]) == 0
    md = (report / f"{REPORT_NAME}.md").read_text()
    assert "| tap | DSSP (full history) |" in md and "| tap | reactive baseline" in md and "| 0.1 |" in md
    assert "| window T_h = 3 | " in md and "| full (DSSP) | " in md  # the ablation table
    assert (report / f"{REPORT_NAME}.png").read_bytes()[:4] == b"\x89PNG"
    data = json.loads((report / f"{REPORT_NAME}.json").read_text())
    assert (
        set(data["evals"]) == {"tap_dssp_s0", "tap_reactive_s0", "tap_window3_s0"}
        and data["summary"]["tap"]["dssp"]["n"] == 1
    )
    rms = data["evals"]["tap_dssp_s0"]["z_rms"]  # σ is also read against the tokens' own scale
    assert rms > 0 and f"| 0.1 | {0.1 / rms:.2f} |" in md
    assert set(data["robustness"]) == {f"tap_{v}_s0_noise0.1" for v in ("dssp", "window3", "reactive")}
    done = sorted(p.stem for p in (work / "done").glob("*.json"))
    assert len(done) == 13  # each stage's time (its done marker), summed by the report
    record = report / "record"  # every evaluation and stage time, kept beside the report
    assert sorted(f.stem for f in (record / "evals").glob("*.json")) == sorted([*data["evals"], *data["robustness"]])
    assert sorted(f.name for f in (record / "seconds").iterdir()) == [f"{name}.seconds" for name in done]
    # another machine, without the work directory, resumes from the record: nothing is collected, trained or evaluated again
    capsys.readouterr()
    elsewhere = tmp_path / "elsewhere"
    assert study_main(["--work", str(elsewhere), "--report", str(report), "--quick", "--force"]) == 0
    out = capsys.readouterr().out
    assert out.count(": recorded") == 6 and "0 stage(s)" in out and not (elsewhere / "data").exists()
    assert json.loads((report / f"{REPORT_NAME}.json").read_text())["evals"] == data["evals"]
    # a report from the record alone: an evaluation not run yet is listed as pending
    (record / "evals" / "tap_window3_s0_noise0.1.json").unlink()
    assert study_main(["--work", str(elsewhere), "--report", str(report), "--quick", "--force", "--report-only"]) == 0
    md = (report / f"{REPORT_NAME}.md").read_text()
    assert "**Partial report**: 1 evaluation(s) of the plan are pending (not run yet): `tap_window3_s0_noise0.1`" in md
    assert "| 0.1 | " in md and "pending |" in md
    assert json.loads((report / f"{REPORT_NAME}.json").read_text())["pending"] == ["tap_window3_s0_noise0.1"]
    assert study_main(["--work", str(elsewhere), "--report", str(tmp_path / "empty"), "--quick", "--report-only"]) == 2
    assert "holds no evaluation of this plan" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        study_main(["--work", str(work), "--report", str(report), "--quick", "--tasks", "swap"])
    assert "--tasks: swap not in the plan (tap)" in capsys.readouterr().err


QUICK_RECORD = FIXTURES / "sim_study_quick_record"
"""The record of one whole quick-plan study (``python -m studies.sim_study --work W --report R --quick``, then
R/record): what the long end-to-end test above produces, kept so that the record's uses are tested in seconds."""


def test_the_study_resumes_from_its_record_and_reports_from_it(tmp_path, capsys):
    from studies.sim_study import REPORT_NAME
    from studies.sim_study import main as study_main

    report = tmp_path / "report"
    shutil.copytree(QUICK_RECORD, report / "record")
    recorded = sorted(f.stem for f in (report / "record" / "evals").glob("*.json"))
    # a machine without the work directory resumes from the record: nothing is collected, trained or evaluated
    elsewhere = tmp_path / "elsewhere"
    assert study_main(["--work", str(elsewhere), "--report", str(report), "--quick", "--force"]) == 0
    out = capsys.readouterr().out
    assert out.count(": recorded") == 6 and "0 stage(s)" in out and not (elsewhere / "data").exists()
    md = (report / f"{REPORT_NAME}.md").read_text()
    assert "| tap | DSSP (full history) |" in md and "| tap | reactive baseline" in md and "| 0.1 |" in md
    assert "| window T_h = 3 | " in md and "| full (DSSP) | " in md  # the ablation table
    assert (report / f"{REPORT_NAME}.png").read_bytes()[:4] == b"\x89PNG"
    data = json.loads((report / f"{REPORT_NAME}.json").read_text())
    assert sorted([*data["evals"], *data["robustness"]]) == recorded and "pending" not in md.lower()
    for name, row in data["evals"].items():  # the report's figures are the record's
        assert row == json.loads((report / "record" / "evals" / f"{name}.json").read_text())
    rms = data["evals"]["tap_dssp_s0"]["z_rms"]
    assert rms > 0 and f"| 0.1 | {0.1 / rms:.2f} |" in md
    # the compute time is the record's stage times (kept from the machine that ran the stages)
    minutes = sum(float(f.read_text()) for f in (report / "record" / "seconds").glob("*.seconds")) / 60
    assert f"({minutes:.0f} min of stage time" in md
    # a report from the record alone: an evaluation not run yet is listed as pending
    (report / "record" / "evals" / "tap_window3_s0_noise0.1.json").unlink()
    assert study_main(["--work", str(elsewhere), "--report", str(report), "--quick", "--force", "--report-only"]) == 0
    md = (report / f"{REPORT_NAME}.md").read_text()
    assert "**Partial report**: 1 evaluation(s) of the plan are pending (not run yet): `tap_window3_s0_noise0.1`" in md
    assert json.loads((report / f"{REPORT_NAME}.json").read_text())["pending"] == ["tap_window3_s0_noise0.1"]
    assert study_main(["--work", str(elsewhere), "--report", str(tmp_path / "empty"), "--quick", "--report-only"]) == 2
    assert "holds no evaluation of this plan" in capsys.readouterr().err
    # only the missing evaluation's stages would run: its model's training and export, and the evaluation
    names = [s.name for s in sim_study.stages(sim_study.QUICK_PLAN, ["tap"], report / "record")]
    assert names == ["collect_tap", "train_tap_window3_s0", "export_tap_window3_s0", "eval_tap_window3_s0_noise0.1"]


def test_the_stages_are_calls_of_entry_points_in_dependency_order(tmp_path):
    stages = sim_study.stages(sim_study.QUICK_PLAN, ["tap"], tmp_path / "record")
    by_name = {s.name: s for s in stages}
    assert len(stages) == 13 and stages[0].name == "collect_tap"
    assert {s.entry for s in stages} == {"dssp_sim.sim_cli:main", "dssp_train.cli.train:main", "export.to_onnx:main"}
    assert by_name["export_tap_window3_s0"].after == ("train_tap_window3_s0",)
    noisy = by_name["eval_tap_dssp_s0_noise0.1"]
    assert noisy.after == ("export_tap_dssp_s0",) and noisy.outputs == ("evals/tap_dssp_s0_noise0.1.json",)
    assert noisy.argv[noisy.argv.index("--noise") + 1] == "0.1" and noisy.argv[noisy.argv.index("--threads") + 1] == "1"
    assert (
        "--history-window" in by_name["train_tap_window3_s0"].argv
        and "--no-history" in by_name["train_tap_reactive_s0"].argv
    )


def test_a_training_stopped_halfway_is_resumed_not_taken_for_done(tmp_path):
    train = next(
        s for s in sim_study.stages(sim_study.PLAN, ["tap"], tmp_path / "record") if s.name == "train_tap_dssp_s0"
    )
    assert "--force" in train.argv and "--preset" in train.argv and "--resume" not in train.argv
    assert (
        "--resume" in train.resume
        and "--force" not in train.resume
        and train.resume[train.resume.index("--out") + 1] == "runs/tap_dssp_s0"
    )
    work = tmp_path / "work"
    (work / train.started).mkdir(parents=True)  # a checkpoint, but the stage never finished (no done marker)
    assert train.started == "runs/tap_dssp_s0/checkpoint"
    # the call it makes, not the training
    stage = dataclasses.replace(train, entry=f"{STUDY_ENTRIES}:record_call", after=())
    Runner(work, say=lambda _: None).run([stage])
    assert [json.loads(line) for line in (work / "calls.jsonl").read_text().splitlines()] == [list(train.resume)]
    assert Runner(work, say=lambda _: None).run([stage]) == {}  # finished: not run again
    assert len((work / "calls.jsonl").read_text().splitlines()) == 1


def test_a_collection_stopped_halfway_is_collected_again_not_appended_to(tmp_path):
    collect = sim_study.stages(sim_study.QUICK_PLAN, ["tap"], tmp_path / "record")[0]
    assert collect.name == "collect_tap" and collect.argv[collect.argv.index("--out") + 1] == "data/tap.zarr"
    assert collect.clean == ("data/tap.zarr",)
    work = tmp_path / "work"
    partial = work / "data" / "tap.zarr"
    (partial / "data").mkdir(parents=True)  # a collection interrupted before its stage finished (no done marker)
    stage = dataclasses.replace(collect, entry=f"{STUDY_ENTRIES}:write_marker", argv=("data/tap.zarr/meta",))
    Runner(work, say=lambda _: None).run([stage])
    assert sorted(p.name for p in partial.iterdir()) == ["meta"]  # removed before the stage: collect would append to it
    assert Runner(work, say=lambda _: None).run([stage]) == {}
    assert sorted(p.name for p in partial.iterdir()) == ["meta"]  # a finished collection stays


def test_seeds_split_a_tasks_models_across_processes(tmp_path, capsys):
    plan = {**sim_study.QUICK_PLAN, "seeds": {"tap": [0, 1]}, "ablation_seeds": {"tap": [1]}}
    trained = [
        s.name for s in sim_study.stages(plan, ["tap"], tmp_path / "record", seeds=[1]) if s.name.startswith("train")
    ]
    assert trained == ["train_tap_dssp_s1", "train_tap_reactive_s1", "train_tap_window3_s1"]
    trained = [
        s.name for s in sim_study.stages(plan, ["tap"], tmp_path / "record", seeds=[0]) if s.name.startswith("train")
    ]
    assert trained == ["train_tap_dssp_s0", "train_tap_reactive_s0"]
    with pytest.raises(SystemExit):
        sim_study.main(["--work", str(tmp_path / "w"), "--quick", "--seeds", "7"])
    assert "--seeds [7]: the plan trains seeds [0]" in capsys.readouterr().err

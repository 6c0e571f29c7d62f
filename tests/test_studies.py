"""The studies' foundations: the stage runner, the protocol's seed ranges and frozen plan, and the statistics."""

from __future__ import annotations

import itertools
import json
import os
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pytest
from conftest import STUDY_ENTRIES
from scipy.stats import binomtest
from waiting import wait_for

from dssp_core.errors import DSSPError
from studies import protocol
from studies.runner import Runner, Stage
from studies.stats import cluster_bootstrap, describe_p, paired_difference, paired_exact_test


def test_stages_run_in_order_in_their_folder_with_one_thread_and_are_not_run_twice(tmp_path):
    work = tmp_path / "work"
    stages = [
        Stage("second", f"{STUDY_ENTRIES}:needs", ("out/a.json",), after=("first",)),
        Stage("first", f"{STUDY_ENTRIES}:write_marker", ("out/a.json",)),
        Stage("other", f"{STUDY_ENTRIES}:write_marker", ("out/b.json", "x")),
    ]
    said: list[str] = []
    ran = Runner(work, workers=2, say=said.append).run(stages)
    assert set(ran) == {"first", "second", "other"}
    a = json.loads((work / "out/a.json").read_text())
    assert a["omp"] == "1" and Path(a["cwd"]) == work.resolve()
    assert "wrote out/a.json" in (work / "logs/first.log").read_text()
    again = Runner(work, workers=2, say=said.append).run(stages)
    assert again == {} and "  first: done before" in said
    assert json.loads((work / "done/first.json").read_text())["argv"] == ["out/a.json"]


def test_each_evaluation_is_kept_in_the_record_as_soon_as_its_stage_finishes(tmp_path):
    from studies.evaluations import run_and_keep

    work, record = tmp_path / "work", tmp_path / "record"
    kept = record / "evals/a.json"
    stages = [
        Stage("first", f"{STUDY_ENTRIES}:write_marker", ("evals/a.json",), outputs=("evals/a.json",)),
        # runs only once the first is done, and fails unless the record already holds the first's evaluation
        Stage("second", f"{STUDY_ENTRIES}:needs", (str(kept),), after=("first",)),
    ]
    run_and_keep(work, record, stages, workers=1, what="a test", seconds=True)
    assert set(json.loads(kept.read_text())) == {"code_commit"}  # an evaluation's fields; this one has none
    assert (record / "seconds/first.seconds").is_file() and (record / "seconds/second.seconds").is_file()


def test_a_failed_stage_stops_the_study_with_one_line_and_runs_again_next_time(tmp_path):
    work = tmp_path / "work"
    stages = [
        Stage("bad", f"{STUDY_ENTRIES}:fail", ("x",)),
        Stage("after_bad", f"{STUDY_ENTRIES}:write_marker", ("out/c.json",), after=("bad",)),
    ]
    with pytest.raises(DSSPError) as info:
        Runner(work, say=lambda _: None).run(stages)
    message = str(info.value)
    assert (
        "stage bad" in message and "exit code 3" in message and "something broke: x" in message and "\n" not in message
    )
    assert not (work / "done/bad.json").exists() and not (work / "out/c.json").exists()


def test_with_echo_each_stage_is_shown_line_by_line_behind_its_name(tmp_path):
    said: list[str] = []
    Runner(tmp_path, workers=2, echo=True, say=said.append).run(
        [Stage("a", f"{STUDY_ENTRIES}:chatter", ()), Stage("b", f"{STUDY_ENTRIES}:write_marker", ("m.json",))]
    )
    assert [line for line in said if line.startswith("[a]")] == [
        "[a] one",
        "[a] bar 1",
        "[a] bar 2",
        "[a] 1",
        "[a] no newline",
    ]
    assert "[b] wrote m.json" in said
    assert (tmp_path / "logs/a.log").read_bytes() == b"one\n\rbar 1\rbar 2\n1\nno newline"


def test_the_demo_stops_at_a_failed_stage_with_its_log_kept_outside_out(tmp_path, monkeypatch, capsys):
    import studies.demo as demo

    monkeypatch.setattr(
        demo,
        "stages",
        lambda *args: [
            Stage("first", f"{STUDY_ENTRIES}:write_marker", ("m.json",)),
            Stage("bad", f"{STUDY_ENTRIES}:fail", ("x",), after=("first",)),
            Stage("never", f"{STUDY_ENTRIES}:write_marker", ("n.json",), after=("bad",)),
        ],
    )
    out = tmp_path / "demo"
    assert demo.main(["--out", str(out), "--steps", "1", "--demos", "1", "--episodes", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: bad failed (exit 3); its log: ") and err.endswith(": something broke: x"), err
    assert "\n" not in err and not out.exists()  # --out, new, is gone
    kept = Path(err.split("its log: ")[1].split(": something broke")[0])
    assert kept.read_text() == "first line\nsomething broke: x\n"
    kept.unlink()


def test_the_demo_runs_its_stages_in_order_in_out(tmp_path):
    from studies.demo import VARIANTS, stages

    listed = stages(10, 3, 2, 0)
    names = [s.name for s in listed]
    assert names[0] == "collect" and len(names) == 1 + 3 * len(VARIANTS)
    for name in VARIANTS:  # each model: train after collect, export after train, evaluate after export
        by = {s.name: s for s in listed}
        assert by[f"train_{name}"].after == ("collect",) and by[f"export_{name}"].after == (f"train_{name}",)
        assert by[f"eval_{name}"].after == (f"export_{name}",) and f"evals/{name}.json" in by[f"eval_{name}"].argv
    assert "--no-history" in by["train_reactive"].argv and "--no-history" not in by["train_dssp"].argv


def test_a_stage_stopped_halfway_resumes_or_starts_clean(tmp_path):
    work = tmp_path / "work"
    (work / "partial").mkdir(parents=True)
    (work / "half.zarr").mkdir()
    (work / "half.zarr/junk").write_text("left by a collection stopped halfway")
    stages = [
        Stage(
            "train",
            f"{STUDY_ENTRIES}:write_marker",
            ("out/fresh.json",),
            resume=("out/resumed.json",),
            started="partial",
        ),
        Stage("collect", f"{STUDY_ENTRIES}:write_marker", ("half.zarr/new.json",), clean=("half.zarr",)),
    ]
    Runner(work, say=lambda _: None).run(stages)
    assert (work / "out/resumed.json").is_file() and not (work / "out/fresh.json").exists()
    assert sorted(p.name for p in (work / "half.zarr").iterdir()) == ["new.json"]
    with pytest.raises(DSSPError, match="inside its work folder"):
        Runner(work, say=lambda _: None).run(
            [Stage("escape", f"{STUDY_ENTRIES}:write_marker", ("y",), clean=("../outside",))]
        )


def test_stages_that_cannot_run_are_named(tmp_path):
    with pytest.raises(DSSPError, match="no stage makes"):
        Runner(tmp_path, say=lambda _: None).run(
            [Stage("a", f"{STUDY_ENTRIES}:write_marker", ("z",), after=("missing",))]
        )
    with pytest.raises(DSSPError, match="repeat"):
        Runner(tmp_path, say=lambda _: None).run(
            [Stage("a", f"{STUDY_ENTRIES}:fail", ()), Stage("a", f"{STUDY_ENTRIES}:fail", ())]
        )
    with pytest.raises(ValueError, match="plain file name"):
        Stage("a/b", f"{STUDY_ENTRIES}:fail", ())


# ---------------------------------------------------------------------------------------------- protocol
def test_the_seed_ranges_are_disjoint_and_every_model_sees_the_same_scenes():
    protocol.check_disjoint()
    demo, val, test = protocol.DEMO_SEEDS, protocol.VALIDATION_SEEDS, protocol.TEST_SEEDS
    assert not set(demo) & set(val) and not set(val) & set(test) and not set(demo) & set(test)
    assert protocol.split_seeds("test", 50) == list(range(10_000, 10_050)) == protocol.split_seeds("test", 50)
    with pytest.raises(DSSPError, match="unknown split"):
        protocol.split_seeds("train", 5)


def test_the_test_split_runs_only_the_frozen_plan(tmp_path):
    plan = {"tasks": {"tap": {"steps": 3000}}, "seeds": [0, 1, 2]}
    with pytest.raises(DSSPError, match="needs a frozen plan"):
        protocol.check_frozen(tmp_path, plan)
    digest = protocol.freeze_plan(tmp_path, plan)
    protocol.check_frozen(tmp_path, plan)
    assert protocol.freeze_plan(tmp_path, plan) == digest  # freezing again is a no-op
    tuned = {**plan, "seeds": [0, 1, 2, 3]}
    with pytest.raises(DSSPError, match="the plan changed since it was frozen"):
        protocol.check_frozen(tmp_path, tuned)
    with pytest.raises(DSSPError, match="a new study"):
        protocol.freeze_plan(tmp_path, tuned)
    frozen = json.loads((tmp_path / protocol.FROZEN_NAME).read_text())
    (tmp_path / protocol.FROZEN_NAME).write_text(json.dumps({**frozen, "task_definition": "0" * 16}))
    with pytest.raises(DSSPError, match="task definition changed"):
        protocol.check_frozen(tmp_path, plan)
    # the same plan frozen again on the changed definition needs a reason; the earlier freeze is kept with the tasks
    # tested on it, the new one says why, when and at which commit
    with pytest.raises(DSSPError, match=r"needs --reason TEXT"):
        protocol.freeze_plan(tmp_path, plan, tested=["tap"], reason="  ")
    when = datetime(2026, 12, 7, 8, 0, tzinfo=timezone.utc)
    assert protocol.freeze_plan(tmp_path, plan, tested=["tap"], reason="scorer fixed", now=lambda: when) == digest
    protocol.check_frozen(tmp_path, plan)
    refrozen = json.loads((tmp_path / protocol.FROZEN_NAME).read_text())
    assert refrozen["task_definition"] == protocol.task_definition_hash() and refrozen["reason"] == "scorer fixed"
    assert refrozen["at"] == "2026-12-07T08:00:00+00:00" and refrozen["commit"] == protocol.code_commit()
    assert refrozen["earlier"] == [{**frozen, "task_definition": "0" * 16, "tested": ["tap"]}]
    with pytest.raises(DSSPError, match="a new study"):  # still: never another plan
        protocol.freeze_plan(tmp_path, tuned)


def test_a_plan_fixed_before_any_run_can_be_frozen_into_a_new_record_folder(tmp_path):
    record = tmp_path / "reports" / "study" / "record"  # nothing there yet
    plan = {"tasks": ["reach"], "seeds": [0]}
    digest = protocol.freeze_plan(record, plan, definition="ab" * 8)
    frozen = json.loads((record / protocol.FROZEN_NAME).read_text())
    assert {k: frozen[k] for k in ("plan", "task_definition", "commit")} == {
        "plan": digest,
        "task_definition": "ab" * 8,
        "commit": protocol.code_commit(),
    }
    assert datetime.fromisoformat(frozen["at"]).tzinfo is not None  # when, in UTC
    protocol.check_frozen(record, plan, definition="ab" * 8)


def test_a_study_on_uncommitted_code_is_refused_unless_its_plan_is_quick(tmp_path, monkeypatch):
    monkeypatch.setattr(protocol, "code_commit", lambda: "ab" * 20 + "+changes")
    with pytest.raises(DSSPError, match="uncommitted changes .*commit them first"):
        protocol.note_provenance(tmp_path, {"a": 1}, "validation")
    assert not (tmp_path / "provenance_validation.json").exists()
    protocol.note_provenance(tmp_path, {"a": 1}, "validation", allow_changes=True)
    assert json.loads((tmp_path / "provenance_validation.json").read_text())[0]["commit"].endswith("+changes")


def test_provenance_names_the_task_the_code_and_the_machine():
    prov = protocol.provenance({"a": 1})
    assert len(prov["task_definition"]) == 16 and prov["plan"] == protocol.plan_hash({"a": 1})
    assert prov["commit"] == "unknown" or len(prov["commit"].split("+")[0]) == 40
    assert prov["machine"]["cores"] >= 1 and prov["machine"]["cpu"]


# ---------------------------------------------------------------------------------------------- statistics
def test_the_paired_test_with_one_seed_is_the_exact_mcnemar_test():
    rng = np.random.default_rng(1)
    a, b = rng.integers(0, 2, (1, 40)), rng.integers(0, 2, (1, 40))
    n10, n01 = int(((a == 1) & (b == 0)).sum()), int(((a == 0) & (b == 1)).sum())
    assert paired_exact_test(a, b) == pytest.approx(binomtest(n10, n10 + n01, 0.5).pvalue, rel=1e-12)


def test_the_paired_test_over_seeds_is_the_full_sign_flip_enumeration():
    rng = np.random.default_rng(2)
    a, b = rng.integers(0, 2, (3, 12)), rng.integers(0, 2, (3, 12))
    d = a.sum(0) - b.sum(0)
    extreme = sum(abs(np.dot(signs, d)) >= abs(d.sum()) for signs in itertools.product([-1, 1], repeat=12))
    assert paired_exact_test(a, b) == pytest.approx(extreme / 2**12, rel=1e-12)
    assert paired_exact_test(a, a) == 1.0
    assert paired_exact_test(np.ones((3, 20)), np.zeros((3, 20))) == pytest.approx(2 / 2**20)


def test_the_cluster_bootstrap_is_wider_than_pooling_when_seeds_differ_and_is_deterministic():
    from dssp_sim.evaluate import wilson_interval

    outcomes = np.zeros((3, 50), int)
    outcomes[0] = 1  # one training seed succeeds everywhere, the others never: the seeds are what varies
    mean, lo, hi = cluster_bootstrap(outcomes)
    w_lo, w_hi = wilson_interval(50, 150)
    assert mean == pytest.approx(1 / 3) and hi - lo > 2 * (w_hi - w_lo)
    assert cluster_bootstrap(outcomes) == (mean, lo, hi)
    d, dlo, dhi = paired_difference(np.ones((3, 30)), np.zeros((3, 30)))
    assert (d, dlo, dhi) == (1.0, 1.0, 1.0)
    with pytest.raises(ValueError, match="share their scenes"):
        paired_difference(np.ones((3, 30)), np.ones((3, 31)))
    # five training seeds against three: each model resamples its own seeds, the scenes stay paired
    five = np.ones((5, 30))
    five[0] = 0  # one of five seeds fails everywhere: the interval spreads over which seeds are drawn
    d, dlo, dhi = paired_difference(five, np.zeros((3, 30)))
    assert d == pytest.approx(0.8) and 0 < dlo < 0.8 < dhi + 1e-12 and dhi == 1.0
    assert describe_p(0.2) == "p = 0.2, not significant" and describe_p(0.004) == "p = 0.004"


# ---------------------------------------------------------------------------------------------- the memory study
def _fake_eval(record: Path, name: str, scenes: list[int], wins: list[int], presses: list[int]) -> None:
    episodes = [
        {
            "seed": s,
            "success": bool(w),
            "reason": "" if w else "timeout",
            "steps": 60,
            "decision": {"reached": True, "correct": p == 3, "choice": f"{p} presses"},
        }
        for s, w, p in zip(scenes, wins, presses)
    ]
    result = {
        "task": "tap",
        "n": len(scenes),
        "successes": sum(wins),
        "failure_reasons": {"timeout": len(wins) - sum(wins)} if len(wins) > sum(wins) else {},
        "decisions": {
            "reached": len(scenes),
            "correct": sum(p == 3 for p in presses),
            "choices": {f"{p} presses": presses.count(p) for p in set(presses)},
        },
        "episodes": episodes,
    }
    (record / "evals").mkdir(parents=True, exist_ok=True)
    (record / "evals" / f"{name}.json").write_text(json.dumps(result))


def test_the_memory_report_pairs_every_model_with_dssp_and_marks_what_is_pending(tmp_path):
    from studies import memory_tasks

    plan = {**memory_tasks.QUICK_PLAN, "seeds": [0, 1], "episodes": {"validation": 10, "test": 10}}
    scenes = protocol.split_seeds("validation", 10)
    for seed in (0, 1):
        _fake_eval(tmp_path, f"tap_dssp_s{seed}_validation", scenes, [1] * 9 + [0], [3] * 9 + [2])
        _fake_eval(tmp_path, f"tap_wo_history_s{seed}_validation", scenes, [0] * 8 + [1, 1], [2, 4] * 4 + [3, 3])
    lines, figures = memory_tasks.report_lines(plan, tmp_path, "validation", shown_record="reports/memory/record")
    text = "\n".join(lines)
    row = figures["tasks"]["tap"]["wo_history"]
    assert row["success"] == pytest.approx(0.2) and row["delta"] == pytest.approx(-0.7)
    assert row["p"] == pytest.approx(paired_exact_test([[0] * 8 + [1, 1]] * 2, [[1] * 9 + [0]] * 2))
    assert row["decision_right"] == 4 and row["decision_reached"] == 20
    assert "| DSSP w/o history | 20 (" in text and describe_p(row["p"]) in text
    assert "| DP3 (sim size, 0.71 M) | pending |" in text  # not evaluated yet: never a made-up row
    assert "1 of the table's 2 comparisons are recorded" in text  # Holm over a partial family is said to be so
    assert row["p_holm"] == pytest.approx(row["p"])  # a family of one
    assert "| 2 presses | 3 presses | 4 presses |" in text and "not a test result" in text
    assert "reports/memory/record" in text and str(tmp_path) not in text
    # trainings run on another machine are stated; a malformed statement is refused, not skipped
    elsewhere = {
        "models": ["wo_history"],
        "tasks": ["tap"],
        "seeds": [0, 1],
        "machine": "a GPU",
        "how": "side by side",
        "code": "abc",
    }
    (tmp_path / "trained_elsewhere.json").write_text(json.dumps([elsewhere]))
    text = "\n".join(memory_tasks.report_lines(plan, tmp_path, "validation")[0])
    assert "Trained elsewhere (DSSP w/o history; tap; training seeds [0, 1]): a GPU; side by side (code abc)." in text
    (tmp_path / "trained_elsewhere.json").write_text(json.dumps([{"models": ["wo_history"]}]))
    with pytest.raises(DSSPError, match="trained_elsewhere.json must hold"):
        memory_tasks.report_lines(plan, tmp_path, "validation")
    (tmp_path / "trained_elsewhere.json").unlink()
    # each run's line names its split and tasks, so two runs of one plan on different tasks read apart
    run = {
        "task_definition": "d",
        "plan": "p",
        "commit": "c",
        "tasks": ["tap", "swap"],
        "machine": {"cpu": "X", "cores": 2, "onnxruntime": "1", "torch": "2"},
    }
    assert protocol.describe_run(run, "test", definition="benchmark definition") == (
        "Run (test: tap, swap) on: benchmark definition d, plan p, code c; X (2 cores), onnxruntime 1, torch 2."
    )
    assert protocol.describe_run({**run, "tasks": []}).startswith("Run on: task definition d,")
    _fake_eval(tmp_path, "tap_dssp_s1_validation", scenes[::-1], [1] * 10, [3] * 10)
    with pytest.raises(DSSPError, match="different scenes"):
        memory_tasks.report_lines(plan, tmp_path, "validation")


@pytest.mark.slow
def test_the_quick_memory_study_runs_end_to_end_and_locks_the_test_split(tmp_path, capsys):
    from studies import memory_tasks

    work, report = tmp_path / "work", tmp_path / "report"
    base = ["--quick", "--work", str(work), "--report", str(report), "--workers", "2"]
    assert memory_tasks.main([*base, "--split", "test"]) == 2
    assert "needs a frozen plan" in capsys.readouterr().err
    assert memory_tasks.main(base) == 0
    out = capsys.readouterr().out
    assert "| DSSP (full history) |" in out and "| DP3 (sim size, 0.71 M) |" in out and "pending" not in out
    assert memory_tasks.main([*base, "--freeze"]) == 0
    assert memory_tasks.main([*base, "--split", "test"]) == 0  # the trained models are reused: only evaluations run
    evals = sorted(p.name for p in (report / "record/evals").iterdir())
    assert len(evals) == 2 * 3 * 2 and all(
        json.loads((report / "record/evals" / e).read_text())["n"] == 2 for e in evals
    )
    trains = [p for p in (work / "done").glob("train_*.json")]
    assert len(trains) == 3 * 2
    assert memory_tasks.main([*base, "--split", "test", "--report-only"]) == 0


@pytest.mark.slow
def test_the_quick_sampling_study_runs_end_to_end_and_rebuilds_from_its_record(tmp_path, capsys):
    from studies import sampling

    work, report = tmp_path / "work", tmp_path / "report"
    assert sampling.main(["--quick", "--work", str(work), "--report", str(report), "--workers", "2"]) == 0
    first = (report / "sampling.md").read_text()
    assert "| 2 | " in first and "| 1 | " in first and "validation seeds 1000–1000" in first
    assert len(list((report / "record/evals").glob("*.json"))) == 4
    capsys.readouterr()
    assert sampling.main(["--quick", "--work", str(work), "--report", str(report)]) == 0
    assert "0 stage(s)" in capsys.readouterr().out  # every cell is in the record: nothing runs again
    assert sampling.main(["--quick", "--report", str(report), "--report-only"]) == 0
    assert (report / "sampling.md").read_text() == first


def test_sigterm_stops_the_running_stages_and_keeps_what_finished(tmp_path):
    import signal
    import subprocess
    import sys

    work = tmp_path / "work"
    code = (
        f"import sys; sys.path.insert(0, {str(Path(__file__).parent)!r}); from studies.runner import Runner, Stage; "
        f"Runner({str(work)!r}, workers=2, say=print).run([Stage('quick', 'study_entries:write_marker', ('done.json',)), "
        f"Stage('long', 'study_entries:sleep_long', ('pid',))])"
    )
    # started the way a background launch is: SIGINT ignored, so only SIGTERM can stop it
    proc = subprocess.Popen(
        [sys.executable, "-c", code],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN),
    )
    wait_for(
        lambda: (work / "pid").is_file() and (work / "done/quick.json").is_file(),
        timeout=60,
        what="the first stage done and the second started",
        poll=0.1,
    )
    stage_pid = int((work / "pid").read_text())
    proc.send_signal(signal.SIGTERM)
    proc.wait(timeout=30)
    assert proc.returncode != 0 and (work / "done/quick.json").is_file() and not (work / "done/long.json").exists()

    def gone() -> bool:  # the stage went with the runner
        try:
            os.kill(stage_pid, 0)
        except ProcessLookupError:
            return True
        return False

    wait_for(gone, what="the stage's process ended")


def test_the_code_commit_ignores_the_records_a_study_rewrites(tmp_path, monkeypatch):
    """A study rewrites its record under reports/ as it runs: the code is still the commit's, no ``+changes``;
    a changed source file is a change."""
    import shutil
    import subprocess

    from studies import protocol

    repo = tmp_path / "repo"
    (repo / "studies").mkdir(parents=True)
    (repo / "reports").mkdir()
    shutil.copy(protocol.__file__, repo / "studies" / "protocol.py")
    (repo / "reports" / "record.json").write_text("{}")
    git = ["git", "-C", str(repo), "-c", "user.name=t", "-c", "user.email=t@t"]
    subprocess.run([*git, "init", "-q"], check=True)
    subprocess.run([*git, "add", "-A"], check=True)
    subprocess.run([*git, "commit", "-qm", "x"], check=True)
    head = subprocess.run([*git, "rev-parse", "HEAD"], capture_output=True, text=True, check=True).stdout.strip()
    monkeypatch.setattr(protocol, "__file__", str(repo / "studies" / "protocol.py"))
    (repo / "reports" / "record.json").write_text('{"more": 1}')
    assert protocol.code_commit() == head
    (repo / "studies" / "protocol.py").write_text("# changed\n")
    assert protocol.code_commit() == head + "+changes"

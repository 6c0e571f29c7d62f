"""The delay study's plan and report arithmetic (its figures are rebuilt from the committed record by
``python -m studies.rebuild --check``, which the tests run): every (mode, delay, training seed) cell one evaluation
on the same validation scenes from that seed's --inpainting export; the tests pair by scene and seed."""

import json

from studies import delay_study, protocol


def test_every_cell_is_an_evaluation_of_the_one_inpainting_export(tmp_path):
    plan = delay_study.PLAN
    stages = delay_study.stages(plan, ["tap"], tmp_path)
    names = [s.name for s in stages]
    assert names[:3] == ["collect_tap", "train_tap_s0", "export_tap_s0"] and "train_tap_s1" in names
    assert "--inpainting" in stages[2].argv
    train = list(stages[names.index("train_tap_s1")].argv)
    assert train[train.index("--seed") + 1] == "1"
    cells = [s for s in stages if s.name.startswith("eval_")]
    assert len(cells) == len(plan["delays_ms"]) * len(plan["smoothings"]) * len(plan["seeds"]) == 30
    first = str(protocol.split_seeds("validation", plan["episodes"])[0])
    for s in cells:
        argv = list(s.argv)
        seed = s.name.rsplit("_s", 1)[1]
        assert argv[argv.index("--seed") + 1] == first and argv[argv.index("--model") + 1] == f"model_tap_s{seed}"
    # a cell already in the record is not run again
    (tmp_path / "evals").mkdir()
    (tmp_path / "evals" / "tap_rtc_d200_s1.json").write_text("{}")
    assert "eval_tap_rtc_d200_s1" not in [s.name for s in delay_study.stages(plan, ["tap"], tmp_path)]


def _eval(successes, jerk=(30.0, 10.0)):
    return {
        "n": len(successes),
        "successes": sum(successes),
        "injected_delay_ticks": 2,
        "boundary_jerk": {"at_boundaries": jerk[0], "elsewhere": jerk[1]},
        "episodes": [{"seed": 1000 + i, "success": bool(s), "holds": 3} for i, s in enumerate(successes)],
    }


def test_the_report_pairs_by_scene_and_seed_and_says_what_is_not_significant(tmp_path):
    plan = {
        **delay_study.PLAN,
        "tasks": {"tap": {"demos": 50, "steps": 3000}},
        "delays_ms": [200],
        "episodes": 4,
        "seeds": [0, 1],
    }
    evals = tmp_path / "record" / "evals"
    evals.mkdir(parents=True)
    runs = {"none": [0] * 4, "ensemble": [1, 0, 1, 0], "rtc": [1] * 4}
    for mode, outcome in runs.items():
        for seed in (0, 1):
            (evals / f"tap_{mode}_d200_s{seed}.json").write_text(json.dumps(_eval(outcome)))
    md = delay_study.write_report(plan, tmp_path / "record", tmp_path / "report")
    record = json.loads((tmp_path / "report" / "delay.json").read_text())
    tests = {t["vs"]: t for t in record["paired_tests"]}
    assert tests["none"]["difference"] == 1.0 and tests["none"]["p"] < 0.2  # every scene favours RTC, in both seeds
    assert tests["ensemble"]["difference"] == 0.5 and tests["ensemble"]["p"] > 0.05
    text = md.read_text()
    assert "not significant" in text and "| 200 ms (2) |" in text
    assert record["summary"]["tap"]["rtc"]["200"]["holds"] == 3.0 and record["summary"]["tap"]["rtc"]["200"]["n"] == 8
    assert (
        record["summary"]["tap"]["ensemble"]["200"]["interval95"][0]
        < 0.5
        < record["summary"]["tap"]["ensemble"]["200"]["interval95"][1]
    )
    # a seed not yet evaluated leaves the cell pending rather than reported on fewer seeds
    (evals / "tap_rtc_d200_s1.json").unlink()
    md = delay_study.write_report(plan, tmp_path / "record", tmp_path / "report")
    assert "pending" in md.read_text()
    assert (tmp_path / "report" / "delay.png").is_file()


def test_the_fair_study_gives_each_mode_its_robot_compute_and_leaves_waits_out_of_the_limit(tmp_path):
    from studies import delay_fair

    plan = delay_fair.FAIR_PLAN
    stages = {s.name: s for s in delay_study.stages(plan, ["tap"], tmp_path)}
    assert [delay_study.ticks_of(d) for d in plan["delays_ms"]] == [0, 1, 2, 4]  # distinct ticks
    for d in plan["delays_ms"]:
        argv = stages[f"eval_{delay_study.cell('tap', 'ensemble', d, 0)}"].argv
        assert argv[argv.index("--ensemble-every") + 1] == str(max(1, delay_study.ticks_of(d)))  # one chunk in flight
        for mode in plan["smoothings"]:
            argv = stages[f"eval_{delay_study.cell('tap', mode, d, 0)}"].argv
            assert "--limit-excludes-holds" in argv and argv[argv.index("--inject-delay") + 1] == str(d)
    assert "--prefetch" in stages[f"eval_{delay_study.cell('tap', 'prefetch', 100, 0)}"].argv
    trained = stages[f"eval_{delay_study.cell('tap', 'rtc_trained', 200, 1)}"].argv
    assert trained[trained.index("--model") + 1] == "model_tap_trained_rtc_s1" and "rtc" in trained
    assert "model.committed_prefix_max=4" in stages["train_tap_trained_rtc_s1"].argv
    assert "model.committed_prefix_max=4" not in stages["train_tap_s1"].argv
    # the earlier plan's stages are what they were: --smoothing MODE --inject-delay MS, nothing more
    old = {s.name: s.argv for s in delay_study.stages(delay_study.PLAN, ["tap"], tmp_path)}
    argv = old[f"eval_{delay_study.cell('tap', 'ensemble', 400, 0)}"]
    assert argv[argv.index("--seed") + 2 : argv.index("--threads")] == (
        "--smoothing",
        "ensemble",
        "--inject-delay",
        "400",
    )

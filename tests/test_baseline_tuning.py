"""The baselines' tuning study: every model gets the same training windows and the same number of configurations,
DP3 trains with its recipe, and the choice is made from the record (validation seeds) by a stated rule."""

import json

from studies import baseline_tuning as study
from studies.protocol import split_seeds


def test_every_model_sees_the_same_windows_with_as_many_learning_rates():
    plan = study.PLAN
    assert len({len(m["lrs"]) for m in plan["models"].values()}) == 1
    for task, spec in plan["tasks"].items():
        seen = {name: study.steps_of(plan, task, name) * m["batch"] for name, m in plan["models"].items()}
        assert set(seen.values()) == {spec["windows"]}, seen
    assert [m["lrs"][0] for n, m in plan["models"].items() if n.startswith("dp3")] == [1e-4] * 3  # DP3's own rate first


def test_the_stages_train_dp3_with_its_recipe_and_evaluate_on_validation_scenes(tmp_path):
    stages = study.stages(study.PLAN, ["tap"], tmp_path)
    by_name = {s.name: s for s in stages}
    train = by_name["train_tap_dp3_17m_lr0.0003"].argv
    assert "dp3_recipe" in train and "model.unet_down_dims=[128,256,512]" in train and "train.lr=0.0003" in train
    assert "train.batch_size=128" in train and train[train.index("--steps") + 1] == "750"
    evaluate = by_name["eval_tap_dp3_17m_lr0.0003"].argv
    assert evaluate[evaluate.index("--seed") + 1] == str(split_seeds("validation", 20)[0])
    assert len([s for s in stages if s.name.startswith("eval_")]) == 16 and stages[0].name == "collect_tap"
    (tmp_path / "evals").mkdir()
    for s in stages:
        if s.name.startswith("eval_"):
            (tmp_path / s.outputs[0]).write_text("{}")
    assert study.stages(study.PLAN, ["tap"], tmp_path) == []  # a recorded configuration needs nothing


def test_the_choice_is_the_most_successes_and_a_tie_keeps_the_recipes_rate(tmp_path):
    plan = {**study.PLAN, "tasks": {"tap": study.PLAN["tasks"]["tap"]}}
    (tmp_path / "evals").mkdir()
    wins = {"dssp": [9, 12, 12, 5], "dp3_0.7m": [7, 7, 3, 1], "dp3_4.8m": [5, 9, 2, 9]}
    for name, ks in wins.items():
        for lr, k in zip(plan["models"][name]["lrs"], ks):
            (tmp_path / "evals" / f"{study.cell('tap', name, lr)}.json").write_text(
                json.dumps({"successes": k, "n": 20})
            )
    figures = study.chosen(plan, tmp_path)["tap"]
    assert figures["dssp"]["chosen_lr"] == "0.0003" and figures["dp3_0.7m"]["chosen_lr"] == "0.0001"
    assert figures["dp3_4.8m"]["chosen_lr"] == "0.0003" and figures["dp3_17m"]["chosen_lr"] is None  # not run yet
    md = study.write_report(plan, tmp_path, tmp_path / "report").read_text()
    assert "| DP3, DP3's recipe, UNet [128,256,512] | 750 × 128 | 0.0001: pending; " in md
    assert "0.0003: 60 % (12/20; " in md and "| 3000 × 32 |" in md
    # a choice at the smallest or largest rate tried says so (the best may lie beyond the grid)
    assert (
        "Chosen at an edge of its grid, so the grid may not hold its best rate: DP3, DP3's recipe, UNet [32,48,64]."
        in md
    )


def test_metaworld_is_tuned_as_its_study_trains_with_one_rate_for_the_suite(tmp_path):
    from studies import metaworld

    suite = ["button-press", "basketball", "assembly", "disassemble"]
    assert [t for t, spec in study.PLAN["tasks"].items() if spec.get("suite") == "metaworld"] == suite
    by_name = {s.name: s for s in study.stages(study.PLAN, ["button-press"], tmp_path)}
    assert by_name["collect_button-press"].argv[:3] == ("collect", "--task", "metaworld/button-press")
    train = by_name["train_button-press_dp3_4.8m_lr0.001"].argv
    assert train[train.index("--steps") + 1] == str(metaworld.steps_of(metaworld.PLAN) * 32 // 128)
    assert "--no-holdout" in train and " ".join(metaworld.HORIZONS) in " ".join(train)
    assert "metaworld/button-press" in by_name["eval_button-press_dssp_lr0.001"].argv

    plan = {
        **study.PLAN,
        "tasks": {t: study.PLAN["tasks"][t] for t in suite},
        "models": {"dssp": study.PLAN["models"]["dssp"]},
    }
    (tmp_path / "evals").mkdir()
    wins = {
        "button-press": [20, 19, 3, 0],
        "basketball": [0, 5, 9, 0],
        "assembly": [0, 2, 9, 0],
        "disassemble": [1, 1, 1, 1],
    }
    for task, ks in wins.items():
        for lr, k in zip(plan["models"]["dssp"]["lrs"], ks):
            (tmp_path / "evals" / f"{study.cell(task, 'dssp', lr)}.json").write_text(
                json.dumps({"successes": k, "n": 20})
            )
    figures = study.chosen(plan, tmp_path)
    pooled = study.pooled(plan, figures)["metaworld"]["dssp"]
    assert pooled["results"]["0.001"] == [21, 80] and pooled["chosen_lr"] == "0.0003"  # 27 of 80, not a task's best
    assert {figures[t]["dssp"]["chosen_lr"] for t in suite} == {"0.0003"}
    md = study.write_report(plan, tmp_path, tmp_path / "report").read_text()
    assert "## metaworld: button-press, basketball, assembly, disassemble pooled" in md
    assert "| 0.0003 (metaworld) |" in md and "0.0003: 34 % (27/80; " in md
    # one task missing a rate: the suite's choice waits for it
    (tmp_path / "evals" / f"{study.cell('assembly', 'dssp', 3e-3)}.json").unlink()
    assert study.chosen(plan, tmp_path)["button-press"]["dssp"]["chosen_lr"] is None

"""The baselines' tuning study: every model gets the same training windows and the same number of configurations,
DP3 trains with its recipe, and the choice is made from the record (validation seeds) by a stated rule."""

import json

from studies import baseline_tuning as study
from studies.protocol import split_seeds


def test_every_model_sees_the_same_windows_with_as_many_configurations():
    plan = study.PLAN
    assert {len(study.configurations(m)) for m in plan["models"].values()} == {8}
    assert {tuple(sorted(m["batches"])) for m in plan["models"].values()} == {(32, 128)}
    for task, spec in plan["tasks"].items():
        seen = {
            (name, b): study.steps_of(plan, task, name, b) * b
            for name, m in plan["models"].items()
            for b in m["batches"]
        }
        assert set(seen.values()) == {spec["windows"]}, seen
    dp3 = [m for n, m in plan["models"].items() if n.startswith("dp3")]
    assert [(m["batches"][0], m["lrs"][0]) for m in dp3] == [(128, 1e-4)] * 3  # DP3's own batch and rate first
    assert plan["models"]["dssp"]["batches"][0] == 32


def test_the_stages_train_dp3_with_its_recipe_and_evaluate_on_validation_scenes(tmp_path):
    stages = study.stages(study.PLAN, ["tap"], tmp_path)
    by_name = {s.name: s for s in stages}
    train = by_name["train_tap_dp3_17m_lr0.0003"].argv
    assert "dp3_recipe" in train and "model.unet_down_dims=[128,256,512]" in train and "train.lr=0.0003" in train
    assert "train.batch_size=128" in train and train[train.index("--steps") + 1] == "750"
    small = by_name["train_tap_dp3_17m_b32_lr0.0003"].argv  # the other batch: named, the same windows in more steps
    assert "train.batch_size=32" in small and small[small.index("--steps") + 1] == "3000"
    large = by_name["train_tap_dssp_b128_lr0.001"].argv
    assert "train.batch_size=128" in large and large[large.index("--steps") + 1] == "750" and "sim" in large
    evaluate = by_name["eval_tap_dp3_17m_lr0.0003"].argv
    assert evaluate[evaluate.index("--seed") + 1] == str(split_seeds("validation", 20)[0])
    assert len([s for s in stages if s.name.startswith("eval_")]) == 32 and stages[0].name == "collect_tap"
    (tmp_path / "evals").mkdir()
    for s in stages:
        if s.name.startswith("eval_"):
            (tmp_path / s.outputs[0]).write_text("{}")
    assert study.stages(study.PLAN, ["tap"], tmp_path) == []  # a recorded configuration needs nothing


def _record(tmp_path, plan, task, name, wins, batch=None):
    """Evaluations of ``name`` on ``task`` with ``wins`` successes of 20 at each rate of the plan, at ``batch`` (None:
    the recipe's own)."""
    (tmp_path / "evals").mkdir(exist_ok=True)
    for lr, k in zip(plan["models"][name]["lrs"], wins):
        path = tmp_path / "evals" / f"{study.cell(task, name, lr, batch)}.json"
        path.write_text(json.dumps({"successes": k, "n": 20}))


def test_the_choice_is_the_most_successes_and_a_tie_keeps_the_recipes_batch_and_rate(tmp_path):
    plan = {**study.PLAN, "tasks": {"tap": study.PLAN["tasks"]["tap"]}}
    for name, own, other in (
        ("dssp", [9, 12, 12, 5], [3, 4, 12, 0]),
        ("dp3_0.7m", [7, 7, 3, 1], [2, 2, 2, 2]),
        ("dp3_4.8m", [5, 9, 2, 9], [5, 9, 10, 1]),
    ):
        _record(tmp_path, plan, "tap", name, own)
        _record(tmp_path, plan, "tap", name, other, batch=[b for b in plan["models"][name]["batches"]][1])
    _record(tmp_path, plan, "tap", "dp3_17m", [1, 2, 3, 4])  # its other batch not run yet
    figures = study.chosen(plan, tmp_path)["tap"]
    assert figures["dssp"]["chosen"] == {"batch": 32, "lr": "0.0003"}  # a tie with batch 128: the recipe's own
    assert figures["dp3_0.7m"]["chosen"] == {"batch": 128, "lr": "0.0001"}
    assert figures["dp3_4.8m"]["chosen"] == {"batch": 32, "lr": "0.001"} and figures["dp3_17m"]["chosen"] is None
    assert figures["dp3_4.8m"]["results"]["32"]["0.001"] == [10, 20]
    md = study.write_report(plan, tmp_path, tmp_path / "report").read_text()
    assert "| DP3, DP3's recipe, UNet [128,256,512] | 750 × 128 | 0.0001: 5 % (1/20; " in md
    assert "|  | 3000 × 32 | 0.0001: pending; " in md and "| pending |" in md
    assert "0.0003: 60 % (12/20; " in md and "| DSSP (sim) | 3000 × 32 |" in md and "|  | 750 × 128 |" in md
    assert "| 0.001 at batch 32 |" in md
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

    dssp = {**study.PLAN["models"]["dssp"], "batches": [32]}  # one batch: the suite's rule is the same at any
    plan = {**study.PLAN, "tasks": {t: study.PLAN["tasks"][t] for t in suite}, "models": {"dssp": dssp}}
    wins = {
        "button-press": [20, 19, 3, 0],
        "basketball": [0, 5, 9, 0],
        "assembly": [0, 2, 9, 0],
        "disassemble": [1, 1, 1, 1],
    }
    for task, ks in wins.items():
        _record(tmp_path, plan, task, "dssp", ks)
    figures = study.chosen(plan, tmp_path)
    pooled = study.pooled(plan, figures)["metaworld"]["dssp"]
    assert pooled["results"]["32"]["0.001"] == [21, 80]
    assert pooled["chosen"] == {"batch": 32, "lr": "0.0003"}  # 27 of 80, not a task's best
    assert {figures[t]["dssp"]["chosen"]["lr"] for t in suite} == {"0.0003"}
    md = study.write_report(plan, tmp_path, tmp_path / "report").read_text()
    assert "## metaworld: button-press, basketball, assembly, disassemble pooled" in md
    assert "| 0.0003 at batch 32 (metaworld) |" in md and "0.0003: 34 % (27/80; " in md
    # one task missing a rate: the suite's choice waits for it
    (tmp_path / "evals" / f"{study.cell('assembly', 'dssp', 3e-3)}.json").unlink()
    assert study.chosen(plan, tmp_path)["button-press"]["dssp"]["chosen"] is None

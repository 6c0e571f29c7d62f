"""The memory study with every model at its best: the plan takes each model's rate from the tuning's report, DP3
trains with its recipe on the same windows, the headline rows have five training seeds, and a pending tuning is
refused before anything runs."""

import json

import numpy as np
import pytest

from dssp_core.errors import DSSPError
from studies import baseline_tuning, memory_fair, memory_tasks
from studies.study_stages import SIM_BATCH, seeds_of


def _tuning(tmp_path, chosen=None):
    """A tuning report whose every model chose ``chosen[model]`` ((batch, rate); default its recipe's own batch and
    1e-3) on every task."""
    chosen = chosen or {}
    models = baseline_tuning.PLAN["models"]
    tasks = {
        task: {
            name: {"chosen": dict(zip(("batch", "lr"), chosen.get(name, (model["batches"][0], "0.001"))))}
            for name, model in models.items()
        }
        for task in memory_tasks.PLAN["tasks"]
    }
    path = tmp_path / "baseline_tuning.json"
    path.write_text(json.dumps({"tasks": tasks}))
    return path


def test_each_model_trains_at_its_chosen_configuration_on_the_same_windows(tmp_path):
    plan = memory_fair.fair_plan(
        _tuning(tmp_path, {"dp3_17m": (128, "0.003"), "dssp": (32, "0.0003"), "dp3_4.8m": (32, "0.0003")})
    )
    stages = {s.name: s.argv for s in memory_tasks.stages(plan, "test", ["tap"], tmp_path / "record")}
    dp3 = stages["train_tap_dp3_17m_s4"]
    assert "dp3_recipe" in dp3 and "train.lr=0.003" in dp3 and "train.batch_size=128" in dp3
    assert "model.unet_down_dims=[128,256,512]" in dp3 and dp3[dp3.index("--steps") + 1] == "750"
    dssp = stages["train_tap_dssp_s4"]
    assert (
        "train.lr=0.0003" in dssp and dssp[dssp.index("--steps") + 1] == "3000" and "train.batch_size=128" not in dssp
    )
    # the same windows: steps × batch equal for DSSP (the sim preset's 32) and DP3 (128, or 32 where it chose it)
    assert 3000 * SIM_BATCH == 750 * 128
    small = stages["train_tap_dp3_4.8m_s0"]
    assert small[small.index("--steps") + 1] == "3000" and "train.batch_size=32" in small and "train.lr=0.0003" in small
    # five seeds on the headline rows, three for DSSP w/o history and the ablations (at DSSP's rate)
    for name, seeds in (("dssp", 5), ("dp3_0.7m", 5), ("wo_history", 3), ("no_dynamics_loss", 3)):
        assert len([s for s in stages if s.startswith(f"train_tap_{name}_s")]) == seeds, name
    assert "train.lr=0.0003" in stages["train_tap_no_dynamics_loss_s2"]
    assert "train_tap_no_dynamics_loss_s3" not in stages
    # DP3 at its own size: a GPU command with its recipe and its own rate, on the same windows
    gpu = [c for c in memory_tasks.gpu_commands(plan, ["tap"]) if "runs/tap_dp3_s0 " in c][0]
    assert "--preset dp3 " in gpu and "train.sampling=windows" in gpu and "train.lr=0.0001" in gpu
    assert "--steps 750 " in gpu and gpu.endswith("--device cuda")


def test_a_pending_tuning_is_refused_with_the_command_that_completes_it(tmp_path):
    path = _tuning(tmp_path)
    report = json.loads(path.read_text())
    report["tasks"]["swap"]["dp3_4.8m"]["chosen"] = None
    path.write_text(json.dumps(report))
    with pytest.raises(DSSPError, match=r"dp3_4.8m on swap is not chosen yet: run python -m studies.baseline_tuning"):
        memory_fair.fair_plan(path)
    del report["tasks"]["swap"]
    path.write_text(json.dumps(report))
    with pytest.raises(DSSPError, match="dssp on swap is not chosen yet"):
        memory_fair.fair_plan(path)
    (tmp_path / "folder").mkdir()
    with pytest.raises(DSSPError, match="cannot read the tuning report"):
        memory_fair.fair_plan(tmp_path / "folder")


def test_the_report_pairs_five_seeds_against_three(tmp_path):
    plan = memory_fair.quick_plan()
    plan = {**plan, "seeds": [0, 1, 2], "episodes": {"validation": 10, "test": 10}}
    scenes = list(range(1000, 1010))
    rng = np.random.default_rng(0)
    for name, model in plan["models"].items():
        for seed in seeds_of(plan, model):
            wins = rng.integers(0, 2, 10) if name != "dssp" else np.ones(10, int)
            episodes = [
                {"seed": s, "success": bool(w), "presses": 3, "reason": "success" if w else "wrong count"}
                for s, w in zip(scenes, wins)
            ]
            (tmp_path / "evals").mkdir(exist_ok=True)
            (tmp_path / "evals" / f"{memory_tasks.eval_name('tap', name, seed, 'validation')}.json").write_text(
                json.dumps(
                    {
                        "episodes": episodes,
                        "decisions": {"reached": 10, "correct": int(wins.sum()), "choices": {"3 presses": 10}},
                        "failure_reasons": {"wrong count": int(10 - wins.sum())},
                    }
                )
            )
    lines, figures = memory_tasks.report_lines(plan, tmp_path, "validation", naming=memory_fair.NAMING)
    text = "\n".join(lines)
    assert "python -m studies.memory_fair --split validation --report-only" in text
    assert "training seeds [0, 1, 2] (DSSP w/o history: [0])" in text and "| DSSP (full history) |" in text
    rows = figures["tasks"]["tap"]
    assert len(rows["wo_history"]["per_seed"]) == 1 and len(rows["dssp"]["per_seed"]) == 3
    assert rows["wo_history"]["delta"] < 0 and 0 <= rows["wo_history"]["p_seeds"] <= 1


def test_a_pending_tuning_stops_the_command_in_one_line(tmp_path, capsys, monkeypatch):
    path = _tuning(tmp_path)
    report = json.loads(path.read_text())
    report["tasks"]["tap"]["dssp"]["chosen"] = None
    path.write_text(json.dumps(report))
    monkeypatch.setattr(baseline_tuning, "CHOICES", path)
    assert memory_fair.main(["--report-only", "--report", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "dssp on tap is not chosen yet" in err[0]


@pytest.mark.slow
def test_the_quick_plan_runs_end_to_end(tmp_path, capsys):
    work, report = tmp_path / "work", tmp_path / "report"
    assert memory_fair.main(["--quick", "--work", str(work), "--report", str(report), "--workers", "2"]) == 0
    out = capsys.readouterr().out
    assert "python -m studies.memory_fair --split validation --report-only" in out and "pending" not in out
    assert len(list((report / "record/evals").glob("tap_*_validation.json"))) == 2 + 2 + 1
    dp3 = json.loads((work / "done/train_tap_dp3_0.7m_s1.json").read_text())["argv"]
    assert "train.batch_size=32" in dp3 and "train.lr=0.001" in dp3

"""MetaWorld under DP3's protocol: the task list, the weld rows on this MuJoCo, the demonstrations as a DP3 zarr that
plain zarr-python reads the way DP3's ReplayBuffer does, and the whole chain (collect, train, export, evaluate)."""

import json

import mujoco  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
import zarr  # noqa: E402
from conftest import SET_SMALL, one_error_line

from dssp_core.errors import ConfigError, DSSPError
from dssp_sim import metaworld_env as mw  # before mujoco: it sets MUJOCO_GL=egl
from dssp_sim.sim_cli import main as sim_main

TASK = "reach"  # the quickest expert


def test_the_difficulty_groups_hold_metaworlds_50_tasks_once():
    assert [len(mw.DIFFICULTY[g]) for g in ("easy", "medium", "hard", "very_hard")] == [28, 11, 6, 5]
    assert len(set(mw.TASKS)) == len(mw.TASKS) == 50
    easy = [t for t in mw.DIFFICULTY["easy"] if t != "door-open"]
    assert mw.tasks_of(["door-open", "easy", "metaworld/hammer"]) == ["door-open", *easy, "hammer"]  # in order, once
    assert mw.tasks_of(["all"]) == list(mw.TASKS)
    assert mw.difficulty_of("stick-pull") == "very_hard"
    with pytest.raises(ConfigError, match="unknown MetaWorld task 'door-opn'"):
        mw.task_name("metaworld/door-opn")


def test_the_hand_follows_the_action_on_this_mujoco():
    """metaworld writes 11 numbers per weld row; on a MuJoCo with 12 the hand must still follow the mocap."""
    with mw.MetaWorldEnv(TASK, seed=3) as env:
        welds = [i for i in range(env.model.neq) if env.model.eq_type[i] == mujoco.mjtEq.mjEQ_WELD]
        assert welds
        for i in welds:
            assert env.model.eq_data[i][6] == -1.0 and env.model.eq_data[i][10] == 5.0
            if mujoco.mjNEQDATA > 11:
                assert env.model.eq_data[i][11] == 0.0  # the relative pose is the one given
        start = env.state()[:3].copy()
        for _ in range(10):
            env.step([1.0, 0.0, 0.0, -1.0])
        moved = env.state()[:3] - start
        assert moved[0] > 0.02 and abs(moved[1]) < 0.01 and abs(moved[2]) < 0.01


def test_scenes_are_drawn_from_the_seed():
    with mw.MetaWorldEnv(TASK, seed=0) as env:
        env.reset(5)
        first = env.obs.copy()
        env.reset(6)
        other = env.obs.copy()
        env.reset(5)
        np.testing.assert_array_equal(env.obs, first)
        assert not np.array_equal(first[-3:], other[-3:])  # the goal moved


def test_the_cue_variant_shows_the_goal_for_ten_steps_then_hides_it():
    assert mw.task_id("metaworld-cue/reach") == "metaworld-cue/reach" and mw.task_id("reach") == "metaworld/reach"
    with pytest.raises(ConfigError, match="unknown MetaWorld cue task 'door-open'"):
        mw.task_name("metaworld-cue/door-open")

    def depth_at_goal(env) -> tuple[float, float]:
        """(depth rendered where the goal projects, m; the goal's own depth, m) — in the camera's optical frame."""
        raw, unit, intr, _ = env.render_depth()
        cam = env._camera_id
        rot = env.data.cam_xmat[cam].reshape(3, 3)  # MuJoCo's camera: x right, y up, looking along -z
        x, y, z = np.diag([1.0, -1.0, -1.0]) @ rot.T @ (env.env._target_pos - env.data.cam_xpos[cam])
        u, v = round(intr.fx * x / z + intr.ppx), round(intr.fy * y / z + intr.ppy)
        return float(raw[v, u]) * unit, float(z)

    with mw.MetaWorldEnv("metaworld-cue/reach", seed=3) as env:
        for _ in range(mw.CUE_STEPS):
            assert env.cue_shown()
            seen, goal = depth_at_goal(env)
            assert seen == pytest.approx(goal - mw.CUE_RADIUS_M, abs=0.01)  # the cue's near surface
            env.hold()
        assert not env.cue_shown()
        seen, goal = depth_at_goal(env)
        assert seen == 0.0 or seen > goal + 0.05  # what lies behind it (or nothing within range)
        assert np.array_equal(env.data.site_xpos[env._goal_site], env.env._target_pos)  # hidden, not moved
        env.reset(3)  # a new episode shows it again; the expert, which knows the goal, still succeeds
        assert env.cue_shown() and depth_at_goal(env)[0] == pytest.approx(
            depth_at_goal(env)[1] - mw.CUE_RADIUS_M, abs=0.01
        )
        expert = mw.MetaWorldExpert(env)
        while not env.status().done:
            env.step(expert.act(env))
        assert env.status().success and env.status().info["cue_steps"] == mw.CUE_STEPS


@pytest.fixture(scope="module")
def demos(tmp_path_factory):
    out = tmp_path_factory.mktemp("mw") / "reach.zarr"
    assert (
        sim_main(["collect", "--task", f"metaworld/{TASK}", "--episodes", "2", "--out", str(out), "--no-progress"]) == 0
    )
    return out


def test_demonstrations_are_a_dp3_zarr_read_the_way_dp3_reads_it(demos):
    """DP3's ReplayBuffer opens the group with zarr-python and copies ``data/*`` and ``meta/episode_ends``; its
    MetaWorld data: 200-step episodes, point_cloud (T, 512, 3), state (T, 9), action (T, 4), float32."""
    root = zarr.open_group(str(demos), mode="r")
    assert root.metadata.zarr_format == 2
    ends = root["meta"]["episode_ends"][:]
    np.testing.assert_array_equal(ends, [200, 400])
    cloud, state, action = (root["data"][k][:] for k in ("point_cloud", "state", "action"))
    assert cloud.shape == (400, 512, 3) and state.shape == (400, 9) and action.shape == (400, 4)
    assert cloud.dtype == state.dtype == action.dtype == np.float32
    for key in ("point_cloud", "state", "action"):
        a = root["data"][key]
        assert a.chunks[0] == 100
        codec = a.metadata.compressor.get_config()
        assert (codec["id"], codec["cname"], codec["clevel"], codec["shuffle"]) == ("blosc", "zstd", 3, 1)
    # the clouds lie in DP3's crop box of its cloud frame and are farthest-point samples (no repeats)
    assert (cloud >= np.array(mw.CROP_MIN, np.float32) - 1e-6).all() and (
        cloud <= np.array(mw.CROP_MAX, np.float32) + 1e-6
    ).all()
    assert len(np.unique(cloud[0], axis=0)) == 512
    # the state is the hand and the two fingertips; the first action moves the hand toward the goal
    assert np.allclose(state[0, :3], state[0, 3:6], atol=0.1) and np.allclose(state[0, :3], state[0, 6:9], atol=0.1)
    attrs = root.attrs.asdict()
    assert attrs["pointcloud_frame"] == mw.FRAME and attrs["task"] == f"metaworld/{TASK}"
    assert attrs["benchmark"]["protocol"] == "DP3" and attrs["benchmark"]["task"] == f"{TASK}-v3"
    assert attrs["pointcloud"]["n_points"] == 512 and attrs["pointcloud"]["crop_min"] == list(mw.CROP_MIN)
    assert attrs["control_rate_hz"] == pytest.approx(80.0)


def test_train_export_and_evaluate_on_metaworld(demos, tmp_path, capsys):
    from dssp_train.cli.train import main as train_main
    from export.to_onnx import main as export_main

    run, model = tmp_path / "run", tmp_path / "model"
    assert (
        train_main(
            [
                "--data",
                str(demos),
                "--out",
                str(run),
                "--preset",
                "tiny",
                "--steps",
                "4",
                "--no-holdout",
                "--set",
                "model.n_points=512",
                *SET_SMALL,
                "--no-progress",
            ]
        )
        == 0
    )
    assert json.loads((run / "config.json").read_text())["observation"]["frame"] == mw.FRAME
    assert export_main([str(run), "-o", str(model), "--skip-verify", "--quantize", "none"]) == 0
    out = tmp_path / "eval.json"
    assert (
        sim_main(
            [
                "eval",
                "--model",
                str(model),
                "--task",
                f"metaworld/{TASK}",
                "--episodes",
                "1",
                "--threads",
                "1",
                "--json",
                str(out),
                "--no-progress",
            ]
        )
        == 0
    )
    result = json.loads(out.read_text())
    assert result["task"] == f"metaworld/{TASK}" and result["n"] == 1
    episode = result["episodes"][0]
    assert episode["seed"] == 1000 and 1 <= episode["steps"] <= mw.EPISODE_STEPS
    assert episode["success"] or (episode["steps"] == mw.EPISODE_STEPS and episode["reason"] == "timeout")
    assert result["latency_ms"]["cloud"]["n"] == episode["steps"]
    out = capsys.readouterr().out
    assert "memory decision" not in out and "whole tick (cloud + policy + step)" in out

    # Rerun views of MetaWorld episodes are refused with one line
    assert (
        sim_main(
            [
                "eval",
                "--model",
                str(model),
                "--task",
                f"metaworld/{TASK}",
                "--episodes",
                "1",
                "--rerun-save",
                str(tmp_path / "v.rrd"),
                "--no-progress",
            ]
        )
        == 2
    )
    assert "metaworld" in one_error_line(capsys.readouterr().err).lower()


def test_a_model_of_other_dimensions_is_refused_before_any_episode(tiny_export, capsys):
    _, model, _ = tiny_export  # trained on a Piper dataset: state (7,), action (7,)
    assert (
        sim_main(["eval", "--model", str(model), "--task", f"metaworld/{TASK}", "--episodes", "1", "--no-progress"])
        == 2
    )
    assert "MetaWorld's are (9,) and (4,)" in one_error_line(capsys.readouterr().err)


# ---------------------------------------------------------------------------------------------- the study
def _fake_mw_eval(record, name, scenes, wins):
    result = {
        "task": "x",
        "n": len(scenes),
        "successes": sum(wins),
        "failure_reasons": {},
        "episodes": [
            {"seed": s, "success": bool(w), "reason": "", "steps": 50, "decision": {}} for s, w in zip(scenes, wins)
        ],
    }
    (record / "evals").mkdir(parents=True, exist_ok=True)
    (record / "evals" / f"{name}.json").write_text(json.dumps(result))


def test_the_study_selects_tasks_and_plans_every_checkpoints_evaluation():
    from studies import metaworld as study
    from studies.protocol import split_seeds

    assert study.select_tasks(["easy:2", "hard:1", "button-press"]) == [
        "button-press",
        "button-press-topdown",
        "assembly",
    ]
    with pytest.raises(DSSPError, match="GROUP:N"):
        study.select_tasks(["tricky:2"])
    plan = {**study.PLAN, "tasks": ["reach"], "seeds": [0]}
    assert study.checkpoint_steps(plan) == [200, 400, 600, 800, 1000]
    with pytest.raises(DSSPError, match="do not divide"):
        study.checkpoint_steps({**plan, "evaluations": 3})
    from pathlib import Path

    names = [s.name for s in study.stages(plan, "validation", ["reach"], Path("/nonexistent"))]
    assert names[0] == "collect_reach" and len(names) == 1 + 3 * (1 + 2 * 5)
    test = study.stages(plan, "test", ["reach"], Path("/nonexistent"))
    evals = [s for s in test if s.name.startswith("eval_")]
    assert [s.name for s in evals] == [f"eval_reach_{m}_s0_step1000_test" for m in plan["models"]]
    assert evals[0].argv[evals[0].argv.index("--seed") + 1] == str(split_seeds("test", 50)[0])
    memory = study.stages({**study.MEMORY_PLAN, "seeds": [0]}, "validation", ["reach"], Path("/nonexistent"))
    assert memory[0].argv[:3] == ("collect", "--task", "metaworld-cue/reach")
    assert all(
        s.argv[s.argv.index("--task") + 1] == "metaworld-cue/reach" for s in memory if s.name.startswith("eval_")
    )
    assert study.main(["--memory", "--tasks", "door-open", "--cost"]) == 2  # not a cue task: one line, nothing runs


def test_the_report_gives_the_papers_metric_and_the_paired_test_split(tmp_path):
    from studies import metaworld as study
    from studies.stats import paired_exact_test

    plan = {
        **study.PLAN,
        "tasks": ["button-press", "assembly"],
        "seeds": [0, 1],
        "evaluations": 5,
        "episodes": {"validation": 4, "test": 6},
    }
    val, test = list(range(1000, 1004)), list(range(10000, 10006))
    rates = {"dssp": [0, 1, 2, 3, 4, 4], "dp3_sim": [1, 1, 1, 1, 1, 0]}  # wins per checkpoint (6 numbers: 5 used)
    for task in plan["tasks"]:
        for name in ("dssp", "dp3_sim"):
            for seed in (0, 1):
                for k, step in enumerate(study.checkpoint_steps(plan)):
                    wins = rates[name][k + seed]
                    _fake_mw_eval(
                        tmp_path,
                        study.eval_name(task, name, seed, step, "validation"),
                        val,
                        [1] * wins + [0] * (4 - wins),
                    )
                _fake_mw_eval(
                    tmp_path,
                    study.eval_name(task, name, seed, 1000, "test"),
                    test,
                    [1] * 6 if name == "dssp" else [0, 0, 0, 0, 0, 1],
                )
    lines, figures = study.report_lines(plan, tmp_path, shown_record="reports/metaworld/record")
    text = "\n".join(lines)
    row = figures["tasks"]["button-press"]["dssp"]
    # seed 0: 0,1,2,3,4 of 4 -> mean of the top five = 0.5; seed 1: 1,2,3,4,4 -> 0.7
    assert row["top5"]["per_seed"] == [pytest.approx(0.5), pytest.approx(0.7)]
    assert study.paper_metric([0.1, 0.9, 0.5, 0.2, 0.3, 0.8, 0.7], top=5) == pytest.approx(
        (0.9 + 0.8 + 0.7 + 0.5 + 0.3) / 5
    )
    dp3 = figures["tasks"]["assembly"]["dp3_sim"]["test"]
    assert dp3["success"] == pytest.approx(1 / 6) and dp3["delta"] == pytest.approx(-5 / 6)
    assert dp3["p"] == pytest.approx(paired_exact_test([[0, 0, 0, 0, 0, 1]] * 2, [[1] * 6] * 2))
    assert figures["groups"]["easy"]["dssp"]["top5"] == pytest.approx(0.6)
    # the group's top-5 with its std over training seeds (0.5 and 0.7), beside the paper's mean ± std
    assert "| easy (1 / 21) | 60.0 ± 10.0 |" in text and "90.5 ± 2.1" in text and "87.3 ± 2.2" in text
    assert figures["groups"]["easy"]["dssp"]["test_ci"][0] <= figures["groups"]["easy"]["dssp"]["test"]
    assert dp3["p_holm"] >= dp3["p"] and f"Holm {dp3['p_holm']:.2g}" in text
    assert "| button-press | DSSP w/o history | pending |" in text  # never a made-up row
    family = 2 * (len(study.model_order(plan)) - 1)  # Holm over the recorded two of the family is said to be so
    assert f"2 of the table's {family} comparisons are recorded" in text
    assert "plain mean of them all, no selection" in text and "optimistic" not in text  # top 5 of 5 checkpoints
    assert "0.10 of the paper's 1000 epochs" in text
    (tmp_path / "plan.json").write_text(json.dumps(plan))  # the README's block: the same table, from the record
    block = study.readme_table(tmp_path)
    assert block.startswith("| group (tasks here / paper's) |") and "| easy (1 / 21) | 60.0 ± 10.0 |" in block
    assert block.rstrip().endswith("No claim beyond this budget.") and block in text + "\n"


@pytest.mark.slow
def test_the_quick_study_runs_end_to_end_and_locks_the_test_split(tmp_path, capsys, monkeypatch):
    from studies import metaworld as study

    monkeypatch.chdir(tmp_path)
    args = ["--quick", "--work", "w", "--report", "rep"]
    assert study.main([*args, "--split", "test"]) == 2  # nothing frozen yet: the test seeds stay untouched
    assert "frozen plan" in one_error_line(capsys.readouterr().err)
    assert study.main(args) == 0
    assert study.main([*args, "--freeze"]) == 0 and study.main([*args, "--split", "test"]) == 0
    figures = json.loads((tmp_path / "rep" / "metaworld.json").read_text())
    assert set(figures["tasks"]["reach"]) == {"dssp", "dp3_sim", "wo_history"}
    assert all("top5" in r and "test" in r for r in figures["tasks"]["reach"].values())
    assert len(list((tmp_path / "rep" / "record" / "evals").glob("*.json"))) == 3 * 2 * (2 + 1)


def test_the_fair_plan_trains_each_model_at_its_tuned_rate_on_the_same_windows(tmp_path, capsys, monkeypatch):
    from pathlib import Path

    from studies import baseline_tuning
    from studies import metaworld as study

    choices = tmp_path / "baseline_tuning.json"
    configs = {"dssp": (32, "0.0003"), "dp3_0.7m": (128, "0.001"), "dp3_4.8m": (128, "0.003"), "dp3_17m": None}

    def write():
        chosen = {n: {"chosen": c and {"batch": c[0], "lr": c[1]}} for n, c in configs.items()}
        choices.write_text(json.dumps({"suites": {"metaworld": chosen}}))

    write()
    with pytest.raises(
        DSSPError, match="dp3_17m on metaworld is not chosen yet: run python -m studies.baseline_tuning"
    ):
        study.fair_plan(choices)
    monkeypatch.setattr(baseline_tuning, "CHOICES", choices)
    assert study.main(["--fair", "--cost"]) == 2
    one_error_line(capsys.readouterr().err, "--tasks button-press basketball assembly disassemble")
    configs["dp3_17m"] = (32, "0.0001")  # DP3 at the sim preset's batch: the same windows in as many steps as DSSP
    write()
    plan = {**study.fair_plan(choices), "tasks": ["reach"]}
    stages = {s.name: s.argv for s in study.stages(plan, "test", ["reach"], Path("/nonexistent"))}
    dp3 = stages["train_reach_dp3_4.8m_s4"]
    assert dp3[dp3.index("--steps") + 1] == "250" and "train.keep_every=50" in dp3 and "--no-holdout" in dp3
    assert "train.lr=0.003" in dp3 and "train.batch_size=128" in dp3 and "model.unet_down_dims=[64,128,256]" in dp3
    assert " ".join(study.HORIZONS) in " ".join(dp3)
    dp3 = stages["train_reach_dp3_17m_s0"]
    assert dp3[dp3.index("--steps") + 1] == "1000" and "train.keep_every=200" in dp3 and "train.batch_size=32" in dp3
    assert "eval_reach_dp3_17m_s4_step1000_test" in stages
    assert "eval_reach_dp3_4.8m_s4_step250_test" in stages and "eval_reach_dssp_s4_step1000_test" in stages
    assert "train.lr=0.0003" in stages["train_reach_wo_history_s2"] and "train_reach_wo_history_s3" not in stages
    # the report pairs five seeds of DSSP with three of DSSP w/o history on the same scenes
    scenes = list(range(10000, 10050))
    for name, seeds in (("dssp", 5), ("wo_history", 3)):
        step = study.checkpoint_steps(plan, name)[-1]
        for seed in range(seeds):
            _fake_mw_eval(tmp_path, study.eval_name("reach", name, seed, step, "test"), scenes, [name == "dssp"] * 50)
    lines, figures = study.report_lines(plan, tmp_path)
    text = "\n".join(lines)
    assert "python -m studies.metaworld --fair --report-only" in text and "DSSP 0.0003 at batch 32" in text
    row = figures["tasks"]["reach"]["wo_history"]["test"]
    assert row["delta"] == -1.0 and row["p_seeds"] == pytest.approx(1 / 56)  # 5 against 3 seeds: C(8, 3) splits

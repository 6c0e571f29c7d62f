"""The baselines' tuning: DSSP and DP3 (trained with DP3's recipe, at three sizes) with the same tuning budget on
validation seeds, so that the memory tasks' test tables compare each at its best.

    python -m studies.baseline_tuning [--tasks tap swap put2] [--workers 2] [--work runs/baseline_tuning]
                                      [--report reports/baseline_tuning] [--report-only] [--quick]

Every model of the plan trains on the same data and sees the same number of training windows per task (the
memory study's DSSP budget: steps × 32 windows), at each of its learning rates (the same four each, 1e-4 to 3e-3:
the same budget of configurations; widened from three when two of DP3's sizes chose the largest), training seed 0,
and is evaluated in closed loop on the same validation scenes. DP3's recipe
(preset ``dp3_recipe``): its optimiser (AdamW, betas 0.95/0.999, weight decay 1e-6), its cosine schedule with a
linear warm-up, its EMA (power 0.75, at most 0.9999), its min/max normalisation and its sampling — windows drawn
from the whole dataset, 128 per step (``train.sampling=windows``) — with DP3's own learning rate first among those
tried. Decided here where DP3's recipe assumes its own budget: the warm-up is 100 steps, as the ``sim`` preset's,
not DP3's 500 (which assumes some 10^5 steps; here DP3 runs 750 on tap). The sizes: the ``sim`` preset's parameter
count (0.71 M) and about 4.8 M and 17 M (UNet widths ×2 and ×4).

The report picks each model's learning rate by its validation success (a tie: the first in the plan's order, the
recipe's own); those choices are what a test plan may use. One training seed and 20 scenes per configuration:
the choice is noisy, and the report gives the Wilson interval of each cell to show how much.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from studies import memory_tasks, protocol
from studies.evaluations import study_main, write_md_and_json
from studies.runner import Stage
from studies.sim_study import pct
from studies.study_stages import collect_stage, eval_stage, export_stage, train_stage

REPORT_NAME = "baseline_tuning"
DP3_SIZES = {"dp3_0.7m": "[32,48,64]", "dp3_4.8m": "[64,128,256]", "dp3_17m": "[128,256,512]"}
PLAN = {
    "tasks": {
        task: {"demos": spec["demos"], "windows": spec["steps"] * memory_tasks.SIM_BATCH}
        for task, spec in memory_tasks.PLAN["tasks"].items()
    },
    "models": {
        "dssp": {"preset": "sim", "batch": 32, "lrs": [1e-3, 3e-4, 3e-3, 1e-4], "flags": []},
        **{
            name: {
                "preset": "dp3_recipe",
                "batch": 128,
                "lrs": [1e-4, 3e-4, 1e-3, 3e-3],
                "flags": ["--set", f"model.unet_down_dims={dims}"],
            }
            for name, dims in DP3_SIZES.items()
        },
    },
    "seed": 0,
    "episodes": 20,
    "export_flags": ["--quantize", "int8"],
}
QUICK_PLAN = {
    **PLAN,
    "tasks": {"tap": {"demos": 3, "windows": 64}},
    "models": {
        "dssp": {"preset": "sim", "batch": 32, "lrs": [1e-3], "flags": []},
        "dp3_0.7m": {
            "preset": "dp3_recipe",
            "batch": 32,
            "lrs": [1e-4, 1e-3],
            "flags": ["--set", "model.unet_down_dims=[16,32]"],
        },
    },
    "episodes": 1,
    "export_flags": ["--skip-verify", "--quantize", "none"],
}
LABELS = {"dssp": "DSSP (sim)", **{name: f"DP3, DP3's recipe, UNet {dims}" for name, dims in DP3_SIZES.items()}}


def cell(task: str, model: str, lr: float) -> str:
    return f"{task}_{model}_lr{lr:g}"


def steps_of(plan: dict, task: str, model: str) -> int:
    """The training steps that give ``model`` the task's budget of windows."""
    return max(1, plan["tasks"][task]["windows"] // plan["models"][model]["batch"])


def stages(plan: dict, tasks: list[str], record: Path) -> list[Stage]:
    """Every stage of ``tasks``; a configuration whose evaluation is in the record needs none."""
    first = protocol.split_seeds("validation", plan["episodes"])[0]
    out: list[Stage] = []
    for task in tasks:
        data, collected, task_stages = f"data/{task}.zarr", (f"collect_{task}",), []
        for name, model in plan["models"].items():
            for lr in model["lrs"]:
                key = cell(task, name, lr)
                if (record / "evals" / f"{key}.json").is_file():
                    continue
                run, model_dir = f"runs/{key}", f"models/{key}"
                flags = (*model["flags"], "--set", f"train.lr={lr:g}", "--set", f"train.batch_size={model['batch']}")
                steps = steps_of(plan, task, name)
                task_stages += [
                    train_stage(key, data, run, model["preset"], steps, plan["seed"], *flags, after=collected),
                    export_stage(
                        key, run, model_dir, "--force", "--threads", "1", *plan["export_flags"], after=(f"train_{key}",)
                    ),
                    eval_stage(key, model_dir, task, plan["episodes"], first, after=(f"export_{key}",)),
                ]
        if task_stages:
            out += [collect_stage(task, task, plan["tasks"][task]["demos"], data), *task_stages]
    return out


def chosen(plan: dict, record: Path) -> dict:
    """Per task and model: every learning rate's validation (successes, n) and the chosen one (the most successes; a
    tie: the first in the plan's order), or None until all of the model's configurations are recorded."""
    out: dict = {}
    for task in plan["tasks"]:
        for name, model in plan["models"].items():
            results = {}
            for lr in model["lrs"]:
                path = record / "evals" / f"{cell(task, name, lr)}.json"
                if path.is_file():
                    e = json.loads(path.read_text())
                    results[f"{lr:g}"] = [e["successes"], e["n"]]
            best = max(results, key=lambda lr: results[lr][0]) if len(results) == len(model["lrs"]) else None
            out.setdefault(task, {})[name] = {
                "results": results,
                "chosen_lr": best,
                "steps": steps_of(plan, task, name),
            }
    return out


def write_report(plan: dict, record: Path, report: Path, shown_record: str | None = None) -> Path:
    """``baseline_tuning.md`` and ``.json`` from the record alone."""
    figures = chosen(plan, record)
    scenes = protocol.split_seeds("validation", plan["episodes"])
    budgets = ", ".join(f"{task} {spec['windows']}" for task, spec in plan["tasks"].items())
    lines = [
        "# The baselines' tuning on validation seeds: DSSP and DP3 with DP3's recipe at three sizes",
        "",
        f"Rebuilt from `{shown_record or record}` by `python -m studies.baseline_tuning --report-only`. Training seed "
        f"{plan['seed']}, {plan['episodes']} closed-loop episodes per configuration on validation scenes {scenes[0]}–"
        f"{scenes[-1]} (a choice: not a test result); the same training windows per task for every model "
        f"({budgets}), "
        f"{max(len(m['lrs']) for m in plan['models'].values())} learning rates each. Success with its 95 % "
        "Wilson interval; **chosen**: the most successes (a tie: the recipe's own rate, listed first).",
    ]
    path = record / "provenance_validation.json"
    for prov in json.loads(path.read_text()) if path.is_file() else []:
        lines += ["", protocol.describe_run(prov, "validation")]
    for task, models in figures.items():
        lines += [
            "",
            f"## {task}",
            "",
            "| model | steps × batch | learning rate: success (95 % CI) | chosen |",
            "|---|---|---|---|",
        ]
        for name, row in models.items():
            cells = []
            for lr in plan["models"][name]["lrs"]:
                k_n = row["results"].get(f"{lr:g}")
                if k_n is None:
                    cells.append(f"{lr:g}: pending")
                    continue
                cells.append(f"{lr:g}: {pct(*k_n)}")
            batch = plan["models"][name]["batch"]
            lines.append(
                f"| {LABELS.get(name, name)} | {row['steps']} × {batch} | {'; '.join(cells)} | {row['chosen_lr'] or 'pending'} |"
            )
        edge = [
            LABELS.get(name, name)
            for name, row in models.items()
            if row["chosen_lr"] is not None
            and float(row["chosen_lr"]) in (min(plan["models"][name]["lrs"]), max(plan["models"][name]["lrs"]))
        ]
        if edge:
            lines += ["", f"Chosen at an edge of its grid, so the grid may not hold its best rate: {'; '.join(edge)}."]
    lines.append("")
    return write_md_and_json(report, REPORT_NAME, lines, {"plan": plan, "tasks": figures})


def main(argv: list[str] | None = None) -> int:
    return study_main(argv, "baseline_tuning", __doc__, PLAN, QUICK_PLAN, "validation", stages, write_report)


if __name__ == "__main__":
    sys.exit(main())

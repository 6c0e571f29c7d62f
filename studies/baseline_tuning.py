"""The baselines' tuning: DSSP and DP3 (trained with DP3's recipe, at three sizes) with the same tuning budget on
validation seeds, so that the memory tasks' and MetaWorld's test tables compare each at its best.

    python -m studies.baseline_tuning [--tasks tap swap put2 button-press ...] [--workers 2] [--work runs/baseline_tuning]
                                      [--report reports/baseline_tuning] [--report-only] [--quick]

Every model of the plan trains on the same data and sees the same number of training windows per task (the
memory study's DSSP budget: steps × 32 windows), at each of its configurations — two batch sizes × four learning
rates, 1e-4 to 3e-3, the same budget of eight configurations each — training seed 0, and is evaluated in closed loop
on the same validation scenes. The batch sizes: the recipe's own (DSSP 32 windows of one trajectory a step, DP3 128
windows drawn across the dataset) and the other's (DSSP 128, DP3 32): with the windows fixed, a smaller batch takes
more steps, and DP3's 128 assumes some 10^5 of them where the budget gives it 750 on tap. DP3's recipe (preset
``dp3_recipe``): its optimiser (AdamW, betas 0.95/0.999, weight decay 1e-6), its cosine schedule with a linear
warm-up, its EMA (power 0.75, at most 0.9999), its min/max normalisation and its sampling — windows drawn from the
whole dataset (``train.sampling=windows``) — with DP3's own batch and learning rate first among those tried. Decided
here where DP3's recipe assumes its own budget: the warm-up is 100 steps, as the ``sim`` preset's, not DP3's 500.
The sizes: the ``sim`` preset's parameter count (0.71 M) and about 4.8 M and 17 M (UNet widths ×2 and ×4).

MetaWorld: one task of each difficulty group (the MetaWorld plan's first four: button-press, basketball, assembly,
disassemble), trained as :mod:`studies.metaworld` trains (its 10 demonstrations, all trained on, its 100 epochs as
1000 steps of 32 windows, its horizons), the last weights evaluated; one configuration per model for the whole
suite, as DP3 uses one for all of MetaWorld, chosen on the four tasks' successes pooled.

The report picks each model's configuration by its validation success (a tie: the first in the plan's order, the
recipe's own batch and rate); those choices are what a test plan may use (:mod:`studies.memory_fair`, ``studies.metaworld
--fair``). One training seed and 20 scenes per configuration:
the choice is noisy, and the report gives the Wilson interval of each cell to show how much.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from dssp_core.errors import DSSPError
from studies import memory_tasks, metaworld, protocol
from studies.evaluations import study_main, write_md_and_json
from studies.runner import Stage
from studies.sim_study import pct
from studies.study_stages import (
    DP3_LABELS,
    DP3_SIZES,
    SIM_BATCH,
    collect_stage,
    dp3_recipe,
    eval_stage,
    export_stage,
    model_steps,
    train_stage,
    training_of,
)

REPORT_NAME = "baseline_tuning"
# the choices a test plan reads: this checkout's committed report (studies.memory_fair, studies.metaworld --fair)
ROOT = Path(__file__).resolve().parents[1]
CHOICES = ROOT / "reports" / REPORT_NAME / f"{REPORT_NAME}.json"
PLAN = {
    "tasks": {
        **{
            task: {"demos": spec["demos"], "windows": spec["steps"] * SIM_BATCH}
            for task, spec in memory_tasks.PLAN["tasks"].items()
        },
        # MetaWorld: one task of each difficulty group (the MetaWorld plan's first four), trained as that study
        # trains (its demonstrations, epochs and horizons, every demonstration trained on); one rate per model for
        # the suite, chosen on the four pooled
        **{
            task: {
                "sim_task": metaworld.task_id(metaworld.PLAN, task),
                "suite": "metaworld",
                "demos": metaworld.PLAN["demos"],
                "windows": metaworld.steps_of(metaworld.PLAN) * SIM_BATCH,
                "flags": ["--no-holdout", *metaworld.HORIZONS],
            }
            for task in metaworld.PLAN["tasks"][:4]
        },
    },
    "models": {
        "dssp": {"preset": "sim", "batches": [SIM_BATCH, 128], "lrs": [1e-3, 3e-4, 3e-3, 1e-4], "flags": []},
        **{
            name: {
                **dp3_recipe(name),
                "batches": [dp3_recipe(name)["batch"], SIM_BATCH],
                "lrs": [1e-4, 3e-4, 1e-3, 3e-3],
            }
            for name in DP3_SIZES
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
        "dssp": {"preset": "sim", "batches": [32], "lrs": [1e-3], "flags": []},
        "dp3_0.7m": {
            "preset": "dp3_recipe",
            "batches": [32, 16],
            "lrs": [1e-4, 1e-3],
            "flags": ["--set", "model.unet_down_dims=[16,32]"],
        },
    },
    "episodes": 1,
    "export_flags": ["--skip-verify", "--quantize", "none"],
}
LABELS = {"dssp": "DSSP (sim)", **DP3_LABELS}


def cell(task: str, model: str, lr: float, batch: int | None = None) -> str:
    """A configuration's name: at a batch other than the recipe's own (``batch``), the batch is in it."""
    return f"{task}_{model}" + (f"_b{batch}" if batch else "") + f"_lr{lr:g}"


def configurations(model: dict) -> list[tuple[int | None, int, float]]:
    """A model's configurations in the plan's order, the recipe's own batch first: (the batch as :func:`cell` names
    it, None for the recipe's own; the batch; the learning rate)."""
    own = model["batches"][0]
    return [(None if batch == own else batch, batch, lr) for batch in model["batches"] for lr in model["lrs"]]


def steps_of(plan: dict, task: str, model: str, batch: int) -> int:
    """The training steps that give ``model`` the task's budget of windows at ``batch``."""
    return model_steps(plan["tasks"][task]["windows"] // SIM_BATCH, {**plan["models"][model], "batch": batch})


def stages(plan: dict, tasks: list[str], record: Path) -> list[Stage]:
    """Every stage of ``tasks``; a configuration whose evaluation is in the record needs none."""
    first = protocol.split_seeds("validation", plan["episodes"])[0]
    out: list[Stage] = []
    for task in tasks:
        data, collected, task_stages = f"data/{task}.zarr", (f"collect_{task}",), []
        spec = plan["tasks"][task]
        sim_task = spec.get("sim_task", task)
        for name, model in plan["models"].items():
            for named, batch, lr in configurations(model):
                key = cell(task, name, lr, named)
                if (record / "evals" / f"{key}.json").is_file():
                    continue
                run, model_dir = f"runs/{key}", f"models/{key}"
                steps, flags = training_of(spec["windows"] // SIM_BATCH, {**model, "batch": batch, "lr": lr}, task)
                task_stages += [
                    train_stage(
                        key,
                        data,
                        run,
                        model["preset"],
                        steps,
                        plan["seed"],
                        *flags,
                        *spec.get("flags", ()),
                        after=collected,
                    ),
                    export_stage(
                        key, run, model_dir, "--force", "--threads", "1", *plan["export_flags"], after=(f"train_{key}",)
                    ),
                    eval_stage(key, model_dir, sim_task, plan["episodes"], first, after=(f"export_{key}",)),
                ]
        if task_stages:
            out += [collect_stage(task, sim_task, spec["demos"], data), *task_stages]
    return out


def _best(results: dict, model: dict) -> dict | None:
    """The configuration with the most successes, {"batch", "lr"} (a tie: the first in the plan's order, the
    recipe's own), or None until every configuration is recorded (``results``: {batch: {lr: (successes, n)}})."""
    recorded = [(b, f"{lr:g}") for _, b, lr in configurations(model) if f"{lr:g}" in results.get(str(b), {})]
    if len(recorded) < len(configurations(model)):
        return None
    batch, lr = max(recorded, key=lambda c: results[str(c[0])][c[1]][0])
    return {"batch": batch, "lr": lr}


def chosen(plan: dict, record: Path) -> dict:
    """Per task and model: every configuration's validation (successes, n) by batch and learning rate, the steps at
    each batch, and the chosen configuration (:func:`_best`); a task of a suite takes the one chosen on the suite's
    tasks pooled (:func:`pooled`)."""
    out: dict = {}
    for task in plan["tasks"]:
        for name, model in plan["models"].items():
            results: dict = {}
            for named, batch, lr in configurations(model):
                path = record / "evals" / f"{cell(task, name, lr, named)}.json"
                if path.is_file():
                    e = json.loads(path.read_text())
                    results.setdefault(str(batch), {})[f"{lr:g}"] = [e["successes"], e["n"]]
            out.setdefault(task, {})[name] = {
                "results": results,
                "chosen": _best(results, model),
                "steps": {str(b): steps_of(plan, task, name, b) for b in model["batches"]},
            }
    for suite, rows in pooled(plan, out).items():
        for task in suite_tasks(plan, suite):
            for name, row in rows.items():
                out[task][name]["chosen"] = row["chosen"]
    return out


def suite_tasks(plan: dict, suite: str) -> list[str]:
    return [task for task, spec in plan["tasks"].items() if spec.get("suite") == suite]


def pooled(plan: dict, figures: dict) -> dict:
    """Per suite and model: each configuration's successes over the suite's tasks pooled, and the one chosen on them
    (None until every task has every configuration)."""
    out: dict = {}
    for suite in sorted({spec["suite"] for spec in plan["tasks"].values() if "suite" in spec}):
        tasks = suite_tasks(plan, suite)
        for name, model in plan["models"].items():
            results: dict = {}
            for _, batch, lr in configurations(model):
                cells = [figures[task][name]["results"].get(str(batch), {}).get(f"{lr:g}") for task in tasks]
                if all(cells):
                    results.setdefault(str(batch), {})[f"{lr:g}"] = [sum(k for k, _ in cells), sum(n for _, n in cells)]
            out.setdefault(suite, {})[name] = {"results": results, "chosen": _best(results, model)}
    return out


def write_report(plan: dict, record: Path, report: Path, shown_record: str | None = None) -> Path:
    """``baseline_tuning.md`` and ``.json`` from the record alone."""
    figures = chosen(plan, record)
    scenes = protocol.split_seeds("validation", plan["episodes"])
    budgets = ", ".join(f"{task} {spec['windows']}" for task, spec in plan["tasks"].items())
    grids = {(len(m["batches"]), len(m["lrs"])) for m in plan["models"].values()}
    lines = [
        "# The baselines' tuning on validation seeds: DSSP and DP3 with DP3's recipe at three sizes",
        "",
        f"Rebuilt from `{shown_record or record}` by `python -m studies.baseline_tuning --report-only`. Training seed "
        f"{plan['seed']}, {plan['episodes']} closed-loop episodes per configuration on validation scenes {scenes[0]}–"
        f"{scenes[-1]} (a choice: not a test result); the same training windows per task for every model "
        f"({budgets}), "
        + " or ".join(f"{b} batch sizes × {n} learning rates" for b, n in sorted(grids))
        + " each, the recipe's own batch first. Success with its 95 % Wilson interval; **chosen**: the most "
        "successes (a tie: the first in the plan's order, the recipe's own batch and rate).",
    ]
    path = record / "provenance_validation.json"
    for prov in json.loads(path.read_text()) if path.is_file() else []:
        lines += ["", protocol.describe_run(prov, "validation")]
    for task, models in figures.items():
        suite = plan["tasks"][task].get("suite")
        lines += ["", f"## {task}" + (f" ({suite}: chosen on the suite's tasks pooled)" if suite else "")]
        lines += _table(plan, models, pooled_from=suite)
    for suite, models in pooled(plan, figures).items():
        lines += ["", f"## {suite}: {', '.join(suite_tasks(plan, suite))} pooled"]
        lines += _table(plan, models)
    lines.append("")
    return write_md_and_json(
        report, REPORT_NAME, lines, {"plan": plan, "tasks": figures, "suites": pooled(plan, figures)}
    )


def describe(choice: dict | None) -> str | None:
    return choice and f"{choice['lr']} at batch {choice['batch']}"


def _table(plan: dict, models: dict, pooled_from: str | None = None) -> list[str]:
    """One task's (or one suite's pooled) table: a row per model and batch, each rate's success, and the chosen
    configuration; a note where a chosen rate lies at an edge of its grid (on a suite's task the choice is the
    suite's, noted in its own table)."""
    lines = [
        "",
        "| model | steps × batch | learning rate: success (95 % CI) | chosen |",
        "|---|---|---|---|",
    ]
    for name, row in models.items():
        model = plan["models"][name]
        choice = describe(row["chosen"])
        choice = f"{choice} ({pooled_from})" if pooled_from and choice else choice or "pending"
        for i, batch in enumerate(model["batches"]):
            results = row["results"].get(str(batch), {})
            cells = [
                f"{lr:g}: {pct(*results[f'{lr:g}']) if f'{lr:g}' in results else 'pending'}" for lr in model["lrs"]
            ]
            steps = f"{row['steps'][str(batch)]} × {batch}" if "steps" in row else f"batch {batch}"
            label = LABELS.get(name, name) if i == 0 else ""
            lines.append(f"| {label} | {steps} | {'; '.join(cells)} | {choice if i == 0 else ''} |")
    edge = [
        LABELS.get(name, name)
        for name, row in models.items()
        if not pooled_from
        and row["chosen"] is not None
        and float(row["chosen"]["lr"]) in (min(plan["models"][name]["lrs"]), max(plan["models"][name]["lrs"]))
    ]
    if edge:
        lines += ["", f"Chosen at an edge of its grid, so the grid may not hold its best rate: {'; '.join(edge)}."]
    return lines


def read_choices(path: Path = CHOICES) -> dict:
    """The figures of the tuning's report at ``path`` (``baseline_tuning.json``), or one line saying how to make
    them."""
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise DSSPError(
            f"cannot read the tuning report {path} ({exc}): rebuild it with python -m studies.baseline_tuning"
        ) from exc


def chosen_configurations(choices: dict, keys: list[str], where: str = "tasks") -> dict[str, dict[str, dict]]:
    """{model: {key: {"batch": int, "lr": float}}}: every model's configuration chosen on each task
    (``where="tasks"``) or suite (``"suites"``) of ``keys``, refused in one line, with the command that completes it,
    while one is pending."""
    out: dict[str, dict[str, dict]] = {}
    for key in keys:
        rows = choices.get(where, {}).get(key, {})
        tasks = suite_tasks(PLAN, key) if where == "suites" else [key]
        for name in PLAN["models"]:
            choice = rows.get(name, {}).get("chosen")
            if choice is None:
                raise DSSPError(
                    f"the configuration of {name} on {key} is not chosen yet: run python -m studies.baseline_tuning "
                    f"--tasks {' '.join(tasks)}, then commit its record"
                )
            out.setdefault(name, {})[key] = {"batch": int(choice["batch"]), "lr": float(choice["lr"])}
    return out


def main(argv: list[str] | None = None) -> int:
    return study_main(argv, "baseline_tuning", __doc__, PLAN, QUICK_PLAN, "validation", stages, write_report)


if __name__ == "__main__":
    sys.exit(main())

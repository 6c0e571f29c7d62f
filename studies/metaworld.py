"""MetaWorld under DP3's protocol: DSSP, DP3 and DSSP without history on the same demonstrations and budget,
scored as the paper scores them and on held-out test seeds.

    python -m studies.metaworld --tasks easy:2 medium:2 hard:2 very_hard:2       # the validation split
    python -m studies.metaworld --freeze
    python -m studies.metaworld --split test [--only button-press]            # all, or some, of the plan's tasks
    python -m studies.metaworld --tasks all --paper-budget --cost                # what the paper's budget costs

For each task (``dssp_sim.metaworld_env``): MetaWorld's scripted expert records the plan's demonstrations
(``dssp-sim collect --task metaworld/NAME``: 200-step episodes kept at 5 successful steps, 512-point clouds in
DP3's frame, DP3's zarr); each model of the plan trains on them with every training seed, keeping its EMA
weights ``evaluations`` times along training (``train.keep_every``); each kept checkpoint is exported (int8) and
evaluated in closed loop through the runtime on the validation seeds. The report gives

- **the paper's metric**: per training seed the mean of the top five of those evaluations (20 episodes each in
  the paper, every 200 of 1000 epochs), then the mean and standard deviation over training seeds. The metric
  picks its best evaluations on the very episodes it reports, so it is optimistic by construction; it is given
  because it is the paper's, beside
- **the last checkpoint on the test split** (``--split test``, after ``--freeze``): success over training
  seeds × test scenes with its cluster-bootstrap interval, each difference with DSSP with its exact paired test.

Per difficulty group the table sits beside the paper's (DSSP and DP3), with the budget as a fraction of the
paper's (epochs × demonstrations, model size). The paper's 34 tasks are not named in it (21 easy, 4 medium,
4 hard, 5 very hard of the 50): ``--tasks`` takes names and the groups of Seo et al. (2022) that DP3 reports
by, ``GROUP:N`` for the first N of a group in alphabetical order, or ``all``.
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import json
import sys
from pathlib import Path

import numpy as np

from dssp_core.cli_runner import ArgumentParser, run_cli
from dssp_core.errors import DSSPError
from dssp_core.files import atomic_write_text
from studies import protocol
from studies.evaluations import run_and_keep, write_md_and_json
from studies.runner import Stage
from studies.stats import (
    FAMILY_NOTE,
    cluster_bootstrap,
    compare,
    describe_p,
    disagreements,
    holm_family,
    partial_family_note,
)
from studies.study_stages import (
    DP3_LABELS,
    DP3_SIZES,
    collect_stage,
    dp3_recipe,
    eval_stage,
    export_stage,
    model_steps,
    seeds_of,
    train_stage,
    training_of,
)

REPORT_NAME = "metaworld"
RECORD_DIR = "record"
TOP = 5  # the paper's metric: the mean of the top five evaluations
# MetaWorld's horizons in the paper (its Table of MetaWorld hyper-parameters; DP3's MetaWorld config has the same)
HORIZONS = [
    "--set",
    "model.n_obs_steps=2",
    "--set",
    "model.horizon=4",
    "--set",
    "model.n_action_steps=3",
    "--set",
    "model.n_points=512",
]
PLAN = {
    "suite": "metaworld",
    # two tasks of each difficulty group, the first two of each in alphabetical order (chosen before any result),
    # one of each group first so that a partial run covers every group
    "tasks": [
        "button-press",
        "basketball",
        "assembly",
        "disassemble",
        "button-press-topdown",
        "bin-picking",
        "hand-insert",
        "pick-place-wall",
    ],
    "demos": 10,
    "epochs": 100,  # the paper trains 1000 epochs; an epoch is one step per training episode (README, "Epochs")
    "evaluations": 5,  # kept checkpoints, evenly along training, each evaluated on the validation seeds
    "models": {
        "dssp": {"preset": "sim", "flags": HORIZONS},
        "dp3_sim": {"preset": "dp3_sim", "flags": HORIZONS},
        "wo_history": {"preset": "sim", "flags": [*HORIZONS, "--no-history"]},
    },
    "seeds": [0, 1, 2],
    "episodes": {"validation": 20, "test": 50},
    "export_flags": ["--quantize", "int8", "--verify-steps", "200"],
}
# The paper's budget and sizes (a GPU job): the `metaworld` preset (45 M parameters) and DP3 at its own size.
PAPER_PLAN = {
    **PLAN,
    "epochs": 1000,
    "models": {
        "dssp": {"preset": "metaworld", "flags": []},
        "dp3": {"preset": "dp3", "flags": HORIZONS},
        "wo_history": {"preset": "metaworld", "flags": ["--no-history"]},
    },
}
# This project's memory variant (dssp_sim.metaworld_env: the goal shown for the first 10 steps, then hidden), same
# protocol and budget as PLAN; no paper to compare with.
MEMORY_PLAN = {**PLAN, "suite": "metaworld-cue", "tasks": ["reach", "push"]}
QUICK_PLAN = {
    "suite": "metaworld",
    "tasks": ["reach"],
    "demos": 2,
    "epochs": 2,
    "evaluations": 2,
    "models": {
        "dssp": {"preset": "tiny", "flags": ["--set", "model.n_points=512"]},
        "dp3_sim": {"preset": "dp3_sim", "flags": [*HORIZONS, "--set", "model.unet_down_dims=[16,32]"]},
        "wo_history": {"preset": "tiny", "flags": ["--set", "model.n_points=512", "--no-history"]},
    },
    "seeds": [0, 1],
    "episodes": {"validation": 1, "test": 1},
    "export_flags": ["--skip-verify", "--quantize", "none"],
}
LABELS = {
    "dssp": "DSSP",
    "dp3_sim": "DP3 (sim size)",
    **DP3_LABELS,
    "dp3": "DP3 (its own size)",
    "wo_history": "DSSP w/o history",
}
FAIR_SEEDS = {"headline": [0, 1, 2, 3, 4], "other": [0, 1, 2]}  # DSSP and DP3; DSSP w/o history


def fair_plan(choices: Path | None = None) -> dict:
    """The plan with every model at its best (``--fair``): :data:`PLAN`'s tasks, demonstrations and budget; DSSP and
    DP3 with its recipe at three sizes (the same training windows), each at the one batch and rate its tuning chose
    for the suite (:mod:`studies.baseline_tuning`'s report at ``choices``, default the committed one), training seeds
    0–4; DSSP w/o history at DSSP's, seeds 0–2."""
    from studies import baseline_tuning  # here: the tuning imports this study's plan

    configs = baseline_tuning.chosen_configurations(
        baseline_tuning.read_choices(choices or baseline_tuning.CHOICES), ["metaworld"], "suites"
    )
    chosen = {name: by_suite["metaworld"] for name, by_suite in configs.items()}
    dssp = {"preset": "sim", "flags": HORIZONS, **chosen["dssp"]}
    return {
        **PLAN,
        "tuned_by": "studies.baseline_tuning",
        "models": {
            "dssp": dssp,
            **{name: {**dp3_recipe(name, *HORIZONS), **chosen[name]} for name in DP3_SIZES},
            "wo_history": {**dssp, "flags": [*HORIZONS, "--no-history"], "seeds": FAIR_SEEDS["other"]},
        },
        "seeds": FAIR_SEEDS["headline"],
    }


# The paper's MetaWorld table (mean ± std over 3 seeds, the top-5 metric), per difficulty group.
PAPER = {
    "dssp": {"easy": (90.5, 2.1), "medium": (67.4, 4.1), "hard": (54.6, 2.4), "very_hard": (71.3, 3.8)},
    "dp3": {"easy": (87.3, 2.2), "medium": (44.5, 8.7), "hard": (32.7, 7.7), "very_hard": (39.4, 9.0)},
}
PAPER_TASKS = {"easy": 21, "medium": 4, "hard": 4, "very_hard": 5}
PAPER_EPOCHS = 1000
PAPER_DEMOS = 10


def _mw():
    from dssp_sim import metaworld_env  # MuJoCo comes with it: imported when a study needs the task list

    return metaworld_env


def select_tasks(items: list[str]) -> list[str]:
    """Task names from names, groups, ``GROUP:N`` (the first N of a group, alphabetically) and ``all``."""
    mw = _mw()
    out: list[str] = []
    for item in items:
        group, _, count = item.partition(":")
        if count:
            if group not in mw.DIFFICULTY or not count.isdecimal() or int(count) < 1:
                raise DSSPError(f"--tasks {item}: GROUP:N takes a group ({', '.join(mw.DIFFICULTY)}) and a count >= 1")
            names = sorted(mw.DIFFICULTY[group])[: int(count)]
        else:
            names = mw.tasks_of([item])
        out.extend(n for n in names if n not in out)
    return out


def task_id(plan: dict, task: str) -> str:
    """The task as dssp-sim names it: ``metaworld/NAME`` or the memory variant's ``metaworld-cue/NAME``."""
    return f"{plan.get('suite', 'metaworld')}/{task}"


def is_fair(plan: dict) -> bool:
    """Whether ``plan`` is :func:`fair_plan`'s (its rates chosen by the tuning)."""
    return "tuned_by" in plan


def is_memory(plan: dict) -> bool:
    return plan.get("suite") == "metaworld-cue"


def steps_of(plan: dict, model: str | None = None) -> int:
    """The training steps of the plan's ``model`` (default: at the ``sim`` preset's batch, an epoch one step per
    demonstration): a model with its own batch takes the same windows in its own steps."""
    steps = plan["epochs"] * plan["demos"]
    return model_steps(steps, plan["models"][model]) if model else steps


def checkpoint_steps(plan: dict, model: str | None = None) -> list[int]:
    """The kept checkpoints' steps: ``evaluations`` of them, evenly along ``model``'s training, the last at the
    end."""
    steps, k = steps_of(plan, model), plan["evaluations"]
    if steps % k:
        raise DSSPError(f"{steps} steps do not divide into {k} evaluations; change the plan's epochs or evaluations")
    return [steps // k * (i + 1) for i in range(k)]


def model_order(plan: dict) -> list[str]:
    """The plan's models as the report lists them: DSSP first, then as :data:`LABELS` orders them (a record's
    plan.json keeps its keys sorted)."""
    order = list(LABELS)
    return sorted(plan["models"], key=lambda n: order.index(n) if n in order else len(order))


def eval_name(task: str, model: str, seed: int, step: int, split: str) -> str:
    return f"{task}_{model}_s{seed}_step{step}_{split}"


def stages(plan: dict, split: str, tasks: list[str], record: Path) -> list[Stage]:
    """Every stage of ``tasks`` for ``split`` not yet in the record: on validation every kept checkpoint is
    evaluated, on test the last one."""
    n = plan["episodes"][split]
    first = protocol.split_seeds(split, n)[0]
    export_options = ("--force", "--threads", "1", *plan["export_flags"])
    out: list[Stage] = []
    for task in tasks:
        data, collected, sim_task = f"data/{task}.zarr", (f"collect_{task}",), task_id(plan, task)
        need_data = False
        for name, model in plan["models"].items():
            steps, flags = training_of(steps_of(plan), model, task)
            kept, preset = checkpoint_steps(plan, name), model["preset"]
            keeping = ("--no-holdout", "--set", f"train.keep_every={steps // plan['evaluations']}")
            for seed in seeds_of(plan, model):
                key = f"{task}_{name}_s{seed}"
                run = f"runs/{key}"
                wanted = [
                    s
                    for s in (kept if split == "validation" else kept[-1:])
                    if not (record / "evals" / f"{eval_name(task, name, seed, s, split)}.json").is_file()
                ]
                if not wanted:
                    continue
                need_data = True
                out.append(train_stage(key, data, run, preset, steps, seed, *flags, after=collected, options=keeping))
                for step in wanted:
                    ckpt, snapshot = f"{key}_step{step}", f"{run}/snapshots/step_{step:07d}"
                    result = eval_name(task, name, seed, step, split)
                    out += [
                        export_stage(ckpt, snapshot, f"models/{ckpt}", *export_options, after=(f"train_{key}",)),
                        eval_stage(result, f"models/{ckpt}", sim_task, n, first, after=(f"export_{ckpt}",)),
                    ]
        if need_data:
            out.insert(0, collect_stage(task, sim_task, plan["demos"], data))
    return out


def definition_hash() -> str:
    """The benchmark's definition: metaworld's version and this project's MetaWorld wrapper (first 16 hex digits)."""

    mw = _mw()
    try:
        version = importlib.metadata.version("metaworld")
    except importlib.metadata.PackageNotFoundError:
        raise DSSPError(f"MetaWorld is not installed; install it with: {mw.INSTALL}") from None
    h = hashlib.sha256(version.encode() + b"\0" + Path(mw.__file__).read_bytes())
    return h.hexdigest()[:16]


# ------------------------------------------------------------------------------------------------ report
def _load(record: Path, task: str, model: str, seed: int, step: int, split: str) -> dict | None:
    path = record / "evals" / f"{eval_name(task, model, seed, step, split)}.json"
    return json.loads(path.read_text()) if path.is_file() else None


def paper_metric(rates: list[float], top: int = TOP) -> float:
    """The mean of the ``top`` best success rates of one training seed's evaluations (all of them when fewer)."""
    return float(np.mean(sorted(rates, reverse=True)[:top]))


def figures_of(plan: dict, record: Path) -> dict:
    """Every figure the report states, from the record alone: per task and model, the paper's metric per training
    seed (validation) and the last checkpoint's test grid; per difficulty group, the means over its tasks."""
    mw = _mw()
    out: dict = {"tasks": {}, "groups": {}}
    for task in plan["tasks"]:
        rows = {}
        for name in model_order(plan):
            row: dict = {}
            per_seed = []
            kept, seeds = checkpoint_steps(plan, name), seeds_of(plan, plan["models"][name])
            for seed in seeds:
                evals = [_load(record, task, name, seed, s, "validation") for s in kept]
                if any(e is None for e in evals):
                    per_seed = None
                    break
                per_seed.append(paper_metric([e["successes"] / e["n"] for e in evals]))
            if per_seed is not None:
                row["top5"] = {"per_seed": per_seed, "mean": float(np.mean(per_seed)), "std": float(np.std(per_seed))}
            tests = [_load(record, task, name, seed, kept[-1], "test") for seed in seeds]
            if all(t is not None for t in tests):
                scenes = [e["seed"] for e in tests[0]["episodes"]]
                if any([e["seed"] for e in t["episodes"]] != scenes for t in tests):
                    raise DSSPError(
                        f"{task}/{name}: the training seeds were tested on different scenes; the study pairs them"
                    )
                grid = [[int(e["success"]) for e in t["episodes"]] for t in tests]
                mean, lo, hi = cluster_bootstrap(grid)
                row["test"] = {"grid": grid, "success": mean, "ci": [lo, hi]}
            rows[name] = row
        out["tasks"][task] = rows
    comparisons = [  # each task's models against its DSSP: the per-task table's family for Holm
        (row["test"], compare(row["test"]["grid"], rows["dssp"]["test"]["grid"]))
        for rows in out["tasks"].values()
        for name, row in rows.items()
        if name != "dssp" and "test" in row and "test" in rows.get("dssp", {})
    ]
    holm_family(c for _, c in comparisons)
    for test, c in comparisons:
        test.update(delta_ci=c.pop("ci"), **c)
    # the family when every row is in: each task's models against its DSSP
    out["holm"] = {"recorded": len(comparisons), "family": len(out["tasks"]) * (len(model_order(plan)) - 1)}
    for group in mw.DIFFICULTY:
        tasks = [t for t in plan["tasks"] if mw.difficulty_of(t) == group]
        if not tasks:
            continue
        g = {}
        for name in model_order(plan):
            top = [out["tasks"][t][name].get("top5", {}).get("per_seed") for t in tasks]
            grids = [out["tasks"][t][name].get("test", {}).get("grid") for t in tasks]
            per_seed = np.mean(top, axis=0) if None not in top else None  # each training seed's mean over the tasks
            # the group's test success: its tasks' scenes side by side, intervals over training seeds x scenes
            test = cluster_bootstrap(np.concatenate(grids, axis=1)) if None not in grids else None
            g[name] = {
                "tasks": len(tasks),
                "top5": float(np.mean(per_seed)) if per_seed is not None else None,
                "top5_std": float(np.std(per_seed)) if per_seed is not None else None,
                "test": test[0] if test else None,
                "test_ci": list(test[1:]) if test else None,
            }
        out["groups"][group] = g
    return out


def _cell(x: float | None, spread: float | list | None = None) -> str:
    """A percentage, with ``± std`` (a float) or its interval (a [low, high] list)."""
    if x is None:
        return "pending"
    if isinstance(spread, list):
        return f"{100 * x:.1f} ({100 * spread[0]:.0f}–{100 * spread[1]:.0f})"
    return f"{100 * x:.1f}" + ("" if spread is None else f" ± {100 * spread:.1f}")


def report_lines(plan: dict, record: Path, shown_record: str | None = None) -> tuple[list[str], dict]:
    figures = figures_of(plan, record)
    steps, kept = steps_of(plan), checkpoint_steps(plan)
    ratio = plan["epochs"] / PAPER_EPOCHS
    memory = is_memory(plan)
    fair = is_fair(plan)
    title = (
        "# MetaWorld with a cue that disappears (this project's memory variant): DSSP, DP3 and DSSP w/o history"
        if memory
        else "# MetaWorld under DP3's protocol, every model at its best: DSSP, DP3 with its recipe at three sizes, "
        "DSSP w/o history"
        if fair
        else "# MetaWorld under DP3's protocol: DSSP, DP3 and DSSP w/o history"
    )
    lines = [
        title,
        "",
        *(
            [
                "The variant (`metaworld-cue/NAME`, dssp_sim/metaworld_env.py) is this project's, not MetaWorld's: the "
                "task's goal marker, a 4 cm sphere, is in the clouds for the first 10 steps of an episode, then hidden; the "
                "expert knows the goal throughout, a policy only from what it remembers. The paper reports no such task.",
                "",
            ]
            if memory
            else []
        ),
        f"Rebuilt from `{shown_record or record}` by `python -m studies.metaworld{' --memory' * memory}{' --fair' * fair} "
        "--report-only`. "
        f"{plan['demos']} expert demonstrations per task (MetaWorld's scripted policies, demonstration seeds from 0), "
        f"512-point clouds in DP3's frame; training seeds {plan['seeds']}; {plan['epochs']} epochs = {steps} steps "
        f"({ratio:.2f} of the paper's {PAPER_EPOCHS} epochs); models "
        + ", ".join(f"{LABELS.get(n, n)} (`--preset {plan['models'][n]['preset']}`)" for n in model_order(plan))
        + "."
        + (
            " Each model at the learning rate and batch its tuning chose for the suite on validation seeds "
            "(`reports/baseline_tuning`): "
            + ", ".join(f"{LABELS.get(n, n)} {m['lr']:g} at batch {m['batch']}" for n, m in plan["models"].items())
            + ". Every model takes the same training windows, in its own steps at its own batch "
            f"(its checkpoints at the same fractions of its training); {LABELS['wo_history']} has training seeds "
            f"{plan['models']['wo_history']['seeds']}."
            if fair
            else ""
        ),
        "",
        f"**Paper metric** (validation seeds): each training seed's checkpoints at steps {kept} are evaluated on "
        f"{plan['episodes']['validation']} episodes; per seed the mean of the top {TOP} (of {len(kept)}), then mean ± std "
        "over training seeds"
        + (
            ". It selects on the evaluations it reports, so it is optimistic."
            if TOP < len(kept)
            else f": with {len(kept)} checkpoints that is the plain mean of them all, no selection."
        )
        + f" **Test**: the last checkpoint on {plan['episodes']['test']} test scenes (the same for every model), 95 % "
        "two-way cluster-bootstrap interval; a group's test success pools its tasks' scenes (interval over training "
        "seeds × scenes). Δ vs DSSP: paired difference with its interval. "
        + FAMILY_NOTE.replace("within its table", "within the per-task table"),
    ]
    for split in ("validation", "test"):
        path = record / f"provenance_{split}.json"
        for prov in json.loads(path.read_text()) if path.is_file() else []:
            lines += ["", protocol.describe_run(prov, split, definition="benchmark definition")]
    for other in protocol.trained_elsewhere(record):
        lines += ["", protocol.describe_trained_elsewhere(other, LABELS)]
    names = model_order(plan)
    if not memory:
        lines += ["", "## Per difficulty group, beside the paper", "", *group_table(figures, names, ratio)]
    lines += [
        "",
        "## Per task",
        "",
        "| task | model | top-5 (mean ± std over seeds) | per seed | test success % (95 % CI) | Δ vs DSSP | paired test "
        "| seed test |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for task, rows in figures["tasks"].items():
        for name, row in rows.items():
            t5 = row.get("top5")
            top = f"{100 * t5['mean']:.1f} ± {100 * t5['std']:.1f}" if t5 else "pending"
            seeds = ", ".join(f"{100 * v:.0f}" for v in t5["per_seed"]) if t5 else ""
            t = row.get("test")
            test = f"{100 * t['success']:.0f} ({100 * t['ci'][0]:.0f}–{100 * t['ci'][1]:.0f})" if t else "pending"
            delta = (
                f"{100 * t['delta']:+.0f} ({100 * t['delta_ci'][0]:+.0f} to {100 * t['delta_ci'][1]:+.0f})"
                if t and "delta" in t
                else "—"
            )
            p = describe_p(t["p"], holm_p=t["p_holm"]) if t and "p" in t else "—"
            ps = describe_p(t["p_seeds"], holm_p=t["p_seeds_holm"]) if t and "p" in t else "—"
            lines.append(f"| {task} | {LABELS.get(name, name)} | {top} | {seeds} | {test} | {delta} | {p} | {ps} |")
    disagree = [
        f"- {task}, {x}"
        for task, rows in figures["tasks"].items()
        for x in disagreements(
            {
                n: {"ci": r["test"]["delta_ci"], "p_holm": r["test"]["p_holm"]}
                for n, r in rows.items()
                if "p" in r.get("test", {})
            },
            LABELS,
        )
    ]
    lines += ["", "Where the paired test and the interval disagree:", "", *disagree] if disagree else []
    lines += partial_family_note(figures["holm"]["recorded"], figures["holm"]["family"])
    lines.append("")
    return lines, figures


def group_table(figures: dict, names: list[str], ratio: float) -> list[str]:
    """Per difficulty group: this study's figures beside the paper's table, and the budget (the report's
    section and the README's ``metaworld`` block)."""
    lines = [
        "| group (tasks here / paper's) | "
        + " | ".join(f"{LABELS.get(n, n)} top-5" for n in names)
        + " | "
        + " | ".join(f"{LABELS.get(n, n)} test" for n in names)
        + " | paper DSSP | paper DP3 |",
        "|---|" + "---:|" * (2 * len(names) + 2),
    ]
    for group, g in figures["groups"].items():
        paper = [f"{PAPER[m][group][0]} ± {PAPER[m][group][1]}" for m in ("dssp", "dp3")]
        lines.append(
            f"| {group} ({g[names[0]]['tasks']} / {PAPER_TASKS[group]}) | "
            + " | ".join(_cell(g[n]["top5"], g[n]["top5_std"]) for n in names)
            + " | "
            + " | ".join(_cell(g[n]["test"], g[n]["test_ci"]) for n in names)
            + f" | {paper[0]} | {paper[1]} |"
        )
    lines += [
        "",
        f"Budget: {ratio:.2f} of the paper's epochs, the models at the sizes named above (the paper's DSSP "
        "is the `metaworld` preset, 45 M parameters, and its DP3 is DP3's own size); the paper's figures "
        "average its 34 tasks, these the tasks run here. No claim beyond this budget.",
    ]
    return lines


def readme_table(record: Path) -> str:
    """The README's ``metaworld`` block: :func:`group_table` of the plan the record was made with."""
    plan = json.loads((Path(record) / "plan.json").read_text())
    return "\n".join(group_table(figures_of(plan, record), model_order(plan), plan["epochs"] / PAPER_EPOCHS)) + "\n"


def write_report(plan: dict, record: Path, report: Path, shown_record: str | None = None) -> Path:
    """``metaworld.md`` and ``metaworld.json`` (every figure), from the record alone."""
    lines, figures = report_lines(plan, record, shown_record)
    return write_md_and_json(report, REPORT_NAME, lines, {"plan": plan, **figures})


def cost(plan: dict, tasks: list[str], record: Path) -> str:
    """What ``plan`` on ``tasks`` asks for, and what it would take on this study's machine, from the seconds its
    record keeps (training steps per second and evaluation seconds per episode, measured here)."""
    seeds = {name: len(seeds_of(plan, model)) for name, model in plan["models"].items()}
    runs = len(tasks) * sum(seeds.values())
    steps = len(tasks) * sum(n * steps_of(plan, name) for name, n in seeds.items())
    episodes = runs * (plan["evaluations"] * plan["episodes"]["validation"] + plan["episodes"]["test"])
    lines = [
        f"{len(tasks)} tasks x ({' + '.join(f'{n} seeds of {name}' for name, n in seeds.items())}) = {runs} trainings "
        f"({steps} steps in all), {runs * plan['evaluations']} exports, {episodes} evaluation episodes"
    ]
    gpu = _gpu_step_ms() if any(m["preset"] == "metaworld" for m in plan["models"].values()) else None
    if gpu is not None:
        ms, where = gpu
        lines.append(
            f"on {where} (reports/gpu, the `metaworld` preset's step, {ms:.0f} ms): the trainings take about "
            f"{steps * ms / 3.6e6:.0f} GPU-hours at the paper's DSSP size, one after another (DP3 at its own "
            "size and the smaller models differ; evaluation is extra)"
        )
    seconds = _measured(record)
    if seconds is None:
        lines.append("no seconds measured yet: the record has no finished evaluation")
        return "\n".join(lines)
    evals_h = episodes * seconds["episode_s"] / 3600
    if seconds["step_s"] is None:
        lines.append(
            f"measured by this record's runs: {seconds['episode_s']:.1f} s per evaluation episode, one core: "
            f"about {evals_h:.0f} core-hours of evaluation on that machine (its trainings ran elsewhere, "
            "record/trained_elsewhere.json)"
        )
    else:
        lines.append(
            f"measured by this record's runs: {seconds['step_s'] * 1e3:.0f} ms per training step (its plan's "
            f"models), {seconds['episode_s']:.1f} s per evaluation episode, one core each: about "
            f"{(steps * seconds['step_s']) / 3600 + evals_h:.0f} core-hours on that machine (larger models "
            "train slower: the paper's 45 M-parameter preset is a GPU job, `benchmarks/train_step_time.py "
            "--paper` times its step)"
        )
    return "\n".join(lines)


GPU_RECORD = Path(__file__).resolve().parent.parent / "reports/gpu/train_step_time_paper_h200.json"


def _gpu_step_ms() -> tuple[float, str] | None:
    """The `metaworld` preset's training step on a GPU, from the committed record (benchmarks/train_step_time.py)."""
    if not GPU_RECORD.is_file():
        return None
    report = json.loads(GPU_RECORD.read_text())
    rows = [r for r in report["rows"] if r.get("preset") == "metaworld"]
    return (float(rows[0]["median_ms"]), report["machine"].get("gpu", "a GPU")) if rows else None


def _measured(record: Path) -> dict | None:
    """{step_s, episode_s}: the record's median training step (None when its trainings ran elsewhere or none
    finished) and evaluation episode, in seconds; None without a finished evaluation."""
    folder = record / "seconds"
    train_seconds = [float(p.read_text()) for p in folder.glob("train_*.seconds")] if folder.is_dir() else []
    evals = (
        [(float(p.read_text()), p.stem[len("eval_") :]) for p in folder.glob("eval_*.seconds")]
        if folder.is_dir()
        else []
    )
    if not evals:
        return None
    step_s = None
    if train_seconds and not protocol.trained_elsewhere(record):
        step_s = float(np.median(train_seconds)) / steps_of(json.loads((record / "plan.json").read_text()))
    per_episode = []
    for secs, name in evals:
        e = json.loads((record / "evals" / f"{name}.json").read_text())
        per_episode.append(secs / e["n"])
    return {"step_s": step_s, "episode_s": float(np.median(per_episode))}


def run_study(
    plan: dict, split: str, tasks: list[str], work: Path, report: Path, workers: int, quick: bool = False
) -> Path:
    """Run ``plan``'s stages for ``tasks`` on ``split`` and rebuild the report (``quick``: a test plan, which may run
    on uncommitted code)."""
    record = report / RECORD_DIR
    if split == "test":
        protocol.check_frozen(record, plan, definition_hash())
    stage_list = stages(plan, split, tasks, record)
    protocol.note_provenance(record, plan, split, tasks, definition_hash(), allow_changes=quick)
    record.mkdir(parents=True, exist_ok=True)
    atomic_write_text(record / "plan.json", json.dumps(plan, indent=1, sort_keys=True) + "\n")
    run_and_keep(work, record, stage_list, workers, f"MetaWorld {', '.join(tasks)} on the {split} split", seconds=True)
    return write_report(plan, record, report)


def main(argv: list[str] | None = None) -> int:
    p = ArgumentParser(prog="python -m studies.metaworld", description=__doc__.split("\n\n")[0])
    p.add_argument("--split", choices=list(protocol.SPLITS), default="validation")
    p.add_argument(
        "--tasks",
        nargs="+",
        metavar="TASK",
        help="names, groups (easy, medium, hard, very_hard), GROUP:N (its first N alphabetically) or all "
        "(default: the plan's 8 tasks, two of each group)",
    )
    p.add_argument(
        "--only",
        nargs="+",
        metavar="TASK",
        help="run only these of the plan's tasks now (the plan, and what it freezes, stays whole)",
    )
    p.add_argument("--workers", type=int, default=2, help="stages side by side, one thread each (default 2)")
    p.add_argument(
        "--memory",
        action="store_true",
        help="the memory variant (metaworld-cue/NAME: reach and push, the goal shown for 10 steps, then "
        "hidden), same protocol and budget; work and report default to runs/ and reports/metaworld_cue",
    )
    p.add_argument(
        "--fair",
        action="store_true",
        help="every model at its best: DP3 with its recipe at three sizes, each model at the batch and rate its tuning chose "
        "(studies.baseline_tuning), five training seeds on DSSP and DP3; work and report default to runs/ and "
        "reports/metaworld_fair",
    )
    p.add_argument("--work", type=Path, help="datasets, runs, models, evaluations, logs (default runs/metaworld)")
    p.add_argument("--report", type=Path, help="the report and its record (default reports/metaworld)")
    p.add_argument(
        "--freeze", action="store_true", help="freeze the plan for the test split (after the validation split)"
    )
    p.add_argument("--reason", help="with --freeze, again on a changed benchmark definition: why (kept in the record)")
    p.add_argument("--report-only", action="store_true", help="run nothing: rebuild the report from the record")
    p.add_argument(
        "--paper-budget",
        action="store_true",
        help="the paper's budget and sizes (1000 epochs, the 45 M-parameter `metaworld` preset, DP3's own "
        "size): a GPU job",
    )
    p.add_argument("--cost", action="store_true", help="run nothing: print what the plan on --tasks asks for")
    p.add_argument("--quick", action="store_true", help="a tiny plan (tests)")
    args = p.parse_args(argv)

    folder = "metaworld_cue" if args.memory else "metaworld_fair" if args.fair else "metaworld"
    args.work = args.work or Path("runs") / folder
    args.report = args.report or Path("reports") / folder
    if args.memory and args.paper_budget:
        p.error("--memory runs this project's variant at the plan's budget; the paper has no such task (drop one)")
    if args.fair and (args.memory or args.paper_budget or args.quick):
        p.error("--fair is the plan's tasks and budget with tuned models: drop --memory, --paper-budget and --quick")

    def _main() -> int:
        plan = dict(
            QUICK_PLAN if args.quick else PAPER_PLAN if args.paper_budget else fair_plan() if args.fair else PLAN
        )
        if args.memory:
            plan = {**plan, "suite": "metaworld-cue", "tasks": MEMORY_PLAN["tasks"] if not args.quick else ["reach"]}
        if args.tasks:
            plan["tasks"] = select_tasks(args.tasks)
        for task in plan["tasks"] if args.memory else ():
            _mw().task_name(task_id(plan, task))  # one of the cue tasks, or one line saying which are
        record = args.report / RECORD_DIR
        if args.cost:
            print(cost(plan, plan["tasks"], record))
            return 0
        if args.freeze:  # again after the definition changed: the tasks already tested stay on the earlier one
            tested = [t for t in plan["tasks"] if any((record / "evals").glob(f"{t}_*_test.json"))]
            print(
                f"plan {protocol.freeze_plan(record, plan, tested, definition=definition_hash(), reason=args.reason)} "
                "frozen in "
                f"{record / protocol.FROZEN_NAME}; --split test runs it"
            )
            return 0
        if args.report_only:  # the plan the record was made with
            ran = record / "plan.json"
            md = write_report(json.loads(ran.read_text()) if ran.is_file() else plan, record, args.report)
        else:
            only = args.only or plan["tasks"]
            outside = [t for t in only if t not in plan["tasks"]]
            if outside:
                raise DSSPError(f"--only {' '.join(outside)}: not in the plan's tasks ({', '.join(plan['tasks'])})")
            md = run_study(plan, args.split, only, args.work, args.report, args.workers, quick=args.quick)
        print(md.read_text())
        return 0

    return run_cli(_main)


if __name__ == "__main__":
    sys.exit(main())

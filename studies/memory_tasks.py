"""The memory-task study under the protocol: DSSP against DP3 and DSSP without history on tap, swap and put2,
on validation seeds and then, once the plan is frozen, on test seeds.

    python -m studies.memory_tasks [--split validation|test] [--tasks T ...] [--workers 2] [--work runs/memory]
                             [--report reports/memory] [--freeze] [--report-only] [--quick]

For each task: collect the expert demonstrations (demonstration seeds 0…); for every model of the plan and
every training seed: train (the same trainer, data and budget), export (parity checked), evaluate in closed loop
through the robot's chain on the split's scenes — the same scenes for every model, so every comparison is
paired. The stages run on :class:`studies.runner.Runner` (side by side, one thread each, resumed after an
interruption). Each finished evaluation is kept in the record (``--report``/record/evals/NAME.json, its
episodes' seeds, outcomes and memory decisions); the report (``memory.md`` and ``memory.json``) is rebuilt
from the record alone (``--report-only``; :func:`write_report`).

The protocol (:mod:`studies.protocol`): ``--split validation`` (seeds 1000…) is where the plan is chosen;
``--freeze`` keeps the plan's hash beside the record; ``--split test`` (seeds 10000…) runs only the frozen
plan. The report gives each model's success with a two-way cluster-bootstrap interval over training seeds and
scenes, the memory decision scored apart from the manipulation (:meth:`dssp_sim.tasks.Task.decision`), and
for every model against DSSP the paired difference with its interval and the exact paired test's p-value
(:mod:`studies.stats`).

DP3 at its own size (the ``dp3`` preset, 262 M parameters) is in the plan as a GPU model: a 2-core CPU does
not train it at this budget, so the study prints its commands instead of running them.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dssp_core.cli_runner import ArgumentParser, run_cli
from dssp_core.errors import DSSPError
from dssp_core.output_guard import write_output_figure
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
    SIM_BATCH,
    collect_stage,
    eval_stage,
    export_stage,
    seeds_of,
    train_argv,
    train_stage,
    training_of,
)

REPORT_NAME = "memory"
PLAN = {
    "tasks": {
        "tap": {"demos": 50, "steps": 3000},
        "swap": {"demos": 150, "steps": 3000},
        "put2": {"demos": 150, "steps": 1500},
    },
    "models": {
        "dssp": {"preset": "sim", "flags": []},
        "dp3_sim": {"preset": "dp3_sim", "flags": []},
        "wo_history": {"preset": "sim", "flags": ["--no-history"]},
    },
    # Table 5's ablations of DSSP, on tap only
    "ablations": {
        "tap": {
            "no_timestep_decoupling": {"preset": "sim", "flags": ["--no-timestep-decoupling"]},
            "no_recent_states": {"preset": "sim", "flags": ["--no-recent-states"]},
            "no_dynamics_loss": {"preset": "sim", "flags": ["--no-dynamics-loss"]},
            "transformer_denoiser": {"preset": "sim", "flags": ["--denoiser-backbone", "transformer"]},
        }
    },
    # trained on a GPU: the study prints their commands
    "gpu_models": {"dp3": {"preset": "dp3", "flags": []}},
    "seeds": [0, 1, 2],
    "episodes": {"validation": 20, "test": 50},
    "export_flags": ["--quantize", "int8"],
}
QUICK_PLAN = {
    "tasks": {"tap": {"demos": 3, "steps": 10}},
    "models": {
        "dssp": {"preset": "sim", "flags": []},
        "dp3_sim": {"preset": "dp3_sim", "flags": ["--set", "model.unet_down_dims=[16,32]"]},
        "wo_history": {"preset": "sim", "flags": ["--no-history"]},
    },
    "ablations": {},
    "gpu_models": {"dp3": {"preset": "dp3", "flags": []}},
    "seeds": [0, 1],
    "episodes": {"validation": 2, "test": 2},
    "export_flags": ["--skip-verify", "--quantize", "none"],
}
LABELS = {
    "dssp": "DSSP (full history)",
    "dp3_sim": "DP3 (sim size, 0.71 M)",
    "dp3": "DP3 (its own size, 262 M)",
    "wo_history": "DSSP w/o history",
    "no_timestep_decoupling": "w/o timestep decoupling",
    "no_recent_states": "w/o recent states",
    "no_dynamics_loss": "w/o dynamics loss",
    "transformer_denoiser": "w/ Transformer denoiser",
}
RECORD_DIR = "record"


@dataclass(frozen=True)
class Naming:
    """How a study of this shape names itself in its reports: its module and its models' labels."""

    command: str = "studies.memory_tasks"
    labels: Mapping[str, str] = field(default_factory=lambda: LABELS)


MEMORY = Naming()


def models_of(plan: dict, task: str) -> dict[str, dict]:
    """The models trained for ``task``: the plan's models, then the task's ablations."""
    return {**plan["models"], **plan["ablations"].get(task, {})}


def eval_name(task: str, model: str, seed: int, split: str) -> str:
    return f"{task}_{model}_s{seed}_{split}"


def stages(plan: dict, split: str, tasks: list[str], record: Path, models: list[str] | None = None) -> list[Stage]:
    """Every stage of ``tasks`` for ``split`` (of ``models`` only, when given); a model whose evaluation is in the
    record needs none."""
    n = plan["episodes"][split]
    first = protocol.split_seeds(split, n)[0]
    out: list[Stage] = []
    for task in tasks:
        spec, data, collected = plan["tasks"][task], f"data/{task}.zarr", (f"collect_{task}",)
        need_data = False
        for name, model in models_of(plan, task).items():
            if models is not None and name not in models:
                continue
            steps, flags = training_of(plan["tasks"][task]["steps"], model, task)
            for seed in seeds_of(plan, model):
                key = f"{task}_{name}_s{seed}"
                result = eval_name(task, name, seed, split)
                if (record / "evals" / f"{result}.json").is_file():
                    continue
                need_data = True
                run, model_dir = f"runs/{key}", f"models/{key}"
                out += [
                    train_stage(key, data, run, model["preset"], steps, seed, *flags, after=collected),
                    export_stage(
                        key, run, model_dir, "--force", "--threads", "1", *plan["export_flags"], after=(f"train_{key}",)
                    ),
                    eval_stage(result, model_dir, task, n, first, after=(f"export_{key}",)),
                ]
        if need_data:
            out.insert(0, collect_stage(task, task, spec["demos"], data))
    return out


def gpu_commands(plan: dict, tasks: list[str]) -> list[str]:
    lines = []
    for name, model in plan["gpu_models"].items():
        for task in tasks:
            steps, flags = training_of(plan["tasks"][task]["steps"], model, task)
            for seed in seeds_of(plan, model):
                data, run = f"data/{task}.zarr", f"runs/{task}_{name}_s{seed}"
                argv = train_argv(data, run, model["preset"], steps, seed, *flags)
                lines.append("dssp-train " + " ".join(argv) + " --device cuda")
    return lines


# ------------------------------------------------------------------------------------------------ report
def grid(
    record: Path, task: str, model: str, seeds: list[int], split: str
) -> tuple[list[list[int]], list[int], list[dict]] | None:
    """(outcomes (R, S), scene seeds, the R evaluations) of one model, or None until all its seeds are recorded."""
    evals = []
    for seed in seeds:
        path = record / "evals" / f"{eval_name(task, model, seed, split)}.json"
        if not path.is_file():
            return None
        evals.append(json.loads(path.read_text()))
    scenes = [e["seed"] for e in evals[0]["episodes"]]
    for r in evals[1:]:
        if [e["seed"] for e in r["episodes"]] != scenes:
            raise DSSPError(
                f"{task}/{model}: the training seeds were evaluated on different scenes; the study pairs them"
            )
    return [[int(e["success"]) for e in r["episodes"]] for r in evals], scenes, evals


def _pct(x: float) -> str:
    return f"{100 * x:.0f}"


def _seeds_text(plan: dict, labels: Mapping[str, str]) -> str:
    """The plan's training seeds, and those of each model that names its own."""
    own = {
        name: model["seeds"]
        for task in plan["tasks"]
        for name, model in models_of(plan, task).items()
        if "seeds" in model and model["seeds"] != plan["seeds"]
    }
    return str(plan["seeds"]) + "".join(f" ({labels.get(n, n)}: {seeds})" for n, seeds in own.items())


def report_lines(
    plan: dict, record: Path, split: str, shown_record: str | None = None, naming: Naming = MEMORY
) -> tuple[list[str], dict]:
    """The report's Markdown lines and its figures, from the record alone (``shown_record``: how the report names the
    record's folder, default its path)."""
    command, labels = naming.command, naming.labels
    figures: dict = {"split": split, "tasks": {}}
    prov_path = record / f"provenance_{split}.json"
    runs = json.loads(prov_path.read_text()) if prov_path.is_file() else []
    runs = [runs] if isinstance(runs, dict) else runs  # one run, written as an object
    if not isinstance(runs, list) or not all(isinstance(r, dict) for r in runs):
        raise DSSPError(f"{prov_path} must hold a list of runs' provenance (objects); write it again with this study")
    n = plan["episodes"][split]
    scene_seeds = protocol.split_seeds(split, n)
    task_steps = ", ".join(f"{task} {spec['steps']}" for task, spec in plan["tasks"].items())
    lines = [
        f"# Memory tasks, {split} split: DSSP against DP3 and DSSP without history",
        "",
        f"Rebuilt from `{shown_record or record}` by `python -m {command} --split {split} --report-only`. "
        f"Scenes: {split} seeds {scene_seeds[0]}–{scene_seeds[-1]} ({n} per model and training seed, the same for every "
        f"model); training seeds {_seeds_text(plan, labels)}; training steps per task "
        f"{task_steps} (at {SIM_BATCH} windows a step; "
        "a model with its own batch takes the same windows in its own steps). "
        "Success: mean over training seeds and scenes, 95 % two-way cluster-bootstrap interval (training seeds × scenes). "
        "Δ vs DSSP: paired difference (same scenes) with its interval. " + FAMILY_NOTE,
    ]
    for prov in runs:
        lines += ["", protocol.describe_run(prov)]
    for other in protocol.trained_elsewhere(record):
        lines += ["", protocol.describe_trained_elsewhere(other, labels)]
    if split == "validation":
        lines += ["", "Validation seeds: the plan is chosen on these, so these figures are not a test result."]
    for task in plan["tasks"]:
        models = models_of(plan, task)
        rows, base = {}, grid(record, task, "dssp", seeds_of(plan, models["dssp"]), split)
        lines += [
            "",
            f"## {task}",
            "",
            "| model | success % (95 % CI) | per training seed | Δ vs DSSP (95 "
            "% CI) | paired test | seed test | memory decision right / reached | failures |",
            "|---|---|---|---|---|---|---|---|",
        ]
        grids = {name: grid(record, task, name, seeds_of(plan, model), split) for name, model in models.items()}
        others = {name: g[0] for name, g in grids.items() if name != "dssp" and g is not None}
        comparisons = {name: compare(g, base[0]) for name, g in others.items()} if base is not None else {}
        holm_family(comparisons.values())
        for name in models:
            g = grids[name]
            if g is None:
                lines.append(f"| {labels.get(name, name)} | pending | | | | | | |")
                continue
            outcomes, _, evals = g
            mean, lo, hi = cluster_bootstrap(outcomes)
            per_seed = ", ".join(f"{sum(o)}/{len(o)}" for o in outcomes)
            reached = sum(e["decisions"]["reached"] for e in evals)
            right = sum(e["decisions"]["correct"] for e in evals)
            reasons: dict[str, int] = {}
            for e in evals:
                for k, v in e["failure_reasons"].items():
                    reasons[k] = reasons.get(k, 0) + v
            fails = ", ".join(f"{k} × {v}" for k, v in sorted(reasons.items())) or "—"
            row = {
                "success": mean,
                "ci": [lo, hi],
                "per_seed": [sum(o) for o in outcomes],
                "episodes": len(outcomes[0]),
                "decision_right": right,
                "decision_reached": reached,
                "failures": reasons,
                "choices": _merge(e["decisions"]["choices"] for e in evals),
            }
            delta = test = seed_test = "—"
            if name in comparisons:
                c = comparisons[name]
                (dlo, dhi), d = c["ci"], c["delta"]
                row.update(
                    delta=d, delta_ci=[dlo, dhi], **{k: c[k] for k in ("p", "p_holm", "p_seeds", "p_seeds_holm")}
                )
                delta = f"{100 * d:+.0f} ({100 * dlo:+.0f} to {100 * dhi:+.0f})"
                test, seed_test = (
                    describe_p(c["p"], holm_p=c["p_holm"]),
                    describe_p(c["p_seeds"], holm_p=c["p_seeds_holm"]),
                )
            rows[name] = row
            decision = f"{right}/{reached}" + (f" ({100 * right / reached:.0f} %)" if reached else "")
            lines.append(
                f"| {labels.get(name, name)} | {_pct(mean)} ({_pct(lo)}–{_pct(hi)}) | {per_seed} | {delta} | {test} | "
                f"{seed_test} | {decision} | {fails} |"
            )
        for name in plan["gpu_models"]:
            lines.append(f"| {labels.get(name, name)} | not run: a GPU model (commands below) | | | | | | |")
        lines += partial_family_note(len(comparisons), len(models) - 1)  # the family: every model against DSSP
        disagree = disagreements(comparisons, labels)
        lines += (
            ["", "Where the paired test and the interval disagree:", "", *[f"- {x}" for x in disagree]]
            if disagree
            else []
        )
        if task == "tap" and rows:
            counts = sorted({c for r in rows.values() for c in r["choices"]}, key=lambda c: int(c.split()[0]))
            lines += [
                "",
                "tap's memory decision: presses counted at the end of each episode (3 is right), all training seeds:",
                "",
                "| model | " + " | ".join(counts) + " |",
                "|---|" + "---:|" * len(counts),
            ]
            for name, r in rows.items():
                lines.append(
                    f"| {labels.get(name, name)} | " + " | ".join(str(r["choices"].get(c, 0)) for c in counts) + " |"
                )
        figures["tasks"][task] = rows
    lines += ["", "DP3 at its own size (the `dp3` preset) trains on a GPU; its commands for this plan:", "", "```"]
    lines += gpu_commands(plan, list(plan["tasks"])) + ["```", ""]
    return lines, figures


def _merge(dicts) -> dict:
    out: dict = {}
    for d in dicts:
        for k, v in d.items():
            out[k] = out.get(k, 0) + v
    return out


def write_report(
    plan: dict, record: Path, report: Path, split: str, shown_record: str | None = None, naming: Naming = MEMORY
) -> Path:
    """``memory_SPLIT.md`` (tables), ``.json`` (every figure) and ``.png`` (the plot), from the record alone
    (:func:`report_lines`)."""
    lines, figures = report_lines(plan, record, split, shown_record, naming)
    name = f"{REPORT_NAME}_{split}"
    lines += [f"![success and memory decision per model]({name}.png)", ""]
    md = write_md_and_json(report, name, lines, {"plan": plan, **figures})
    plot(figures, md.with_suffix(".png"), naming.labels)
    return md


def plot(figures: dict, path: Path, labels: Mapping[str, str] = LABELS) -> None:
    """Per task: each model's success with its cluster-bootstrap interval, and its memory decision's accuracy among
    the episodes that reached it."""
    import matplotlib  # here, not at the top: the study's command starts without it

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # here too, after matplotlib.use("Agg")

    tasks = [t for t, rows in figures["tasks"].items() if rows]
    fig, axes = plt.subplots(1, max(len(tasks), 1), figsize=(5.5 * max(len(tasks), 1), 4), squeeze=False)
    for ax, task in zip(axes[0], tasks):
        rows = figures["tasks"][task]
        names = list(rows)
        x = np.arange(len(names))
        success = [100 * rows[n]["success"] for n in names]
        err = [
            [100 * (rows[n]["success"] - rows[n]["ci"][0]) for n in names],
            [100 * (rows[n]["ci"][1] - rows[n]["success"]) for n in names],
        ]
        decision = [
            100 * rows[n]["decision_right"] / rows[n]["decision_reached"] if rows[n]["decision_reached"] else 0
            for n in names
        ]
        ax.bar(x - 0.2, success, 0.4, yerr=err, capsize=3, label="success (95 % cluster bootstrap)")
        ax.bar(x + 0.2, decision, 0.4, label="memory decision right (of reached)")
        ax.set(xticks=x, ylim=(0, 105), ylabel="%", title=f"{task} ({figures['split']} split)")
        ax.set_xticklabels([labels.get(n, n) for n in names], rotation=20, ha="right", fontsize=7)
        ax.legend(fontsize=7)
    fig.tight_layout()
    write_output_figure(path, fig, force=True, flag="--report")


def run_study(
    plan: dict,
    split: str,
    tasks: list[str],
    work: Path,
    report: Path,
    workers: int,
    models: list[str] | None = None,
    quick: bool = False,
    naming: Naming = MEMORY,
) -> Path:
    """Run ``plan``'s stages of ``tasks`` on ``split`` not in the record yet, keep their evaluations and write the report
    (named by ``naming``)."""
    record = report / RECORD_DIR
    if split == "test":
        protocol.check_frozen(record, plan)
    stage_list = stages(plan, split, tasks, record, models)
    protocol.note_provenance(record, plan, split, tasks, allow_changes=quick)
    run_and_keep(work, record, stage_list, workers, f"{', '.join(tasks)} on the {split} split")
    return write_report(plan, record, report, split, naming=naming)


def main(
    argv: list[str] | None = None,
    plan_of: Callable[[bool], dict] = lambda quick: QUICK_PLAN if quick else PLAN,
    naming: Naming = MEMORY,
    doc: str = __doc__,
) -> int:
    """The study's command on the plan ``plan_of(--quick)`` (another study of this shape passes its own plan, naming
    and docstring; its defaults: ``runs/NAME`` and ``reports/NAME``)."""
    name = naming.command.removeprefix("studies.").removesuffix("_tasks")
    p = ArgumentParser(prog=f"python -m {naming.command}", description=doc.split("\n\n")[0])
    p.add_argument("--split", choices=list(protocol.SPLITS), default="validation")
    p.add_argument("--tasks", nargs="+", metavar="TASK", help="default: every task of the plan")
    p.add_argument("--models", nargs="+", metavar="MODEL", help="only these models (default: every model of the plan)")
    p.add_argument("--workers", type=int, default=2, help="stages side by side, one thread each (default 2)")
    p.add_argument("--work", type=Path, default=Path(f"runs/{name}"), help="datasets, runs, models, evaluations, logs")
    p.add_argument("--report", type=Path, default=Path(f"reports/{name}"), help="the report and its record")
    p.add_argument(
        "--freeze", action="store_true", help="freeze the plan for the test split (after choosing on validation)"
    )
    p.add_argument("--reason", help="with --freeze, again on a changed task definition: why (kept in the record)")
    p.add_argument("--report-only", action="store_true", help="run nothing: rebuild the report from the record")
    p.add_argument("--quick", action="store_true", help="a tiny plan (tests)")
    args = p.parse_args(argv)

    def _main() -> int:
        plan = plan_of(args.quick)
        tasks = args.tasks or list(plan["tasks"])
        unknown = [t for t in tasks if t not in plan["tasks"]]
        if unknown:
            p.error(f"--tasks: {', '.join(unknown)} not in the plan ({', '.join(plan['tasks'])})")
        known = {m for t in tasks for m in models_of(plan, t)}
        if args.models and set(args.models) - known:
            p.error(
                f"--models: {', '.join(sorted(set(args.models) - known))} not in the plan's models for these tasks "
                f"({', '.join(sorted(known))})"
            )
        record = args.report / RECORD_DIR
        if args.freeze:
            tested = [t for t in plan["tasks"] if any((record / "evals").glob(f"{t}_*_test.json"))]
            print(
                f"plan {protocol.freeze_plan(record, plan, tested, reason=args.reason)} frozen in {record / protocol.FROZEN_NAME} on task "
                f"definition {protocol.task_definition_hash()}; --split test runs it"
            )
            return 0
        if args.report_only:
            md = write_report(plan, record, args.report, args.split, naming=naming)
        else:
            md = run_study(
                plan, args.split, tasks, args.work, args.report, args.workers, args.models, args.quick, naming
            )
        print(md.read_text())
        return 0

    return run_cli(_main)


if __name__ == "__main__":
    sys.exit(main())

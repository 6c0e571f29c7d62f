"""The first simulation study: DSSP against the reactive baseline on the memory tasks, the ablations, and the
robustness test. Its figures are validation figures (its scenes are the seeds its settings were chosen on); for
headline claims it is superseded by the memory-task study, studies.memory_tasks.

    python -m studies.sim_study [--work runs/sim_experiment] [--report reports/sim] [--tasks T ...] [--seeds S ...]
                                [--workers 2] [--quick] [--force] [--report-only]

For each task: collect expert demonstrations; train DSSP and the reactive baseline (the same code with
``--no-history``: no history encoder, the denoiser sees only the N most recent state tokens — the
"short window"), same data, preset, budget and seed; export both; evaluate each in closed loop through
the robot's chain on the same unseen episode seeds. Then the ablations (paper Table 5's columns and Table 3's
history window) on the ablation tasks, each a variant of DSSP trained and evaluated the same way; and the
paper's Table 4 test: Gaussian noise on the N most recent state tokens at inference, DSSP (full history)
against the T_h = 10 window ("w/o full history") and the reactive baseline, σ also as a multiple of the
tokens' own RMS (measured in each evaluation). The Transformer history encoder of Table 3 is not in the
study: it does not export (over the full history its state grows).

The stages (:func:`stages`) run on :class:`studies.runner.Runner` in ``--work`` (``--workers`` side by side, one
thread each; an interrupted study resumes: a finished stage is not run again, a training stopped halfway
continues from its checkpoint (``--resume``), a collection stopped halfway is collected again):

- ``collect_TASK`` (``dssp-sim collect``): the task's expert demonstrations, ``data/TASK.zarr``;
- ``train_TASK_VARIANT_sSEED`` (``dssp-train``): one model, ``runs/TASK_VARIANT_sSEED``;
- ``export_TASK_VARIANT_sSEED`` (``python -m export.to_onnx``): its graphs, ``models/TASK_VARIANT_sSEED``, the
  parity checked (the quick plan skips the check and the quantized graphs: the export tests prove both);
- ``eval_NAME`` (``dssp-sim eval``): its closed-loop evaluation, ``evals/NAME.json`` (NAME: the model's, with
  ``_noiseσ`` for the robustness test's noise levels).

``--tasks`` and ``--seeds`` run part of the study (no report); a last run without them writes the report. Every
finished evaluation and stage time is kept in the report's record (``--report``/record: evals/NAME.json,
:func:`studies.evaluations.compact`; seconds/STAGE.seconds), so a machine without the work folder resumes from the
record: a model whose evaluations are all recorded needs no stage, and ``--report-only`` writes the report from
the record alone, the cells not yet run marked as pending. The report — ``REPORT_NAME.md`` (tables), ``.png``
(plot) and ``.json`` (every figure) — is written to ``--report``. The plan is data (:data:`PLAN`, :data:`QUICK_PLAN`).

Outputs (:mod:`dssp_core.output_guard`): ``--work`` must be new, empty or a work folder of this study
(marked ``.dssp-output.json``), which is continued; anything else is refused before any stage runs. The
report's three files are written beside whatever else ``--report`` holds; existing ones are replaced only
with ``--force``, checked before the study starts.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from dssp_core.cli_runner import ArgumentParser, run_cli
from dssp_core.errors import DSSPError
from dssp_core.output_guard import OutputKind, check_output_files, claim_dir, write_output_figure, write_output_text
from dssp_sim.evaluate import wilson_interval
from studies.evaluations import run_and_keep
from studies.runner import Runner, Stage
from studies.study_stages import collect_stage, eval_stage, export_stage, train_stage

REPORT_NAME = "sim_memory_tasks"
PLAN = {
    "preset": "sim",
    # Training steps per task: each step encodes a whole demonstration (the full history), so the longer
    # swap/put2 episodes (about 150 and 120 steps against tap's 60) cost about 2.5x more per step. At 1500
    # steps DSSP lost the first object in 9 of 20 swap episodes: swap gets tap's 3000.
    "steps": {"tap": 3000, "swap": 3000, "put2": 1500},
    "demos": {"tap": 50, "swap": 150, "put2": 150},
    "seeds": {"tap": [0, 1, 2], "swap": [0], "put2": [0]},
    "variants": {"dssp": [], "reactive": ["--no-history"]},
    # Table 5's columns beside "full" (dssp) and "w/o history" (reactive), and Table 3's T_h = 10 window: trained
    # for the ablation tasks and seeds only.
    "ablations": {  # in the order they train: the window first (Table 4 needs it)
        "window10": ["--history-window", "10"],
        "no_timestep_decoupling": ["--no-timestep-decoupling"],
        "no_recent_states": ["--no-recent-states"],
        "no_dynamics_loss": ["--no-dynamics-loss"],
        "transformer_denoiser": ["--denoiser-backbone", "transformer"],
    },
    "ablation_seeds": {"tap": [0, 1, 2], "put2": [0]},
    "eval_episodes": 20,
    "eval_seed": 1000,
    # σ in the tokens' units (each evaluation measures their RMS per element, reported beside σ)
    "robustness": {
        "task": "tap",
        "seed": 0,
        "variants": ["dssp", "window10", "reactive"],
        "sigmas": [0.05, 0.10, 0.15, 0.3, 0.5, 1.0, 2.0],
    },
    "export_flags": [],  # parity is checked on every export of the study
}
QUICK_PLAN = {
    **PLAN,
    "steps": {"tap": 20},
    "demos": {"tap": 3},
    "seeds": {"tap": [0]},
    "eval_episodes": 1,
    "export_flags": [
        "--skip-verify",
        "--quantize",
        "none",
    ],  # the export tests prove parity and quantize; this checks the plumbing
    "ablations": {"window3": ["--history-window", "3"]},
    "ablation_seeds": {"tap": [0]},
    "robustness": {"task": "tap", "seed": 0, "variants": ["dssp", "window3", "reactive"], "sigmas": [0.1]},
}
WORK_ENTRIES = ("data", "runs", "models", "evals", "logs", "done")
"""What a study's work folder holds (the runner's ``logs/`` and ``done/``; older work folders are recognised by
``logs/``)."""
WORK_DIR = OutputKind(
    "a study work directory",
    "python -m studies.sim_study",
    entries=WORK_ENTRIES,
    signature=lambda p: (p / "logs").is_dir(),
)
"""``--work``: data/, runs/, models/, evals/, logs/, done/ (continued by the next run)."""
REPORT_SUFFIXES = (".md", ".json", ".png")
RECORD_DIR = "record"
"""Under ``--report``: evals/NAME.json and seconds/STAGE.seconds of every finished stage (see the module's docstring)."""
VARIANT_LABELS = {
    "dssp": "DSSP (full history)",
    "reactive": "reactive baseline (short window: N recent states)",
    "no_timestep_decoupling": "w/o timestep decoupling",
    "no_recent_states": "w/o recent states",
    "no_dynamics_loss": "w/o dynamics loss",
    "transformer_denoiser": "w/ Transformer denoiser",
    "window10": "w/o full history (window T_h = 10)",
    "window3": "window T_h = 3",
}
# Table 5's rows: the main variants under the paper's names, then the ablations.
TABLE5_LABELS = {"dssp": "full (DSSP)", "reactive": "w/o history (reactive baseline)"}


def recorded(record: Path | None, name: str) -> dict | None:
    """The evaluation ``name`` kept in ``record``, or None."""
    path = record / "evals" / f"{name}.json" if record is not None else None
    return json.loads(path.read_text()) if path is not None and path.is_file() else None


def stage_seconds(work: Path, record: Path | None = None) -> float:
    """Compute time of every stage of the study so far, resumed and parallel runs included: the stage times kept in
    ``record`` (from every machine that ran part of it) and the done stages of ``work``, each stage counted once."""
    folder = record / "seconds" if record is not None else None
    seconds = (
        {f.stem: float(f.read_text()) for f in sorted(folder.glob("*.seconds"))} if folder and folder.is_dir() else {}
    )
    return sum({**seconds, **Runner(work).seconds()}.values())


def eval_name(name: str, sigma: float) -> str:
    """An evaluation's name: the model's, with the noise level when there is noise."""
    return f"{name}_noise{sigma:g}" if sigma else name


def model_runs(plan: dict, task: str) -> list[tuple[int, str, list[str], list[float]]]:
    """(seed, variant, training flags, noise levels it is evaluated at) of every model of ``task``, seed by seed: the
    main variants on the task's seeds, the ablations on its ablation seeds; σ = 0 for all, and the robustness test's
    σs for its models."""
    rob = plan["robustness"]
    seeds = dict.fromkeys([*plan["seeds"][task], *plan["ablation_seeds"].get(task, [])])
    return [
        (
            seed,
            variant,
            flags,
            [
                0.0,
                *(rob["sigmas"] if (task, seed) == (rob["task"], rob["seed"]) and variant in rob["variants"] else []),
            ],
        )
        for seed in seeds
        for variant, flags in [
            *(plan["variants"].items() if seed in plan["seeds"][task] else []),
            *(plan["ablations"].items() if seed in plan["ablation_seeds"].get(task, []) else []),
        ]
    ]


def models(
    plan: dict, tasks: list[str], seeds: list[int] | None = None
) -> Iterator[tuple[str, int, str, list[str], list[float]]]:
    """(task, seed, variant, training flags, noise levels) of every model of ``tasks`` (of training ``seeds`` only,
    when given)."""
    for task in tasks:
        for seed, variant, flags, sigmas in model_runs(plan, task):
            if seeds is None or seed in seeds:
                yield task, seed, variant, flags, sigmas


def stages(plan: dict, tasks: list[str], record: Path, seeds: list[int] | None = None) -> list[Stage]:
    """Every stage of ``tasks`` (the models of training ``seeds`` only, when given; module docstring); a model whose
    evaluations are all in ``record`` needs none, and of the others only the evaluations not recorded run."""
    n, first = plan["eval_episodes"], plan["eval_seed"]
    out: list[Stage] = []
    for task in tasks:
        data, collected = f"data/{task}.zarr", (f"collect_{task}",)
        task_stages: list[Stage] = []
        for _, seed, variant, flags, sigmas in models(plan, [task], seeds):
            name = f"{task}_{variant}_s{seed}"
            pending = [sigma for sigma in sigmas if recorded(record, eval_name(name, sigma)) is None]
            if not pending:
                continue
            run, model, ready = f"runs/{name}", f"models/{name}", (f"export_{name}",)
            task_stages += [
                train_stage(name, data, run, plan["preset"], plan["steps"][task], seed, *flags, after=collected),
                export_stage(
                    name, run, model, "--force", "--threads", "1", *plan["export_flags"], after=(f"train_{name}",)
                ),
                *(
                    eval_stage(eval_name(name, sigma), model, task, n, first, "--noise", str(sigma), after=ready)
                    for sigma in pending
                ),
            ]
        if task_stages:
            out += [collect_stage(task, task, plan["demos"][task], data), *task_stages]
    return out


def run_study(
    plan: dict, tasks: list[str], work: Path, record: Path, workers: int, seeds: list[int] | None = None
) -> None:
    """Claim ``work`` for the study and run (or resume) the stages of ``tasks`` and training ``seeds`` (default: all),
    keeping every finished evaluation and stage time in ``record``."""
    claim_dir(work, kind=WORK_DIR, flag="--work", resume=True)
    for task, seed, variant, _, sigmas in models(plan, tasks, seeds):
        for sigma in sigmas:
            name = eval_name(f"{task}_{variant}_s{seed}", sigma)
            if recorded(record, name) is not None:
                print(f"  eval {name}: recorded")
    run_and_keep(work, record, stages(plan, tasks, record, seeds), workers, ", ".join(tasks), seconds=True)


def recorded_results(plan: dict, record: Path) -> tuple[dict, list[str]]:
    """The study's results as far as ``record`` holds them, and the names of the evaluations it lacks."""
    results: dict = {"plan": plan, "evals": {}, "robustness": {}}
    pending = []
    for task in plan["demos"]:
        for seed, variant, _, sigmas in model_runs(plan, task):
            for sigma in sigmas:
                name = eval_name(f"{task}_{variant}_s{seed}", sigma)
                r = recorded(record, name)
                if r is None:
                    pending.append(name)
                else:
                    results["robustness" if sigma else "evals"][name] = r
    return results, pending


# ------------------------------------------------------------------------------------------------ report
def pct(k: int, n: int) -> str:
    lo, hi = wilson_interval(k, n)
    return f"{100 * k / max(n, 1):.0f} % ({k}/{n}; {100 * lo:.0f}–{100 * hi:.0f})"


def summarise(results: dict) -> dict:
    """Per task and variant: successes and episodes pooled over seeds, per seed too, and failure reasons."""
    table: dict = {}
    for name, r in results["evals"].items():
        task, variant, seed = name.rsplit("_", 2)
        row = table.setdefault(task, {}).setdefault(variant, {"k": 0, "n": 0, "per_seed": {}, "reasons": {}})
        row["k"] += r["successes"]
        row["n"] += r["n"]
        row["per_seed"][seed] = f"{r['successes']}/{r['n']}"
        for reason, count in r["failure_reasons"].items():
            row["reasons"][reason] = row["reasons"].get(reason, 0) + count
    return table


def report_files(report_dir: Path) -> list[Path]:
    """The report's files in ``report_dir``: REPORT_NAME.md, .json and .png."""
    return [report_dir / f"{REPORT_NAME}{suffix}" for suffix in REPORT_SUFFIXES]


def _rob_result(results: dict, rob: dict, variant: str, sigma: float) -> dict | None:
    """One cell of the robustness test (None while pending)."""
    name = eval_name(f"{rob['task']}_{variant}_s{rob['seed']}", sigma)
    return results["robustness" if sigma else "evals"].get(name)


def _z_rms(results: dict, rob: dict) -> float | None:
    """The recent state tokens' RMS per element, as DSSP's noise-free evaluation measured it (None in older results)."""
    return (_rob_result(results, rob, rob["variants"][0], 0.0) or {}).get("z_rms")


def write_report(results: dict, report_dir: Path, seconds: float, force: bool = False, pending: list[str] = ()) -> Path:
    """``seconds``: the compute time of all stages (:func:`stage_seconds`); ``force``: replace existing report files;
    ``pending``: the evaluations not run yet, listed and marked "pending"."""
    check_output_files(report_files(report_dir), force=force, flag="--report")
    table = summarise(results)
    plan = results["plan"]
    lines = [
        "# Memory tasks in simulation: DSSP against the reactive baseline, the ablations, robustness",
        "",
        f"Produced by `python -m studies.sim_study` ({seconds / 60:.0f} min of stage time on this 2-core machine, "
        "summed over resumed and parallel runs). "
        f"Preset `{plan['preset']}`, training steps per task {plan['steps']} (the same for every model), "
        f"{plan['eval_episodes']} evaluation episodes per model on unseen seeds "
        f"({plan['eval_seed']}…), closed loop through the robot's chain (simulated depth → RealSense software device → "
        "point-cloud pipeline → ONNX runtime → safety → Piper CAN frames → MuJoCo arm). Success rates with 95 % Wilson "
        "intervals, pooled over training seeds.",
        "",
        "| task | model | success (k/n; 95 % CI) | per training seed | failures |",
        "|---|---|---|---|---|",
    ]
    for task, variants in table.items():
        for variant, row in variants.items():
            if variant not in plan["variants"]:
                continue
            seeds = ", ".join(f"{s}: {v}" for s, v in sorted(row["per_seed"].items()))
            reasons = ", ".join(f"{k} × {v}" for k, v in sorted(row["reasons"].items())) or "—"
            lines.append(
                f"| {task} | {VARIANT_LABELS.get(variant, variant)} | {pct(row['k'], row['n'])} | {seeds} | {reasons} |"
            )
    ablation_tasks = [t for t in plan["ablation_seeds"] if t in table and any(v in table[t] for v in plan["ablations"])]
    if ablation_tasks:
        seeds = ", ".join(f"`{t}` seeds {plan['ablation_seeds'][t]}" for t in ablation_tasks)
        lines += [
            "",
            f"Ablations (paper Table 5, and Table 3's window): each row one change to DSSP, trained and evaluated "
            f"as above ({seeds}; rows pooled over those seeds only). The Transformer history encoder of Table 3 is "
            "not here: it does not export (over the full history its state grows).",
            "",
            "| model | " + " | ".join(f"`{t}`" for t in ablation_tasks) + " |",
            "|---|" + "---|" * len(ablation_tasks),
        ]
        for variant in [*plan["variants"], *plan["ablations"]]:
            cells = []
            for task in ablation_tasks:
                names = [f"{task}_{variant}_s{seed}" for seed in plan["ablation_seeds"][task]]
                rs = [results["evals"][n] for n in names if n in results["evals"]]
                cells.append(
                    pct(sum(r["successes"] for r in rs), sum(r["n"] for r in rs))
                    + ("" if len(rs) == len(names) else f" (seeds so far: {len(rs)} of {len(names)})")
                    if rs
                    else "pending"
                )
            lines.append(
                f"| {TABLE5_LABELS.get(variant, VARIANT_LABELS.get(variant, variant))} | " + " | ".join(cells) + " |"
            )
    if results["robustness"]:
        rob = plan["robustness"]
        rms = _z_rms(results, rob)
        lines += [
            "",
            f"Robustness (paper Table 4): Gaussian noise σ on the N most recent state tokens at inference, "
            f"task `{rob['task']}`, training seed {rob['seed']}. σ is in the tokens' units"
            + (
                f"; their RMS per element is {rms:.2f} (DSSP, noise-free), so σ / RMS is in the second column."
                if rms
                else "."
            ),
            "",
            "| σ | σ / RMS | " + " | ".join(VARIANT_LABELS.get(v, v) for v in rob["variants"]) + " |",
            "|---:|---:|" + "---|" * len(rob["variants"]),
        ]
        for sigma in [0.0, *rob["sigmas"]]:
            cells = [
                pct(r["successes"], r["n"]) if r else "pending"
                for r in (_rob_result(results, rob, v, sigma) for v in rob["variants"])
            ]
            lines.append(f"| {sigma:g} | {sigma / rms:.2f} | " if rms else f"| {sigma:g} | — | ")
            lines[-1] += " | ".join(cells) + " |"
    if pending:
        lines += [
            "",
            f"**Partial report**: {len(pending)} evaluation(s) of the plan are pending (not run yet): "
            + ", ".join(f"`{n}`" for n in pending)
            + ". Rows pool the seeds run so far.",
        ]
    lines += ["", f"![success rates]({REPORT_NAME}.png)", ""]
    md, js, png = report_files(report_dir)
    write_output_text(md, "\n".join(lines), force=force, flag="--report")
    write_output_text(
        js,
        json.dumps({"summary": table, **results, "pending": list(pending)}, indent=2) + "\n",
        force=force,
        flag="--report",
    )
    _plot(results, table, png, force)
    return md


def _bars(ax, groups: list[str], series: list[tuple[str, list[tuple[int, int]]]], title: str) -> None:
    """Grouped bars of success % with Wilson intervals: ``series`` [(label, [(k, n) per group])]."""
    width = 0.8 / max(len(series), 1)
    for i, (label, counts) in enumerate(series):
        rates, errs = [], [[], []]
        for k, n in counts:
            p = k / max(n, 1)
            lo, hi = wilson_interval(k, n)
            rates.append(100 * p)
            errs[0].append(100 * (p - lo))
            errs[1].append(100 * (hi - p))
        ax.bar(
            np.arange(len(groups)) + (i - (len(series) - 1) / 2) * width,
            rates,
            width,
            yerr=errs,
            capsize=3,
            label=label,
        )
    ax.set(xticks=np.arange(len(groups)), xticklabels=groups, ylabel="success %", ylim=(0, 105), title=title)
    ax.legend(fontsize=7)


def _plot(results: dict, table: dict, path: Path, force: bool = False) -> None:
    import matplotlib  # here, not at the top: the study's command starts without it

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # here too, after matplotlib.use("Agg")

    plan = results["plan"]
    tasks = list(table)
    ablation_tasks = [t for t in plan["ablation_seeds"] if t in table and any(v in table[t] for v in plan["ablations"])]
    panels = 1 + bool(ablation_tasks) + bool(results["robustness"])
    fig, axes = plt.subplots(1, panels, figsize=(5.5 * panels, 4), squeeze=False)
    axes = list(axes[0])
    counts = lambda task, v: (table[task].get(v, {"k": 0})["k"], table[task].get(v, {"n": 0})["n"])  # noqa: E731
    _bars(
        axes.pop(0),
        tasks,
        [(VARIANT_LABELS.get(v, v), [counts(t, v) for t in tasks]) for v in plan["variants"]],
        "Closed-loop success (95 % Wilson)",
    )
    if ablation_tasks:
        series = []
        for v in [*plan["variants"], *plan["ablations"]]:
            cells = []
            for t in ablation_tasks:
                rs = [results["evals"].get(f"{t}_{v}_s{seed}") for seed in plan["ablation_seeds"][t]]
                rs = [r for r in rs if r]
                cells.append((sum(r["successes"] for r in rs), sum(r["n"] for r in rs)))
            series.append((TABLE5_LABELS.get(v, VARIANT_LABELS.get(v, v)), cells))
        _bars(axes.pop(0), ablation_tasks, series, "Ablations (Table 5)")
    if results["robustness"]:
        ax = axes.pop(0)
        rob = plan["robustness"]
        rms = _z_rms(results, rob) or 1.0
        sigmas = [0.0, *rob["sigmas"]]
        for variant in rob["variants"]:
            done = [(s, r) for s in sigmas if (r := _rob_result(results, rob, variant, s))]
            ax.plot(
                [s / rms for s, _ in done],
                [100 * r["successes"] / max(r["n"], 1) for _, r in done],
                "o-",
                label=VARIANT_LABELS.get(variant, variant),
            )
        ax.set(
            xlabel="σ / RMS of the recent state tokens",
            ylabel="success %",
            ylim=(0, 105),
            title=f"Robustness ({rob['task']})",
        )
        ax.legend(fontsize=7)
    fig.tight_layout()
    write_output_figure(path, fig, force=force, flag="--report")


def main(argv: list[str] | None = None) -> int:
    p = ArgumentParser(prog="python -m studies.sim_study", description=__doc__.split("\n\n")[0])
    p.add_argument(
        "--work", type=Path, default=Path("runs/sim_experiment"), help="datasets, runs, models, evaluations, logs"
    )
    p.add_argument("--report", type=Path, default=Path("reports/sim"), help="where the report and its record go")
    p.add_argument("--quick", action="store_true", help="a tiny plan (tests): 3 demos, 20 steps, 1 episode")
    p.add_argument("--workers", type=int, default=2, help="stages side by side, one thread each (default 2)")
    p.add_argument(
        "--tasks", nargs="+", metavar="TASK", help="run only these tasks' stages (default: all, then the report)"
    )
    p.add_argument(
        "--seeds",
        nargs="+",
        type=int,
        metavar="SEED",
        help="run only the models of these training seeds "
        "(with --tasks: split one task's models across processes; no report)",
    )
    p.add_argument("--force", action="store_true", help="replace the report's files if they exist")
    p.add_argument(
        "--report-only",
        action="store_true",
        help="run no stage: write the report from the record "
        f"(--report/{RECORD_DIR}), the evaluations not run yet listed as pending",
    )
    args = p.parse_args(argv)
    plan = QUICK_PLAN if args.quick else PLAN
    unknown = [t for t in args.tasks or [] if t not in plan["demos"]]
    if unknown:
        p.error(f"--tasks: {', '.join(unknown)} not in the plan ({', '.join(plan['demos'])})")
    known = {seed for t in plan["demos"] for seed in [*plan["seeds"][t], *plan["ablation_seeds"].get(t, [])]}
    if args.seeds is not None and set(args.seeds) - known:
        p.error(f"--seeds {sorted(set(args.seeds) - known)}: the plan trains seeds {sorted(known)}")
    if args.workers < 1:
        p.error(f"--workers must be at least 1, got {args.workers}")
    partial = bool(args.tasks) and set(args.tasks) != set(plan["demos"]) or args.seeds is not None
    if args.report_only and partial:
        p.error("--report-only writes the whole report from the record; drop --tasks and --seeds")
    record = args.report / RECORD_DIR

    def _main() -> int:
        if not partial:  # before any stage: a report that may not be replaced stops the study now
            check_output_files(report_files(args.report), force=args.force, flag="--report")
        if not args.report_only:
            run_study(plan, args.tasks or list(plan["demos"]), args.work, record, args.workers, args.seeds)
            if partial:
                print(
                    f"stages of {args.tasks or 'every task'}{f' seeds {args.seeds}' if args.seeds else ''} done (kept in "
                    f"{record}); run without --tasks and --seeds for the report"
                )
                return 0
        results, pending = recorded_results(plan, record)
        if not results["evals"]:
            raise DSSPError(f"{record} holds no evaluation of this plan; run the study first (without --report-only)")
        md = write_report(results, args.report, stage_seconds(args.work, record), force=args.force, pending=pending)
        print(md.read_text())
        return 0

    return run_cli(_main)


if __name__ == "__main__":
    sys.exit(main())

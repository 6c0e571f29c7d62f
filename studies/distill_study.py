"""The distillation study: a chunk in one or two denoising steps, against the 10-step teacher.

    python -m studies.distill_study [--work runs/distill_study] [--report reports/distill] [--tasks T ...]
                                    [--teachers runs/sim_experiment] [--workers 2] [--quick] [--force] [--report-only]

For each task: collect demonstrations and train the teacher as the simulation study does (preset ``sim``,
its steps and demonstrations, seed 0) — or take that study's own run (``--teachers``); export it at K = 10 (its own
sampler) and at K = 1 and 2 trailing steps without distillation (``--timestep-spacing trailing``: the first step at
the noise level); distil it (``dssp-distill``) into K = 1 and K = 2 students — with both objectives on the plan's
method tasks, with the plan's method elsewhere — and export them; evaluate every cell in closed loop on the same
unseen episodes. Then the chunk's cost where it matters, on the ``robotwin`` preset: one model of that size (its
latency does not depend on the weights) exported at K = 10, 2 and 1 and timed by ``dssp-profile`` (2 threads, the
runtime's default graphs).

The stages (:func:`stages`) run on :class:`studies.runner.Runner` in ``--work`` (``--workers`` side by side, one
thread each; an interrupted study resumes where it stopped):

- ``collect_TASK`` (``dssp-sim collect``) and ``train_TASK_teacher`` (``dssp-train``): the teacher, unless
  ``--teachers`` names a simulation study's work folder whose seed-0 DSSP run is taken instead;
- ``distill_CELL`` (``dssp-distill``): a student, ``runs/CELL`` (CELL: ``TASK_METHOD_kK``);
- ``export_CELL`` (``python -m export.to_onnx``): the teacher at K = 10, the teacher at K trailing steps
  (``TASK_ddim_kK``) or a student, ``models/CELL``;
- ``eval_CELL`` (``dssp-sim eval``): its closed-loop evaluation, ``evals/CELL.json``;
- ``latency_data`` (``dssp-synth``), ``latency_train`` (``dssp-train``, one step), ``latency_export_kK`` and
  ``latency_profile_kK`` (``dssp-profile``, ``evals/latency_kK.json``): the chunk's cost on the latency preset;
  the profiles run one at a time after every other stage, so that nothing shares their cores.

``--tasks`` runs part of the study (``latency`` is the chunk's cost; no report); a last run without it writes the
report — ``REPORT_NAME.md``, ``.png``, ``.json`` — to ``--report``. Every finished evaluation and profile and every
stage time is kept in the report's record (``--report``/record, as :mod:`studies.sim_study` keeps them), so a
machine without the work folder runs no stage for a cell already recorded, and ``--report-only`` writes the report
from the record alone.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from dssp_core.cli_runner import ArgumentParser, run_cli
from dssp_core.errors import DSSPError
from dssp_core.output_guard import OutputKind, check_output_files, claim_dir, write_output_figure, write_output_text
from dssp_deploy import profile
from dssp_sim.evaluate import wilson_interval
from dssp_train.cli import distill, synth, train
from studies.evaluations import run_and_keep
from studies.runner import Stage
from studies.sim_study import PLAN as MEMORY_PLAN
from studies.sim_study import RECORD_DIR, WORK_ENTRIES, pct, recorded, stage_seconds
from studies.study_stages import collect_stage, eval_stage, export_stage, train_stage

REPORT_NAME = "distill"
TASKS = ("tap", "put2", "swap")
PLAN = {
    "preset": MEMORY_PLAN["preset"],
    "steps": {task: MEMORY_PLAN["steps"][task] for task in TASKS},
    "demos": {task: MEMORY_PLAN["demos"][task] for task in TASKS},
    "seed": 0,
    "student_steps": [1, 2],
    "distill_steps": {"tap": 1000, "put2": 500, "swap": 1000},  # a third of the teacher's
    "methods": ["consistency", "trajectory"],  # both on the method tasks, the chosen one elsewhere
    "method_tasks": ["tap"],
    "method": "trajectory",
    "eval_episodes": MEMORY_PLAN["eval_episodes"],
    "eval_seed": MEMORY_PLAN["eval_seed"],
    "threads": 1,
    "latency": {"preset": "robotwin", "points": 1024, "threads": 2, "denoise_steps": [10, 2, 1], "profile_flags": []},
    "export_flags": [],  # parity is checked on every export of the study
}
QUICK_PLAN = {
    **PLAN,
    "steps": {"tap": 20},
    "demos": {"tap": 3},
    "distill_steps": {"tap": 4},
    "student_steps": [1],
    "method_tasks": [],
    "eval_episodes": 1,
    "export_flags": ["--skip-verify", "--quantize", "none"],
    "latency": {"preset": "tiny", "points": 64, "threads": 1, "denoise_steps": [10, 1], "profile_flags": ["--quick"]},
}
LATENCY = "latency"
"""The part of the study ``--tasks`` names beside the plan's tasks: the chunk's cost on the latency preset."""
WORK_DIR = OutputKind(
    "a distillation-study work directory",
    "python -m studies.distill_study",
    entries=WORK_ENTRIES,
    signature=lambda p: (p / "logs").is_dir(),
)
REPORT_SUFFIXES = (".md", ".json", ".png")


def cells(task: str, plan: dict) -> list[tuple[str, str, int]]:
    """(cell name, kind, K) of a task: the teacher, undistilled DDIM at each student K, each method's students."""
    methods = plan["methods"] if task in plan["method_tasks"] else [plan["method"]]
    out = [(f"{task}_teacher_k10", "teacher", 10)]
    out += [(f"{task}_ddim_k{k}", "ddim", k) for k in plan["student_steps"]]
    out += [(f"{task}_{m}_k{k}", m, k) for m in methods for k in plan["student_steps"]]
    return out


def teacher_run(teachers: Path, task: str, plan: dict) -> Path:
    """The teacher of ``task`` in a simulation study's work folder ``teachers``: its seed-``plan["seed"]`` DSSP run,
    which must have finished (its done marker)."""
    name = f"{task}_dssp_s{plan['seed']}"
    teacher = teachers.resolve() / "runs" / name
    if not (teacher / "model.safetensors").is_file() or not (teachers / "done" / f"train_{name}.json").is_file():
        raise DSSPError(
            f"{teacher} is not a finished training of the study in {teachers}; run python -m studies.sim_study "
            f"--work {teachers} --tasks {task} first, or drop --teachers"
        )
    return teacher


def task_stages(task: str, plan: dict, record: Path, teachers: Path | None = None) -> list[Stage]:
    """The stages of ``task``'s cells not in ``record`` (none when every cell is): the teacher (collected and
    trained here unless ``teachers`` holds it), the students, every cell's export and evaluation."""
    todo = [(name, kind, k) for name, kind, k in cells(task, plan) if recorded(record, name) is None]
    if not todo:
        return []
    out: list[Stage] = []
    if teachers is None:
        data, teacher, collected = f"data/{task}.zarr", f"runs/{task}_teacher", (f"collect_{task}",)
        out += [
            collect_stage(task, task, plan["demos"][task], data),
            train_stage(
                f"{task}_teacher", data, teacher, plan["preset"], plan["steps"][task], plan["seed"], after=collected
            ),
        ]
        trained: tuple[str, ...] = (f"train_{task}_teacher",)
    else:
        teacher, trained = str(teacher_run(teachers, task, plan)), ()
    for name, kind, k in todo:
        run, flags, ready = (
            teacher,
            ("--denoise-steps", str(k), "--timestep-spacing", "trailing") if kind == "ddim" else (),
            trained,
        )
        if kind not in ("teacher", "ddim"):
            run, ready = f"runs/{name}", (f"distill_{name}",)
            argv = ("--teacher", teacher, "--steps", str(k), "--method", kind, "--out", run)
            argv += ("--train-steps", str(plan["distill_steps"][task]), "--no-progress", "--force")
            resume = ("--out", run, "--resume", "--no-progress")
            out.append(
                Stage(f"distill_{name}", distill.main, argv, after=trained, resume=resume, started=f"{run}/checkpoint")
            )
        model, threads = f"models/{name}", plan["threads"]
        out += [
            export_stage(
                name, run, model, *flags, "--threads", str(threads), "--force", *plan["export_flags"], after=ready
            ),
            eval_stage(
                name, model, task, plan["eval_episodes"], plan["eval_seed"], after=(f"export_{name}",), threads=threads
            ),
        ]
    return out


def latency_stages(plan: dict, record: Path, others: list[Stage]) -> list[Stage]:
    """The chunk's cost at each K not in ``record`` on a model of the latency preset's size (untrained weights: the
    cost is the same); the profiles run one at a time after ``others`` (the rest of the study's stages)."""
    lat = plan["latency"]
    todo = [k for k in lat["denoise_steps"] if recorded(record, f"latency_k{k}") is None]
    if not todo:
        return []
    from export import to_onnx  # deferred: loads torch, which a stage's process imports after setting its threads

    data, run = "data/latency.zarr", f"runs/latency_{lat['preset']}"
    argv = ("--data", data, "--out", run, "--preset", lat["preset"], "--steps", "1", "--set", "train.val_every=1")
    out = [
        Stage(
            "latency_data",
            synth.main,
            ("--out", data, "--episodes", "2", "--points", str(lat["points"])),
            clean=(data,),
        ),
        Stage("latency_train", train.main, (*argv, "--no-progress", "--force"), after=("latency_data",)),
    ]
    options = ("--timestep-spacing", "trailing", "--verify-steps", "50", "--threads", "1", "--force")
    out += [
        Stage(
            f"latency_export_k{k}",
            to_onnx.main,
            (run, "-o", f"models/latency_k{k}", "--denoise-steps", str(k), *options, *plan["export_flags"]),
            after=("latency_train",),
        )
        for k in todo
    ]
    before = tuple(s.name for s in [*others, *out])
    for k in todo:
        model, path = f"models/latency_k{k}", f"evals/latency_k{k}.json"
        argv = (model, "--threads", str(lat["threads"]), "--json", path, "--force", *lat["profile_flags"])
        out.append(Stage(f"latency_profile_k{k}", profile.main, argv, after=before, outputs=(path,)))
        before = (f"latency_profile_k{k}",)
    return out


def stages(plan: dict, parts: list[str], record: Path, teachers: Path | None = None) -> list[Stage]:
    """Every stage of ``parts`` (the plan's tasks, and :data:`LATENCY`) not done in ``record`` (module docstring)."""
    out = [s for task in parts if task != LATENCY for s in task_stages(task, plan, record, teachers)]
    return out + (latency_stages(plan, record, out) if LATENCY in parts else [])


def run_study(
    plan: dict, parts: list[str], work: Path, record: Path, workers: int, teachers: Path | None = None
) -> None:
    """Claim ``work`` for the study and run (or resume) every stage of ``parts``, keeping every finished evaluation,
    profile and stage time in ``record``. ``teachers``: a simulation study's work folder whose seed-``plan["seed"]``
    DSSP runs are the teachers (not trained again; their students train on the datasets they trained on)."""
    stage_list = stages(plan, parts, record, teachers)  # refuses unfinished teachers before anything is written
    claim_dir(work, kind=WORK_DIR, flag="--work", resume=True)
    for task in parts:
        names = (
            [f"latency_k{k}" for k in plan["latency"]["denoise_steps"]]
            if task == LATENCY
            else [c for c, _, _ in cells(task, plan)]
        )
        if all(recorded(record, name) is not None for name in names):
            print(f"{task}: every cell recorded ({record})")
    run_and_keep(work, record, stage_list, workers, ", ".join(parts), seconds=True)


def recorded_results(plan: dict, record: Path) -> tuple[dict, dict, list[str]]:
    """(evaluations, latency figures, names pending) as far as ``record`` holds them."""
    kept = {name: recorded(record, name) for task in plan["demos"] for name, _, _ in cells(task, plan)}
    kept |= {f"latency_k{k}": recorded(record, f"latency_k{k}") for k in plan["latency"]["denoise_steps"]}
    evals = {name: r for name, r in kept.items() if r is not None and not name.startswith("latency_k")}
    latency = {k: kept[f"latency_k{k}"] for k in plan["latency"]["denoise_steps"] if kept[f"latency_k{k}"] is not None}
    return evals, latency, [name for name, r in kept.items() if r is None]


def summarise(evals: dict, latency: dict, plan: dict) -> dict:
    """{"tasks": {task: {cell: {kind, steps, k, n, rate, wilson95, chunk_ms}}}, "latency": {K: {chunk_ms, ratio, path}}}."""
    tasks: dict = {}
    for task in plan["demos"]:
        for name, kind, k in cells(task, plan):
            r = evals.get(name)
            if r is not None:
                tasks.setdefault(task, {})[name] = {
                    "kind": kind,
                    "steps": k,
                    "k": r["successes"],
                    "n": r["n"],
                    "rate": r["successes"] / max(r["n"], 1),
                    "wilson95": list(wilson_interval(r["successes"], r["n"])),
                    "chunk_ms": r["latency_ms"].get("chunk", {}).get("p50"),
                }
    lat = {}
    base = latency.get(10) or latency.get("10")
    for k, f in latency.items():
        chunk = f["latency_ms"]["denoiser_chunk"]["p50"]
        lat[int(k)] = {
            "chunk_ms": chunk,
            "of_k10": chunk / base["latency_ms"]["denoiser_chunk"]["p50"] if base else None,
            "path": f"{f['precision']}, {f['kernel']}",
        }
    return {"tasks": tasks, "latency": lat}


LABELS = {
    "teacher": "teacher (DDIM, 10 steps)",
    "ddim": "teacher, DDIM at K trailing steps (no distillation)",
    "consistency": "student: consistency distillation",
    "trajectory": "student: trajectory distillation",
}


def report_files(report_dir: Path) -> list[Path]:
    """The report's files in ``report_dir``: REPORT_NAME.md, .json and .png."""
    return [report_dir / f"{REPORT_NAME}{suffix}" for suffix in REPORT_SUFFIXES]


def write_report(
    evals: dict,
    latency: dict,
    plan: dict,
    report_dir: Path,
    seconds: float,
    force: bool = False,
    pending: list[str] = (),
) -> Path:
    """The report's three files; ``pending``: the cells not run yet, listed."""
    check_output_files(report_files(report_dir), force=force, flag="--report")
    table = summarise(evals, latency, plan)
    lines = [
        "# Distillation: a chunk in one or two denoising steps",
        "",
        f"Produced by `python -m studies.distill_study` ({seconds / 60:.0f} min of stage time on this 2-core machine). "
        f"Teachers: DSSP, preset `{plan['preset']}`, trained as in the simulation study (steps {plan['steps']}, seed {plan['seed']}); "
        f"students: `dssp-distill` ({plan['distill_steps']} steps; both objectives on {', '.join(plan['method_tasks'])}, "
        f"{plan['method']} elsewhere). {plan['eval_episodes']} closed-loop episodes per cell on unseen seeds ({plan['eval_seed']}…), "
        f"95 % Wilson intervals; chunk = the denoiser's median time during the evaluation ({plan['threads']} thread, beside MuJoCo).",
        "",
    ]
    for task, rows in table["tasks"].items():
        lines += [f"## {task}", "", "| sampler | K | success | chunk ms (sim model) |", "|---|---:|---|---:|"]
        for row in rows.values():
            lines.append(
                f"| {LABELS[row['kind']]} | {row['steps']} | {pct(row['k'], row['n'])} | {row['chunk_ms']:.2f} |"
                if row["chunk_ms"]
                else f"| {LABELS[row['kind']]} | {row['steps']} | {pct(row['k'], row['n'])} | - |"
            )
        lines.append("")
    if table["latency"]:
        lat = plan["latency"]
        lines += [
            f"## The chunk on the `{lat['preset']}` preset",
            "",
            f"`dssp-profile` ({lat['threads']} threads, the runtime's default graphs) of one `{lat['preset']}` model exported at each K:",
            "",
            "| K | chunk ms (p50) | of K = 10 | graphs |",
            "|---:|---:|---:|---|",
        ]
        for k, row in sorted(table["latency"].items(), reverse=True):
            ratio = f"{row['of_k10']:.2f}" if row["of_k10"] is not None else "-"
            lines.append(f"| {k} | {row['chunk_ms']:.2f} | {ratio} | {row['path']} |")
        lines.append("")
    if pending:
        lines += [
            f"**Partial report**: {len(pending)} cell(s) of the plan are pending (not run yet): "
            + ", ".join(f"`{n}`" for n in pending)
            + ".",
            "",
        ]
    lines += [f"![success against K]({REPORT_NAME}.png)", ""]
    md, js, png = report_files(report_dir)
    write_output_text(md, "\n".join(lines), force=force, flag="--report")
    write_output_text(
        js,
        json.dumps(
            {"plan": plan, "summary": table, "evals": evals, "latency": latency, "pending": list(pending)}, indent=2
        )
        + "\n",
        force=force,
        flag="--report",
    )
    _plot(table, png, force)
    return md


def _plot(table: dict, path: Path, force: bool) -> None:
    import matplotlib  # here, not at the top: the study's command starts without it

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # here too, after matplotlib.use("Agg")

    tasks = list(table["tasks"])
    fig, axes = plt.subplots(1, max(1, len(tasks)), figsize=(4.5 * max(1, len(tasks)), 4), squeeze=False)
    for ax, task in zip(axes[0], tasks):
        rows = list(table["tasks"][task].values())
        labels = [f"{r['kind']}\nK={r['steps']}" for r in rows]
        rates = [100 * r["rate"] for r in rows]
        lo = [100 * (r["rate"] - wilson_interval(r["k"], r["n"])[0]) for r in rows]
        hi = [100 * (wilson_interval(r["k"], r["n"])[1] - r["rate"]) for r in rows]
        ax.bar(range(len(rows)), rates, yerr=[lo, hi], capsize=3, color=[f"C{i}" for i in range(len(rows))])
        ax.set_xticks(range(len(rows)), labels, fontsize=7)
        ax.set(ylabel="success %", ylim=(0, 105), title=task)
    fig.tight_layout()
    write_output_figure(path, fig, force=force, flag="--report")


def main(argv: list[str] | None = None) -> int:
    p = ArgumentParser(prog="python -m studies.distill_study", description=__doc__.split("\n")[0])
    p.add_argument(
        "--work", type=Path, default=Path("runs/distill_study"), help="datasets, runs, models, evaluations, logs"
    )
    p.add_argument("--report", type=Path, default=Path("reports/distill"), help="where the report and its record go")
    p.add_argument(
        "--tasks",
        nargs="+",
        metavar="TASK",
        help=f"run only these parts' stages ({', '.join(TASKS)}, {LATENCY}; default: all, then the report)",
    )
    p.add_argument("--quick", action="store_true", help="a tiny plan (tests): tap only, a few steps, one episode")
    p.add_argument(
        "--teachers",
        type=Path,
        metavar="STUDY_WORK",
        help="take the teachers from a simulation study's work "
        "folder (python -m studies.sim_study: its seed-0 DSSP runs) instead of training them",
    )
    p.add_argument("--workers", type=int, default=2, help="stages side by side, one thread each (default 2)")
    p.add_argument("--force", action="store_true", help="replace the report's files if they exist")
    p.add_argument(
        "--report-only",
        action="store_true",
        help="run no stage: write the report from the record "
        f"(--report/{RECORD_DIR}), the cells not run yet listed as pending",
    )
    args = p.parse_args(argv)
    plan = QUICK_PLAN if args.quick else PLAN
    parts = [*plan["demos"], LATENCY]
    unknown = [t for t in args.tasks or [] if t not in parts]
    if unknown:
        p.error(f"--tasks: {', '.join(unknown)} not in the plan ({', '.join(parts)})")
    if args.workers < 1:
        p.error(f"--workers must be at least 1, got {args.workers}")
    if args.report_only and args.tasks:
        p.error("--report-only writes the whole report from the record; drop --tasks")
    record = args.report / RECORD_DIR

    def _main() -> int:
        if not args.tasks:  # before any stage: a report that may not be replaced stops the study now
            check_output_files(report_files(args.report), force=args.force, flag="--report")
        if not args.report_only:
            run_study(plan, args.tasks or parts, args.work, record, args.workers, args.teachers)
            if args.tasks:
                print(f"stages of {', '.join(args.tasks)} done (kept in {record}); run without --tasks for the report")
                return 0
        evals, latency, pending = recorded_results(plan, record)
        if not evals:
            raise DSSPError(f"{record} holds no evaluation of this plan; run the study first")
        md = write_report(
            evals, latency, plan, args.report, stage_seconds(args.work, record), force=args.force, pending=pending
        )
        print(f"report: {md}")
        return 0

    return run_cli(_main)


if __name__ == "__main__":
    sys.exit(main())

"""The distillation study: a chunk in one or two denoising steps, against the 10-step teacher.

    python -m dssp_sim.distill_study [--work runs/distill_study] [--report reports/distill] [--tasks T ...]
                                     [--teachers runs/sim_experiment] [--force]

For each task: collect demonstrations and train the teacher as the simulation study does (preset ``sim``,
its steps and demonstrations, seed 0) — or take that study's own run (``--teachers``); export it at K = 10 (its own sampler) and at K = 1 and 2 trailing
steps without distillation (``--timestep-spacing trailing``: the first step at the noise level); distil it
(``dssp-distill``) into K = 1 and K = 2 students — with both objectives on the plan's method tasks, with the
plan's method elsewhere — and export them; evaluate every cell in closed loop on the same unseen episodes.
Then the chunk's cost where it matters, on the ``robotwin`` preset: one model of that size (its latency does
not depend on the weights) exported at K = 10, 2 and 1 and timed by ``dssp-profile`` (2 threads, the
runtime's default graphs).

The report — ``REPORT_NAME.md``, ``.png``, ``.json`` — goes to ``--report``. Stages are skipped when their
output exists (``--work`` resumes, ``--tasks`` splits the work), and every finished evaluation and stage time is
kept in the report's record (``--report``/record), so a machine without the work directory trains nothing
whose evaluations are recorded — as in :mod:`dssp_sim.experiment`, whose stage runner this uses.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from dssp_data.cli_runner import ArgumentParser, run_cli
from dssp_data.errors import DSSPError
from dssp_data.output_guard import OutputKind, check_output_files, write_output_figure, write_output_text
from dssp_sim.evaluate import wilson_interval
from dssp_sim.experiment import PLAN as MEMORY_PLAN
from dssp_sim.experiment import RECORD_DIR, keep, pct, recorded, stage, stage_seconds, study_tasks, train_stage

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
QUICK_PLAN = {**PLAN, "steps": {"tap": 20}, "demos": {"tap": 3}, "distill_steps": {"tap": 4}, "student_steps": [1],
              "method_tasks": [], "eval_episodes": 1, "export_flags": ["--skip-verify", "--quantize", "none"],
              "latency": {"preset": "tiny", "points": 64, "threads": 1, "denoise_steps": [10, 1], "profile_flags": ["--quick"]}}
WORK_DIR = OutputKind("a distillation-study work directory", "python -m dssp_sim.distill_study",
                      entries=("data", "runs", "models", "evals", "logs"), signature=lambda p: (p / "logs").is_dir())
REPORT_SUFFIXES = (".md", ".json", ".png")


def cells(task: str, plan: dict) -> list[tuple[str, str, int]]:
    """(cell name, kind, K) of a task: the teacher, undistilled DDIM at each student K, each method's students."""
    methods = plan["methods"] if task in plan["method_tasks"] else [plan["method"]]
    out = [(f"{task}_teacher_k10", "teacher", 10)]
    out += [(f"{task}_ddim_k{k}", "ddim", k) for k in plan["student_steps"]]
    out += [(f"{task}_{m}_k{k}", m, k) for m in methods for k in plan["student_steps"]]
    return out


def run_study(work: Path, plan: dict, tasks: list[str] | None = None, teachers: Path | None = None,
              record: Path | None = None) -> tuple[dict, dict]:
    """Run (or resume) every stage; returns ({cell: evaluation}, {K: dssp-profile figures on the latency preset}).

    ``teachers``: a simulation study's work directory whose seed-``plan["seed"]`` DSSP runs are the teachers (they
    are not trained again; their students train on the datasets they trained on). ``record``: where finished
    evaluations are kept; a task whose cells are all recorded trains nothing."""
    py, logs = sys.executable, work / "logs"
    evals: dict = {}
    for task, dataset in study_tasks(work, plan, tasks, WORK_DIR, others=("latency",), record=record):
        kept = {name: recorded(record, name) for name, _, _ in cells(task, plan)}
        if all(r is not None for r in kept.values()):
            evals.update(kept)
            print(f"  every cell recorded ({record})")
            continue
        if teachers is None:
            teacher = work / "runs" / f"{task}_teacher"
            train_stage(work, dataset(), teacher, plan, task, plan["seed"], [], "train the teacher", record=record)
        else:
            teacher = teachers / "runs" / f"{task}_dssp_s{plan['seed']}"
            if not (teacher / "model.safetensors").is_file() or not (teachers / "logs" / f"train_{teacher.name}.seconds").is_file():
                raise SystemExit(f"error: {teacher} is not a finished training of the study in {teachers}; run "
                                 f"python -m dssp_sim.experiment --work {teachers} --tasks {task} first, or drop --teachers")
            print(f"  teacher: {teacher}")
        for name, kind, k in cells(task, plan):
            if kept[name] is not None:
                evals[name] = kept[name]
                continue
            run_dir, flags = teacher, ["--denoise-steps", str(k), "--timestep-spacing", "trailing"] if kind == "ddim" else []
            if kind not in ("teacher", "ddim"):
                run_dir = work / "runs" / name
                stage(run_dir / "checkpoint", f"distil {kind} K={k}", [py, "-m", "dssp_train.cli.distill", "--teacher", str(teacher),
                      "--steps", str(k), "--method", kind, "--out", str(run_dir), "--train-steps", str(plan["distill_steps"][task]),
                      "--no-progress", "--force"], logs / f"distill_{name}.log", record)
            model = work / "models" / name
            stage(model / "dssp_model.json", f"export {name}", [py, "-m", "export.to_onnx", str(run_dir), "-o", str(model), *flags,
                  "--threads", str(plan["threads"]), "--force", *plan["export_flags"]], logs / f"export_{name}.log", record)
            out = work / "evals" / f"{name}.json"
            stage(out, f"eval {name}", [py, "-m", "dssp_sim.sim_cli", "eval", "--model", str(model), "--task", task, "--episodes",
                  str(plan["eval_episodes"]), "--seed", str(plan["eval_seed"]), "--threads", str(plan["threads"]), "--json",
                  str(out), "--no-progress"], logs / f"eval_{name}.log", record)
            keep(record, out, "evals")
            evals[name] = json.loads(out.read_text())
    latency = {} if tasks and "latency" not in tasks else _latency(work, plan, record)
    return evals, latency


def recorded_results(plan: dict, record: Path) -> tuple[dict, dict, list[str]]:
    """(evaluations, latency figures, names pending) as far as ``record`` holds them."""
    kept = {name: recorded(record, name) for task in plan["demos"] for name, _, _ in cells(task, plan)}
    kept |= {f"latency_k{k}": recorded(record, f"latency_k{k}") for k in plan["latency"]["denoise_steps"]}
    evals = {name: r for name, r in kept.items() if r is not None and not name.startswith("latency_k")}
    latency = {k: kept[f"latency_k{k}"] for k in plan["latency"]["denoise_steps"] if kept[f"latency_k{k}"] is not None}
    return evals, latency, [name for name, r in kept.items() if r is None]


def _latency(work: Path, plan: dict, record: Path | None = None) -> dict:
    """The chunk's cost at each K on a model of the latency preset's size (untrained weights: the cost is the same)."""
    py, logs, lat = sys.executable, work / "logs", plan["latency"]
    print(f"latency ({lat['preset']} preset):")
    kept = {k: recorded(record, f"latency_k{k}") for k in lat["denoise_steps"]}
    if all(r is not None for r in kept.values()):
        print(f"  every K recorded ({record})")
        return kept
    data, run_dir = work / "data" / "latency.zarr", work / "runs" / f"latency_{lat['preset']}"
    stage(data / "meta", "synthetic data", [py, "-m", "dssp_train.cli.synth", "--out", str(data), "--episodes", "2", "--points",
          str(lat["points"])], logs / "latency_data.log", record)
    stage(run_dir / "checkpoint", f"a {lat['preset']} model", [py, "-m", "dssp_train.cli.train", "--data", str(data), "--out",
          str(run_dir), "--preset", lat["preset"], "--steps", "1", "--set", "train.val_every=1", "--no-progress", "--force"],
          logs / "latency_train.log", record)
    figures = {}
    for k in lat["denoise_steps"]:
        model, out = work / "models" / f"latency_k{k}", work / "evals" / f"latency_k{k}.json"
        stage(model / "dssp_model.json", f"export K={k}", [py, "-m", "export.to_onnx", str(run_dir), "-o", str(model), "--denoise-steps",
              str(k), "--timestep-spacing", "trailing", "--verify-steps", "50", "--force", *plan["export_flags"]],
              logs / f"latency_export_k{k}.log", record)
        stage(out, f"profile K={k}", [py, "-m", "dssp_deploy.profile", str(model), "--threads", str(lat["threads"]), "--json", str(out),
              *lat["profile_flags"]], logs / f"latency_profile_k{k}.log", record)
        keep(record, out, "evals")
        figures[k] = json.loads(out.read_text())
    return figures


def summarise(evals: dict, latency: dict, plan: dict) -> dict:
    """{"tasks": {task: {cell: {kind, steps, k, n, rate, wilson95, chunk_ms}}}, "latency": {K: {chunk_ms, ratio, path}}}."""
    tasks: dict = {}
    for task in plan["demos"]:
        for name, kind, k in cells(task, plan):
            r = evals.get(name)
            if r is not None:
                tasks.setdefault(task, {})[name] = {
                    "kind": kind, "steps": k, "k": r["successes"], "n": r["n"], "rate": r["success_rate"], "wilson95": r["wilson95"],
                    "chunk_ms": r["latency_ms"].get("chunk", {}).get("p50")}
    lat = {}
    base = latency.get(10) or latency.get("10")
    for k, f in latency.items():
        chunk = f["latency_ms"]["denoiser_chunk"]["p50"]
        lat[int(k)] = {"chunk_ms": chunk, "of_k10": chunk / base["latency_ms"]["denoiser_chunk"]["p50"] if base else None,
                       "path": f"{f['precision']}, {f['kernel']}"}
    return {"tasks": tasks, "latency": lat}


LABELS = {"teacher": "teacher (DDIM, 10 steps)", "ddim": "teacher, DDIM at K trailing steps (no distillation)",
          "consistency": "student: consistency distillation", "trajectory": "student: trajectory distillation"}


def report_files(report_dir: Path) -> list[Path]:
    return [report_dir / f"{REPORT_NAME}{suffix}" for suffix in REPORT_SUFFIXES]


def write_report(evals: dict, latency: dict, plan: dict, report_dir: Path, seconds: float, force: bool = False,
                 pending: list[str] = ()) -> Path:
    """The report's three files; ``pending``: the cells not run yet (``--report-only``), listed."""
    check_output_files(report_files(report_dir), force=force, flag="--report")
    table = summarise(evals, latency, plan)
    lines = [
        "# Distillation: a chunk in one or two denoising steps",
        "",
        f"Produced by `python -m dssp_sim.distill_study` ({seconds / 60:.0f} min of stage time on this 2-core machine). "
        f"Teachers: DSSP, preset `{plan['preset']}`, trained as in the simulation study (steps {plan['steps']}, seed {plan['seed']}); "
        f"students: `dssp-distill` ({plan['distill_steps']} steps; both objectives on {', '.join(plan['method_tasks'])}, "
        f"{plan['method']} elsewhere). {plan['eval_episodes']} closed-loop episodes per cell on unseen seeds ({plan['eval_seed']}…), "
        f"95 % Wilson intervals; chunk = the denoiser's median time during the evaluation ({plan['threads']} thread, beside MuJoCo).",
        "",
    ]
    for task, rows in table["tasks"].items():
        lines += [f"## {task}", "", "| sampler | K | success | chunk ms (sim model) |", "|---|---:|---|---:|"]
        for row in rows.values():
            lines.append(f"| {LABELS[row['kind']]} | {row['steps']} | {pct(row['k'], row['n'])} | "
                         f"{row['chunk_ms']:.2f} |" if row["chunk_ms"] else f"| {LABELS[row['kind']]} | {row['steps']} | "
                         f"{pct(row['k'], row['n'])} | - |")
        lines.append("")
    if table["latency"]:
        lat = plan["latency"]
        lines += [f"## The chunk on the `{lat['preset']}` preset", "",
                  f"`dssp-profile` ({lat['threads']} threads, the runtime's default graphs) of one `{lat['preset']}` model exported at each K:",
                  "", "| K | chunk ms (p50) | of K = 10 | graphs |", "|---:|---:|---:|---|"]
        for k, row in sorted(table["latency"].items(), reverse=True):
            ratio = f"{row['of_k10']:.2f}" if row["of_k10"] is not None else "-"
            lines.append(f"| {k} | {row['chunk_ms']:.2f} | {ratio} | {row['path']} |")
        lines.append("")
    if pending:
        lines += [f"**Partial report**: {len(pending)} cell(s) of the plan are pending (not run yet): "
                  + ", ".join(f"`{n}`" for n in pending) + ".", ""]
    lines += [f"![success against K]({REPORT_NAME}.png)", ""]
    md, js, png = report_files(report_dir)
    write_output_text(md, "\n".join(lines), force=force, flag="--report")
    write_output_text(js, json.dumps({"plan": plan, "summary": table, "evals": evals, "latency": latency,
                                      "pending": list(pending)}, indent=2) + "\n",
                      force=force, flag="--report")
    _plot(table, png, force)
    return md


def _plot(table: dict, path: Path, force: bool) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

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
    p = ArgumentParser(prog="python -m dssp_sim.distill_study", description=__doc__.split("\n")[0])
    p.add_argument("--work", type=Path, default=Path("runs/distill_study"), help="datasets, runs, models, evaluations")
    p.add_argument("--report", type=Path, default=Path("reports/distill"), help="where the report goes")
    p.add_argument("--tasks", nargs="+", metavar="TASK", help="run only these tasks' stages (tap, put2, swap, latency; "
                                                               "default: all, then the report)")
    p.add_argument("--quick", action="store_true", help="a tiny plan (tests): tap only, a few steps, one episode")
    p.add_argument("--teachers", type=Path, metavar="STUDY_WORK", help="take the teachers from a simulation study's work "
                   "directory (python -m dssp_sim.experiment: its seed-0 DSSP runs) instead of training them")
    p.add_argument("--force", action="store_true", help="replace the report's files if they exist")
    p.add_argument("--report-only", action="store_true", help="run no stage: write the report from the record "
                   f"(--report/{RECORD_DIR}), the cells not run yet listed as pending")
    args = p.parse_args(argv)
    plan = QUICK_PLAN if args.quick else PLAN
    if args.report_only and args.tasks:
        p.error("--report-only writes the whole report from the record; drop --tasks")

    def _main() -> int:
        if not args.tasks:
            check_output_files(report_files(args.report), force=args.force, flag="--report")
        if args.report_only:
            evals, latency, pending = recorded_results(plan, args.report / RECORD_DIR)
            if not evals:
                raise DSSPError(f"{args.report / RECORD_DIR} holds no evaluation of this plan; run the study first")
            md = write_report(evals, latency, plan, args.report, stage_seconds(args.work, args.report / RECORD_DIR),
                              force=args.force, pending=pending)
            print(f"report: {md}")
            return 0
        started = time.perf_counter()
        evals, latency = run_study(args.work, plan, args.tasks, args.teachers, args.report / RECORD_DIR)
        if args.tasks:
            print(f"stages of {', '.join(args.tasks)} done in {time.perf_counter() - started:.0f} s; run without --tasks for the report")
            return 0
        md = write_report(evals, latency, plan, args.report, stage_seconds(args.work, args.report / RECORD_DIR), force=args.force)
        print(f"report: {md}")
        return 0

    return run_cli(_main)


if __name__ == "__main__":
    sys.exit(main())

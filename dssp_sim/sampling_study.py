"""The sampling study: closed-loop success and chunk cost against DDIM steps K and weight precision.

    python -m dssp_sim.sampling_study [--work runs/sampling_study] [--report reports/sampling] [--tasks T ...] [--force]

For each task (``tap``, ``put2``): collect expert demonstrations and train DSSP as the simulation study
does (:mod:`dssp_sim.experiment`: preset ``sim``, the same steps, demonstrations and seed 0); export it
once per K in :data:`PLAN` ``denoise_steps`` (every export writes fp32, int8 and int4 graphs, standard
and fused, and proves the parity of the fp32 ones); evaluate every (K, precision) in closed loop through
the robot's chain on the same unseen episode seeds, on the graphs the runtime picks by default (the
fused Mamba kernel when it loads; each evaluation records which ran). The chunk cost of each cell is
the denoiser's median time measured during that evaluation (one ONNX Runtime thread, beside MuJoCo).

The report — ``REPORT_NAME.md`` (tables), ``.png`` (plot), ``.json`` (every figure) — goes to
``--report``. Stages are skipped when their output exists (``--work`` is resumed, ``--tasks`` splits
the work across processes), as in :mod:`dssp_sim.experiment`, whose stage runner this uses.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from dssp_data.cli_runner import ArgumentParser, run_cli
from dssp_data.output_guard import OutputKind, check_output_files, write_output_figure, write_output_text
from dssp_deploy.manifest import PRECISIONS
from dssp_sim.evaluate import wilson_interval
from dssp_sim.experiment import PLAN as MEMORY_PLAN
from dssp_sim.experiment import pct, stage, stage_seconds, study_tasks, train_stage

REPORT_NAME = "sampling"
PLAN = {
    "preset": MEMORY_PLAN["preset"],
    "steps": {task: MEMORY_PLAN["steps"][task] for task in ("tap", "put2")},
    "demos": {task: MEMORY_PLAN["demos"][task] for task in ("tap", "put2")},
    "seed": 0,
    "denoise_steps": [10, 5, 3, 2],
    "precisions": list(PRECISIONS),
    "eval_episodes": MEMORY_PLAN["eval_episodes"],
    "eval_seed": MEMORY_PLAN["eval_seed"],
    "threads": 1,
}
WORK_DIR = OutputKind("a sampling-study work directory", "python -m dssp_sim.sampling_study",
                      entries=("data", "runs", "models", "evals", "logs"), signature=lambda p: (p / "logs").is_dir())
REPORT_SUFFIXES = (".md", ".json", ".png")


def cell(task: str, k: int, precision: str) -> str:
    return f"{task}_k{k}_{precision}"


def run_study(work: Path, plan: dict, tasks: list[str] | None = None) -> dict:
    """Run (or resume) every stage for ``tasks`` (default all); returns {cell name: evaluation result}."""
    py, logs = sys.executable, work / "logs"
    evals: dict = {}
    for task, dataset in study_tasks(work, plan, tasks, WORK_DIR):
        run_dir = work / "runs" / f"{task}_dssp_s{plan['seed']}"
        train_stage(work, dataset(), run_dir, plan, task, plan["seed"], [], "train DSSP", name=task)
        for k in plan["denoise_steps"]:
            model_dir = work / "models" / f"{task}_k{k}"
            stage(model_dir / "dssp_model.json", f"export K={k}", [py, "-m", "export.to_onnx", str(run_dir), "-o", str(model_dir),
                   "--denoise-steps", str(k), "--threads", str(plan["threads"]), "--force"], logs / f"export_{task}_k{k}.log")
            for precision in plan["precisions"]:
                name = cell(task, k, precision)
                out = work / "evals" / f"{name}.json"
                stage(out, f"eval K={k} {precision}", [py, "-m", "dssp_sim.sim_cli", "eval", "--model", str(model_dir), "--task", task,
                       "--episodes", str(plan["eval_episodes"]), "--seed", str(plan["eval_seed"]), "--precision", precision,
                       "--threads", str(plan["threads"]), "--json", str(out), "--no-progress"], logs / f"eval_{name}.log")
                evals[name] = json.loads(out.read_text())
    return evals


def summarise(evals: dict, plan: dict) -> dict:
    """{task: {precision: {K: {k, n, rate, wilson95, chunk_ms, kernel}}}} from the evaluation results."""
    table: dict = {}
    for task in plan["demos"]:
        for precision in plan["precisions"]:
            for k in plan["denoise_steps"]:
                r = evals.get(cell(task, k, precision))
                if r is None:
                    continue
                chunk = r["latency_ms"].get("chunk", {}).get("p50")
                table.setdefault(task, {}).setdefault(precision, {})[k] = {
                    "k": r["successes"], "n": r["n"], "rate": r["success_rate"], "wilson95": r["wilson95"],
                    "chunk_ms": chunk, "kernel": r.get("kernel")}
    return table


def eligible_precisions(table: dict, plan: dict) -> dict:
    """Per precision at K = the plan's first (10): is its success inside fp32's 95 % interval on every task?

    The default precision is the fastest eligible one; speed is a property of the model's size, not of
    these small models (their chunks take about the same time at every precision), so it is judged on the
    robotwin preset (``dssp-profile --precision P``, the README's table)."""
    k = plan["denoise_steps"][0]
    verdict = {}
    for precision in plan["precisions"]:
        rows = {task: table[task].get(precision, {}).get(k) for task in table}
        inside = {task: r is not None and table[task]["fp32"][k]["wilson95"][0] <= r["rate"] <= table[task]["fp32"][k]["wilson95"][1]
                  for task, r in rows.items()}
        verdict[precision] = {"inside_fp32_interval": all(inside.values()), "per_task": inside}
    return {"at_denoise_steps": k, "per_precision": verdict}


def report_files(report_dir: Path) -> list[Path]:
    return [report_dir / f"{REPORT_NAME}{suffix}" for suffix in REPORT_SUFFIXES]


def write_report(evals: dict, plan: dict, report_dir: Path, seconds: float, force: bool = False) -> Path:
    check_output_files(report_files(report_dir), force=force, flag="--report")
    table = summarise(evals, plan)
    choice = eligible_precisions(table, plan)
    kernels = sorted({row["kernel"] for t in table.values() for p in t.values() for row in p.values() if row["kernel"]})
    lines = [
        "# Sampling: DDIM steps K and weight precision against closed-loop success",
        "",
        f"Produced by `python -m dssp_sim.sampling_study` ({seconds / 60:.0f} min of stage time on this 2-core machine). "
        f"DSSP, preset `{plan['preset']}`, trained once per task as in the simulation study (steps {plan['steps']}, seed "
        f"{plan['seed']}), exported once per K; {plan['eval_episodes']} closed-loop episodes per cell on unseen seeds "
        f"({plan['eval_seed']}…), graphs run: {', '.join(kernels) or '-'} Mamba path. Success with 95 % Wilson intervals; "
        f"chunk = the denoiser's median time during the evaluation ({plan['threads']} ONNX Runtime thread, beside MuJoCo).",
        "",
    ]
    for task, per_precision in table.items():
        lines += [f"## {task}", "", "| K | " + " | ".join(f"{p} success | {p} chunk ms" for p in per_precision) + " |",
                  "|---:|" + "---|---:|" * len(per_precision)]
        for k in plan["denoise_steps"]:
            cells = []
            for precision, rows in per_precision.items():
                row = rows.get(k)
                cells += ["-", "-"] if row is None else [pct(row["k"], row["n"]), f"{row['chunk_ms']:.2f}" if row["chunk_ms"] else "-"]
            lines.append(f"| {k} | " + " | ".join(cells) + " |")
        lines.append("")
    k = choice["at_denoise_steps"]
    lines += [f"Eligible as the runtime's default precision (success inside fp32's 95 % interval on every task at K = {k}); "
              "the default is the fastest eligible one on the robotwin preset (the README's CPU table):", ""]
    for precision, v in choice["per_precision"].items():
        lines.append(f"- {precision}: {'eligible' if v['inside_fp32_interval'] else 'not eligible'} "
                     f"({', '.join(f'{t} ' + ('inside' if ok else 'outside') for t, ok in v['per_task'].items())})")
    lines += ["", f"![success and chunk cost against K]({REPORT_NAME}.png)", ""]
    md, js, png = report_files(report_dir)
    write_output_text(md, "\n".join(lines), force=force, flag="--report")
    write_output_text(js, json.dumps({"plan": plan, "summary": table, "eligible_precisions": choice, "evals": evals}, indent=2) + "\n",
                      force=force, flag="--report")
    _plot(table, plan, png, force)
    return md


def _plot(table: dict, plan: dict, path: Path, force: bool) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for task, per_precision in table.items():
        for precision, rows in per_precision.items():
            ks = [k for k in plan["denoise_steps"] if k in rows]
            rates = [100 * rows[k]["rate"] for k in ks]
            lo = [100 * (rows[k]["rate"] - wilson_interval(rows[k]["k"], rows[k]["n"])[0]) for k in ks]
            hi = [100 * (wilson_interval(rows[k]["k"], rows[k]["n"])[1] - rows[k]["rate"]) for k in ks]
            axes[0].errorbar(ks, rates, yerr=[lo, hi], marker="o", capsize=3, label=f"{task} {precision}")
            axes[1].plot(ks, [rows[k]["chunk_ms"] or float("nan") for k in ks], marker="o", label=f"{task} {precision}")
    axes[0].set(xlabel="DDIM steps K", ylabel="success %", ylim=(0, 105), title="Closed-loop success (95 % Wilson)")
    axes[1].set(xlabel="DDIM steps K", ylabel="ms", ylim=(0, None), title="Denoiser chunk, median (1 thread)")
    for ax in axes:
        ax.set_xticks(plan["denoise_steps"])
        ax.legend(fontsize=7)
    fig.tight_layout()
    write_output_figure(path, fig, force=force, flag="--report")


def main(argv: list[str] | None = None) -> int:
    p = ArgumentParser(prog="python -m dssp_sim.sampling_study", description=__doc__.split("\n")[0])
    p.add_argument("--work", type=Path, default=Path("runs/sampling_study"), help="datasets, runs, models, evaluations")
    p.add_argument("--report", type=Path, default=Path("reports/sampling"), help="where the report goes")
    p.add_argument("--tasks", nargs="+", metavar="TASK", help="run only these tasks' stages (default: all, then the report)")
    p.add_argument("--force", action="store_true", help="replace the report's files if they exist")
    args = p.parse_args(argv)

    def _main() -> int:
        if not args.tasks:
            check_output_files(report_files(args.report), force=args.force, flag="--report")
        started = time.perf_counter()
        evals = run_study(args.work, PLAN, args.tasks)
        if args.tasks:
            print(f"stages of {', '.join(args.tasks)} done in {time.perf_counter() - started:.0f} s; run without --tasks for the report")
            return 0
        md = write_report(evals, PLAN, args.report, stage_seconds(args.work), force=args.force)
        print(f"report: {md}")
        return 0

    return run_cli(_main)


if __name__ == "__main__":
    sys.exit(main())

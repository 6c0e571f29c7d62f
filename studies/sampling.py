"""The sampling study: closed-loop success and chunk cost against DDIM steps K and weight precision.

    python -m studies.sampling [--tasks tap put2] [--workers 2] [--work runs/sampling] [--report reports/sampling]
                               [--report-only] [--quick]

For each task (``tap``, ``put2``): collect the expert demonstrations, train DSSP as the memory-task study does
(preset ``sim``, its steps and demonstrations, training seed 0), export it once per K in the plan (every export
writes fp32, int8 and int4 graphs and proves the fp32 ones' parity) and evaluate every (K, precision) cell in
closed loop through the robot's chain on the same scenes, on the graphs the runtime picks (the fused Mamba
kernel when it loads; each evaluation records which ran). K and the default precision are choices, so the
study runs on **validation** seeds only (:mod:`studies.protocol`). The chunk cost of a cell is the denoiser's
median time during its evaluation (one ONNX Runtime thread, beside MuJoCo).

Stages run on :class:`studies.runner.Runner` (side by side, one thread each, resumed). Each evaluation is kept
in the record (``--report``/record/evals/NAME.json, :func:`studies.evaluations.compact`: counts, episodes,
chunk latency); the report —
``sampling.md``, ``.json``, ``.png`` — is rebuilt from the record alone (``--report-only``,
``python -m studies.rebuild``).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from dssp_core.errors import DSSPError
from dssp_core.output_guard import write_output_figure
from dssp_deploy.manifest import PRECISIONS
from dssp_sim.evaluate import wilson_interval
from studies import memory_tasks, protocol
from studies.evaluations import study_main, write_md_and_json
from studies.runner import Stage
from studies.sim_study import pct
from studies.study_stages import collect_stage, eval_stage, export_stage, train_stage

REPORT_NAME = "sampling"
PLAN = {
    "tasks": {task: memory_tasks.PLAN["tasks"][task] for task in ("tap", "put2")},
    "preset": "sim",
    "seed": 0,
    "denoise_steps": [10, 5, 3, 2],
    "precisions": list(PRECISIONS),
    "episodes": 20,
}
QUICK_PLAN = {
    **PLAN,
    "tasks": {"tap": {"demos": 3, "steps": 10}},
    "denoise_steps": [2, 1],
    "precisions": ["fp32", "int8"],
    "episodes": 1,
}
RECORD_DIR = "record"


def cell(task: str, k: int, precision: str) -> str:
    return f"{task}_k{k}_{precision}"


def stages(plan: dict, tasks: list[str], record: Path) -> list[Stage]:
    """Every stage of ``tasks``; a cell whose evaluation is in the record needs none."""
    n = plan["episodes"]
    first = protocol.split_seeds("validation", n)[0]
    out: list[Stage] = []
    for task in tasks:
        spec, data, run = plan["tasks"][task], f"data/{task}.zarr", f"runs/{task}_dssp_s{plan['seed']}"
        task_stages: list[Stage] = []
        trained = (f"train_{task}",)
        for k in plan["denoise_steps"]:
            model, ready = f"models/{task}_k{k}", (f"export_{task}_k{k}",)
            cells = [
                eval_stage(cell(task, k, p), model, task, n, first, "--precision", p, after=ready)
                for p in plan["precisions"]
                if not (record / "evals" / f"{cell(task, k, p)}.json").is_file()
            ]
            if not cells:
                continue
            options = ("--denoise-steps", str(k), "--threads", "1", "--force")
            task_stages += [export_stage(f"{task}_k{k}", run, model, *options, after=trained), *cells]
        if task_stages:
            out += [
                collect_stage(task, task, spec["demos"], data),
                train_stage(task, data, run, plan["preset"], spec["steps"], plan["seed"], after=(f"collect_{task}",)),
                *task_stages,
            ]
    return out


def recorded(plan: dict, record: Path) -> dict:
    """{cell: evaluation} of every cell of the plan the record holds."""
    evals = {}
    for task in plan["tasks"]:
        for k in plan["denoise_steps"]:
            for p in plan["precisions"]:
                path = record / "evals" / f"{cell(task, k, p)}.json"
                if path.is_file():
                    evals[cell(task, k, p)] = json.loads(path.read_text())
    return evals


def summarise(evals: dict, plan: dict) -> dict:
    """{task: {precision: {K: {k, n, rate, wilson95, chunk_ms, kernel}}}} from the evaluations."""
    table: dict = {}
    for task in plan["tasks"]:
        for precision in plan["precisions"]:
            for k in plan["denoise_steps"]:
                r = evals.get(cell(task, k, precision))
                if r is None:
                    continue
                table.setdefault(task, {}).setdefault(precision, {})[k] = {
                    "k": r["successes"],
                    "n": r["n"],
                    "rate": r["successes"] / max(r["n"], 1),
                    "wilson95": list(wilson_interval(r["successes"], r["n"])),
                    "chunk_ms": r["latency_ms"].get("chunk", {}).get("p50"),
                    "kernel": r.get("kernel"),
                }
    return table


def eligible_precisions(table: dict, plan: dict) -> dict:
    """Per precision at the plan's first K: is its success inside fp32's 95 % interval on every task? The default
    precision is the fastest eligible one; speed is judged on the paper's size (the README's CPU table)."""
    k = plan["denoise_steps"][0]
    verdict = {}
    for precision in plan["precisions"]:
        inside = {}
        for task in table:
            r, ref = table[task].get(precision, {}).get(k), table[task].get("fp32", {}).get(k)
            inside[task] = r is not None and ref is not None and ref["wilson95"][0] <= r["rate"] <= ref["wilson95"][1]
        verdict[precision] = {"inside_fp32_interval": all(inside.values()), "per_task": inside}
    return {"at_denoise_steps": k, "per_precision": verdict}


def write_report(plan: dict, record: Path, report: Path, shown_record: str | None = None) -> Path:
    """``sampling.md``, ``.json``, ``.png`` from the record alone."""
    evals = recorded(plan, record)
    if not evals:
        raise DSSPError(f"{record} holds no evaluation of this plan; run the study first")
    table = summarise(evals, plan)
    choice = eligible_precisions(table, plan)
    scenes = protocol.split_seeds("validation", plan["episodes"])
    kernels = sorted({row["kernel"] for t in table.values() for p in t.values() for row in p.values() if row["kernel"]})
    lines = [
        "# Sampling: DDIM steps K and weight precision against closed-loop success",
        "",
        f"Rebuilt from `{shown_record or record}` by `python -m studies.sampling --report-only`. DSSP, preset `{plan['preset']}`, "
        f"trained once per task (steps { ({t: s['steps'] for t, s in plan['tasks'].items()}) }, seed {plan['seed']}), exported "
        f"once per K; {plan['episodes']} closed-loop episodes per cell on validation seeds {scenes[0]}–{scenes[-1]} (K and the "
        f"precision are choices: validation, not a test result); graphs run: {', '.join(kernels) or '-'} Mamba path. Success "
        "with 95 % Wilson intervals (one training seed); chunk = the denoiser's median time during the evaluation (one "
        "ONNX Runtime thread, beside MuJoCo).",
        "",
    ]
    for task, per_precision in table.items():
        lines += [
            f"## {task}",
            "",
            "| K | " + " | ".join(f"{p} success | {p} chunk ms" for p in per_precision) + " |",
            "|---:|" + "---|---:|" * len(per_precision),
        ]
        for k in plan["denoise_steps"]:
            cells = []
            for rows in per_precision.values():
                row = rows.get(k)
                cells += (
                    ["pending", "-"]
                    if row is None
                    else [pct(row["k"], row["n"]), f"{row['chunk_ms']:.2f}" if row["chunk_ms"] else "-"]
                )
            lines.append(f"| {k} | " + " | ".join(cells) + " |")
        lines.append("")
    lines += [
        f"Eligible as the runtime's default precision (success inside fp32's 95 % interval on every task at K = "
        f"{choice['at_denoise_steps']}):",
        "",
    ]
    for precision, v in choice["per_precision"].items():
        lines.append(
            f"- {precision}: {'eligible' if v['inside_fp32_interval'] else 'not eligible'} ("
            + ", ".join(f"{t} " + ("inside" if ok else "outside") for t, ok in v["per_task"].items())
            + ")"
        )
    lines += ["", f"![success and chunk cost against K]({REPORT_NAME}.png)", ""]
    md = write_md_and_json(report, REPORT_NAME, lines, {"plan": plan, "summary": table, "eligible_precisions": choice})
    plot(table, plan, report / f"{REPORT_NAME}.png")
    return md


def readme_table(record: Path, plan: dict = PLAN) -> str:
    """The README's ``sampling`` block: each task's success per precision at the plan's first K, and which
    precisions are eligible as the runtime's default (:func:`eligible_precisions`)."""
    table = summarise(recorded(plan, record), plan)
    k, precisions = plan["denoise_steps"][0], plan["precisions"]
    lines = [
        f"| task (K = {k}, {plan['episodes']} validation episodes) | " + " | ".join(precisions) + " |",
        "|---|" + "---:|" * len(precisions),
    ]
    for task, per_precision in table.items():
        cells = [per_precision.get(p, {}).get(k) for p in precisions]
        lines.append(
            f"| {task} | "
            + " | ".join("pending" if c is None else pct(c["k"], c["n"]).split(" (")[0] for c in cells)
            + " |"
        )
    verdict = eligible_precisions(table, plan)["per_precision"]
    lines += [
        "",
        "Eligible as the default precision (inside fp32's 95 % interval on every task): "
        + ", ".join(f"{p} {'yes' if v['inside_fp32_interval'] else 'no'}" for p, v in verdict.items() if p != "fp32")
        + ".",
    ]
    return "\n".join(lines) + "\n"


def plot(table: dict, plan: dict, path: Path) -> None:
    import matplotlib  # here, not at the top: the study's command starts without it

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # here too, after matplotlib.use("Agg")

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for task, per_precision in table.items():
        for precision, rows in per_precision.items():
            ks = [k for k in plan["denoise_steps"] if k in rows]
            rates = [100 * rows[k]["rate"] for k in ks]
            lo = [100 * (rows[k]["rate"] - rows[k]["wilson95"][0]) for k in ks]
            hi = [100 * (rows[k]["wilson95"][1] - rows[k]["rate"]) for k in ks]
            axes[0].errorbar(ks, rates, yerr=[lo, hi], marker="o", capsize=3, label=f"{task} {precision}")
            axes[1].plot(ks, [rows[k]["chunk_ms"] or float("nan") for k in ks], marker="o", label=f"{task} {precision}")
    axes[0].set(xlabel="DDIM steps K", ylabel="success %", ylim=(0, 105), title="Closed-loop success (95 % Wilson)")
    axes[1].set(xlabel="DDIM steps K", ylabel="ms", ylim=(0, None), title="Denoiser chunk, median (1 thread)")
    for ax in axes:
        ax.set_xticks(plan["denoise_steps"])
        ax.legend(fontsize=7)
    fig.tight_layout()
    write_output_figure(path, fig, force=True, flag="--report")


def main(argv: list[str] | None = None) -> int:
    return study_main(argv, "sampling", __doc__, PLAN, QUICK_PLAN, "validation", stages, write_report)


if __name__ == "__main__":
    sys.exit(main())

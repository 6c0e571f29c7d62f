"""The delay study: closed-loop success and the jerk at chunk boundaries against the inference delay, for the three
ways of taking actions from chunks (none, temporal ensembling, real-time chunking).

    python -m studies.delay_study [--tasks tap put2] [--workers 2] [--work runs/delay] [--report reports/delay]
                                  [--report-only] [--quick]

For each task (``tap``, ``put2``): collect the expert demonstrations, train DSSP with each training seed of the plan
(preset ``sim``), export each with ``--inpainting`` (the denoiser real-time chunking needs; with zero weights it is the plain chain,
so one model serves the three modes), and evaluate every (smoothing, delay) cell in the MuJoCo twin, in lockstep, with
the delay injected per chunk (``dssp-sim eval --inject-delay MS``: each chunk usable only that long after its
observation, in whole 10 Hz ticks — 50 and 100 ms are both one tick, 200 ms two, 400 ms four). The modes:

- ``none``: synchronous; the arm holds while a chunk is computed, then executes its H_a actions from the first;
- ``ensemble``: ACT's temporal ensembling, a chunk every tick (decay 0.01), each taken in late at the actions for
  the ticks it then covers;
- ``rtc``: real-time chunking, the next chunk started H_a ticks after the previous one, inpainted to agree with the
  actions still committed, taking over after the delay.

Nothing is tuned here (the modes' settings are their defaults, fixed before any evaluation), and the evaluations
use the **validation** seeds, the same scenes in every cell (paired). A cell's jerk is the commanded joints' jerk
(rad/s³) at the ticks a new chunk took over, beside the other ticks' (:func:`dssp_sim.evaluate.command_jerk`).
Success rates come with the two-way cluster-bootstrap interval over training seeds and scenes, and differences
between modes at each delay with the exact paired test over the shared scenes and seeds (:mod:`studies.stats`).

Stages run on :class:`studies.runner.Runner` (side by side, one thread each, resumed); the record keeps each
evaluation (``record/evals``); ``delay.md``, ``.json``, ``.png`` are rebuilt from it alone (``--report-only``,
``python -m studies.rebuild``).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from dssp_core.errors import DSSPError
from dssp_core.output_guard import write_output_figure
from studies import protocol
from studies.evaluations import study_main, write_md_and_json
from studies.runner import Stage
from studies.stats import (
    agrees,
    cluster_bootstrap,
    describe_p,
    disagreements,
    holm_family,
    paired_difference,
    paired_exact_test,
)
from studies.study_stages import collect_stage, eval_stage, export_stage, train_stage

REPORT_NAME = "delay"
PLAN = {
    "tasks": {"tap": {"demos": 50, "steps": 3000}, "put2": {"demos": 50, "steps": 1500}},
    "preset": "sim",
    "seeds": [0, 1],
    "delays_ms": [0, 50, 100, 200, 400],
    "smoothings": ["none", "ensemble", "rtc"],
    "episodes": 20,
    "export_flags": ["--inpainting", "--quantize", "int8"],
}
QUICK_PLAN = {
    **PLAN,
    "tasks": {"tap": {"demos": 3, "steps": 10}},
    "delays_ms": [0, 200],
    "episodes": 1,
    "seeds": [0],
    "export_flags": ["--inpainting", "--skip-verify", "--quantize", "none"],
}
RECORD_DIR = "record"
SPLIT = "validation"
CONTROL_RATE_HZ = 10  # the twin's: a delay of d ms is ceil(d / 100) ticks


UNEQUAL_COMPUTE = (
    "The compute is not equal: `none` and `rtc` have one chunk in flight at a time, `ensemble` starts one every tick, so "
    "with a delay of d ticks it has d chunks in flight at once — d times the denoiser throughput of one computation that "
    "takes d ticks (on one CPU that also takes d ticks each, it could not keep up)."
)


def ticks_of(delay_ms: int) -> int:
    """The injected delay in whole control ticks (rounded up, as ``dssp-sim eval --inject-delay`` counts it)."""
    return -(-delay_ms * CONTROL_RATE_HZ // 1000)


def eval_flags(plan: dict, mode: str, delay_ms: int) -> tuple[str, ...]:
    """``dssp-sim eval``'s flags for ``mode`` at ``delay_ms``: the plan's mode flags (default ``--smoothing MODE``;
    ``{every}``: the delay in ticks, at least 1), the delay, then the plan's ``eval_flags``."""
    spec = plan.get("modes", {}).get(mode, {"flags": ["--smoothing", mode]})
    flags = (f.format(every=max(1, ticks_of(delay_ms))) for f in spec["flags"])
    return (*flags, "--inject-delay", str(delay_ms), *plan.get("eval_flags", []))


def model_of(plan: dict, mode: str) -> str:
    """Which of a seed's models ``mode`` evaluates: "plain" (the preset's), or a name in the plan's ``models``."""
    return plan.get("modes", {}).get(mode, {}).get("model", "plain")


def cell(task: str, smoothing: str, delay: int, seed: int) -> str:
    return f"{task}_{smoothing}_d{delay}_s{seed}"


def stages(plan: dict, tasks: list[str], record: Path) -> list[Stage]:
    """Every stage of ``tasks``; a cell whose evaluation is in the record needs none."""
    n = plan["episodes"]
    first = protocol.split_seeds(SPLIT, n)[0]
    out: list[Stage] = []
    for task in tasks:
        spec, data = plan["tasks"][task], f"data_{task}.zarr"
        task_stages: list[Stage] = []
        for seed in plan["seeds"]:
            for variant, train_flags in {"plain": (), **plan.get("models", {})}.items():
                suffix = "" if variant == "plain" else f"_{variant}"
                run, model, key = (
                    f"run_{task}{suffix}_s{seed}",
                    f"model_{task}{suffix}_s{seed}",
                    f"{task}{suffix}_s{seed}",
                )
                ready = (f"export_{key}",)
                names = {
                    cell(task, s, d, seed): (s, d)
                    for d in plan["delays_ms"]
                    for s in plan["smoothings"]
                    if model_of(plan, s) == variant
                }
                cells = [
                    eval_stage(name, model, task, n, first, *eval_flags(plan, s, d), after=ready)
                    for name, (s, d) in names.items()
                    if not (record / "evals" / f"{name}.json").is_file()
                ]
                if not cells:
                    continue
                task_stages += [
                    train_stage(
                        key, data, run, plan["preset"], spec["steps"], seed, *train_flags, after=(f"collect_{task}",)
                    ),
                    export_stage(
                        key, run, model, "--threads", "1", "--force", *plan["export_flags"], after=(f"train_{key}",)
                    ),
                    *cells,
                ]
        if task_stages:
            out += [collect_stage(task, task, spec["demos"], data), *task_stages]
    return out


def recorded(plan: dict, record: Path) -> dict:
    """{cell: evaluation} of every cell of the plan the record holds."""
    evals = {}
    for task in plan["tasks"]:
        for d in plan["delays_ms"]:
            for s in plan["smoothings"]:
                for seed in plan["seeds"]:
                    path = record / "evals" / f"{cell(task, s, d, seed)}.json"
                    if path.is_file():
                        evals[cell(task, s, d, seed)] = json.loads(path.read_text())
    return evals


def _grid(evals: dict, plan: dict, task: str, smoothing: str, delay: int) -> tuple[list[list[int]], list[dict]] | None:
    """The (training seeds, scenes) success grid of a (task, mode, delay) and its evaluations; None until every seed's
    evaluation is in."""
    runs = [evals.get(cell(task, smoothing, delay, seed)) for seed in plan["seeds"]]
    if any(r is None for r in runs):
        return None
    grid = [[int(e["success"]) for e in sorted(r["episodes"], key=lambda e: e["seed"])] for r in runs]
    return grid, runs


def summarise(evals: dict, plan: dict) -> dict:
    """{task: {smoothing: {delay: {k, n, rate, interval95, ticks, jerk_boundary, jerk_elsewhere, holds}}}}: over every
    training seed (pending cells left out), the interval the two-way cluster bootstrap over seeds and scenes."""
    table: dict = {}
    for task in plan["tasks"]:
        for s in plan["smoothings"]:
            for d in plan["delays_ms"]:
                got = _grid(evals, plan, task, s, d)
                if got is None:
                    continue
                grid, runs = got
                rate, lo, hi = cluster_bootstrap(grid)
                jerks = [r.get("boundary_jerk") or {} for r in runs]

                def mean(key):
                    values = [j[key] for j in jerks if j.get(key) is not None]
                    return sum(values) / len(values) if values else None

                n = sum(r["n"] for r in runs)
                table.setdefault(task, {}).setdefault(s, {})[d] = {
                    "k": sum(r["successes"] for r in runs),
                    "n": n,
                    "rate": rate,
                    "interval95": [lo, hi],
                    "ticks": runs[0].get("injected_delay_ticks"),
                    "jerk_boundary": mean("at_boundaries"),
                    "jerk_elsewhere": mean("elsewhere"),
                    "holds": sum(e.get("holds", 0) for r in runs for e in r["episodes"]) / max(n, 1),
                }
    return table


def comparisons(evals: dict, plan: dict) -> list[dict]:
    """RTC against each other mode at each delay: the exact paired test over the shared scenes and training seeds,
    Holm-corrected over the table (the family: every comparison it states)."""
    out = []
    for task in plan["tasks"]:
        for d in plan["delays_ms"]:
            rtc = _grid(evals, plan, task, "rtc", d)
            for other in (s for s in plan["smoothings"] if s != "rtc"):
                b = _grid(evals, plan, task, other, d)
                if rtc is None or b is None:
                    continue
                diff, lo, hi = paired_difference(rtc[0], b[0])
                out.append(
                    {
                        "task": task,
                        "delay_ms": d,
                        "vs": other,
                        "n": sum(len(row) for row in rtc[0]),
                        "difference": diff,
                        "interval95": [lo, hi],
                        "p": paired_exact_test(rtc[0], b[0]),
                    }
                )
    holm_family(out, keys=("p",))
    for c in out:
        c.update(verdict=describe_p(c["p"], holm_p=c["p_holm"]), agree=agrees(c["p_holm"], c["interval95"]))
    return out


def write_report(
    plan: dict, record: Path, report: Path, shown_record: str | None = None, command: str = "studies.delay_study"
) -> Path:
    """``delay.md``, ``.json``, ``.png`` from the record alone (``command``: the study that rebuilds it)."""
    evals = recorded(plan, record)
    if not evals:
        raise DSSPError(f"{record} holds no evaluation of this plan; run the study first")
    table = summarise(evals, plan)
    if not table:
        raise DSSPError(
            f"{record} holds no cell with every training seed's evaluation ({plan['seeds']}) yet; run the "
            "study to fill it"
        )
    tests = comparisons(evals, plan)
    scenes = protocol.split_seeds(SPLIT, plan["episodes"])
    budgets = "; ".join(
        f"{task}: {spec['demos']} demonstrations, {spec['steps']} steps" for task, spec in plan["tasks"].items()
    )
    lines = [
        plan.get("title", "# Inference delay: none, temporal ensembling and real-time chunking"),
        "",
        f"Rebuilt from `{shown_record or record}` by `python -m {command} --report-only`. DSSP, preset "
        f"`{plan['preset']}`, trained per task with training seeds {plan['seeds']} ({budgets}), each exported with `--inpainting` at int8; "
        f"{plan['episodes']} closed-loop episodes per cell and seed in the MuJoCo twin on validation seeds "
        f"{scenes[0]}–{scenes[-1]} (the same scenes in every cell; nothing here was tuned). The delay is injected per chunk "
        "in lockstep, in whole 10 Hz ticks (50 and 100 ms are both one tick). Success over every training seed and scene, "
        "with the 95 % two-way cluster-bootstrap interval over seeds and "
        "scenes; jerk = the commanded joints' mean ‖third difference‖ × rate³ "
        "(rad/s³) at the ticks a new chunk took over, and at the other ticks; holds = ticks per episode with no action "
        "(the loop waiting for a chunk, or the safety layer holding). " + plan.get("about", UNEQUAL_COMPUTE),
        "",
    ]
    for task in table:
        per_mode = {s: table[task].get(s, {}) for s in plan["smoothings"]}  # every mode: a missing cell is pending
        lines += [
            f"## {task}",
            "",
            "| delay (ticks) | "
            + " | ".join(f"{s} success" for s in per_mode)
            + " | "
            + " | ".join(f"{s} jerk at boundary / elsewhere | {s} holds" for s in per_mode)
            + " |",
            "|---|" + "---|" * len(per_mode) + "---|---:|" * len(per_mode),
        ]
        for d in plan["delays_ms"]:
            rows = [per_mode[s].get(d) for s in per_mode]
            ticks = next((r["ticks"] for r in rows if r is not None), None)
            success = [
                "pending"
                if r is None
                else f"{100 * r['rate']:.0f} % ({r['k']}/{r['n']}; {100 * r['interval95'][0]:.0f}–{100 * r['interval95'][1]:.0f})"
                for r in rows
            ]
            jerk = []
            for r in rows:
                if r is None:
                    jerk += ["-", "-"]
                    continue
                b, e = r["jerk_boundary"], r["jerk_elsewhere"]
                shown = (
                    "-" if b is None else f"{b:.0f} / " + ("– (every tick a new chunk)" if e is None else f"{e:.0f}")
                )
                jerk += [shown, f"{r['holds']:.1f}"]
            lines.append(f"| {d} ms ({ticks}) | " + " | ".join(success) + " | " + " | ".join(jerk) + " |")
        lines.append("")
    lines += [
        "## Real-time chunking against the other modes (paired over the shared scenes and seeds)",
        "",
        "The exact paired test is over scenes (these trained networks), Holm-corrected over this table's comparisons "
        "and judged on Holm's p; the interval is a two-way cluster bootstrap over training seeds × scenes.",
        "",
        "| task | delay | vs | RTC − other (95 % bootstrap) | exact paired test |",
        "|---|---:|---|---:|---|",
    ]
    for t in tests:
        lo, hi = t["interval95"]
        lines.append(
            f"| {t['task']} | {t['delay_ms']} ms | {t['vs']} | {100 * t['difference']:+.0f} points "
            f"({100 * lo:+.0f} to {100 * hi:+.0f}) | {t['verdict']} |"
        )
    disagree = disagreements(
        {f"{t['task']} at {t['delay_ms']} ms vs {t['vs']}": {**t, "ci": t["interval95"]} for t in tests}, {}
    )
    lines += (
        ["", "Where the paired test and the interval disagree:", "", *[f"- {x}" for x in disagree]] if disagree else []
    )
    lines += ["", f"![success and boundary jerk against the inference delay]({REPORT_NAME}.png)", ""]
    md = write_md_and_json(report, REPORT_NAME, lines, {"plan": plan, "summary": table, "paired_tests": tests})
    plot(table, plan, report / f"{REPORT_NAME}.png")
    return md


def plot(table: dict, plan: dict, path: Path) -> None:
    import matplotlib  # here, not at the top: the study's command starts without it

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tasks = list(table)
    fig, axes = plt.subplots(2, len(tasks), figsize=(5.5 * len(tasks), 7.5), squeeze=False)
    for col, task in enumerate(tasks):
        for s, rows in table[task].items():
            ds = [d for d in plan["delays_ms"] if d in rows]
            rates = [100 * rows[d]["rate"] for d in ds]
            lo = [100 * (rows[d]["rate"] - rows[d]["interval95"][0]) for d in ds]
            hi = [100 * (rows[d]["interval95"][1] - rows[d]["rate"]) for d in ds]
            axes[0][col].errorbar(ds, rates, yerr=[lo, hi], marker="o", capsize=3, label=s)
            axes[1][col].plot(
                ds,
                [rows[d]["jerk_boundary"] if rows[d]["jerk_boundary"] is not None else float("nan") for d in ds],
                marker="o",
                label=s,
            )
        axes[0][col].set(
            title=f"{task}: success (95 % cluster bootstrap)",
            xlabel="injected delay per chunk (ms)",
            ylabel="success %",
            ylim=(0, 105),
        )
        axes[1][col].set(
            title=f"{task}: commanded jerk at chunk boundaries",
            xlabel="injected delay per chunk (ms)",
            ylabel="rad/s³",
            ylim=(0, None),
        )
        for ax in (axes[0][col], axes[1][col]):
            ax.set_xticks(plan["delays_ms"])
            ax.legend(fontsize=8)
    fig.tight_layout()
    write_output_figure(path, fig, force=True, flag="--report")


def readme_table(record: Path, plan: dict = PLAN) -> str:
    """The README's ``delay`` block: success per mode at each delay, per task."""
    table = summarise(recorded(plan, record), plan)
    lines = [
        f"| task, mode ({len(plan['seeds'])} training seeds × {plan['episodes']} validation scenes) | "
        + " | ".join(f"{d} ms" for d in plan["delays_ms"])
        + " |",
        "|---|" + "---:|" * len(plan["delays_ms"]),
    ]
    for task, per_mode in table.items():
        for s, rows in per_mode.items():
            lines.append(
                f"| {task}, {s} | "
                + " | ".join(
                    "pending" if rows.get(d) is None else f"{100 * rows[d]['rate']:.0f} %" for d in plan["delays_ms"]
                )
                + " |"
            )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    return study_main(argv, "delay_study", __doc__, PLAN, QUICK_PLAN, SPLIT, stages, write_report)


if __name__ == "__main__":
    sys.exit(main())

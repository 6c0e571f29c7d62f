"""The simulation study: DSSP against the reactive baseline on the memory tasks, the ablations, and the
robustness test.

    python -m dssp_sim.experiment [--work runs/sim_experiment] [--report reports/sim] [--tasks T ...] [--quick] [--force]

For each task: collect expert demonstrations; train DSSP and the reactive baseline (the same code with
``--no-history``: no history encoder, the denoiser sees only the N most recent state tokens — the
"short window"), same data, preset, budget and seed; export both; evaluate each in closed loop through
the robot's chain on the same unseen episode seeds. Then the ablations (paper Table 5's columns and Table 3's
history window) on the ablation tasks, each a variant of DSSP trained and evaluated the same way; and the
paper's Table 4 test: Gaussian noise on the N most recent state tokens at inference, DSSP (full history)
against the T_h = 10 window ("w/o full history") and the reactive baseline, σ also as a multiple of the
tokens' own RMS (measured in each evaluation). The Transformer history encoder of Table 3 is not in the
study: it does not export (over the full history its state grows).

Every stage writes its output under ``--work`` and is skipped when that output exists, so an interrupted
study resumes where it stopped, and ``--tasks`` splits it across processes or machines sharing ``--work``
(``--seeds`` splits a task's models by training seed; a last run without either finds every stage done and writes
the whole report). Every finished evaluation
and stage time is also kept in the report's record (``--report``/record: evals/NAME.json, seconds/STAGE.seconds,
a few kB each, committed with the report), so a machine without the work directory resumes from the record:
a model whose evaluations are all recorded is not trained again, and ``--report-only`` writes the report from
the record alone, the cells not yet run marked as pending. The report — ``REPORT_NAME.md`` (tables), ``.png``
(plot) and ``.json`` (every figure) — is written to ``--report``. The plan is data (:data:`PLAN`, :data:`QUICK_PLAN`).

Outputs (:mod:`dssp_data.output_guard`): ``--work`` must be new, empty or a work directory of this study
(marked ``.dssp-output.json``), which is continued; anything else is refused before any stage runs. The
report's three files are written beside whatever else ``--report`` holds; existing ones are replaced only
with ``--force``, checked before the study starts.
"""

from __future__ import annotations

import functools
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

from dssp_sim.evaluate import wilson_interval
from dssp_data.files import atomic_write_text
from dssp_data.cli_runner import ArgumentParser
from dssp_data.errors import DSSPError
from dssp_data.output_guard import (
    OutputKind,
    check_output_files,
    claim_dir,
    write_output_figure,
    write_output_text,
)

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
    "robustness": {"task": "tap", "seed": 0, "variants": ["dssp", "window10", "reactive"],
                   "sigmas": [0.05, 0.10, 0.15, 0.3, 0.5, 1.0, 2.0]},
    "export_flags": [],  # parity is checked on every export of the study
}
QUICK_PLAN = {**PLAN, "steps": {"tap": 20}, "demos": {"tap": 3}, "seeds": {"tap": [0]}, "eval_episodes": 1,
              "export_flags": ["--skip-verify", "--quantize", "none"],  # the export tests prove parity and quantize; this checks the plumbing
              "ablations": {"window3": ["--history-window", "3"]}, "ablation_seeds": {"tap": [0]},
              "robustness": {"task": "tap", "seed": 0, "variants": ["dssp", "window3", "reactive"], "sigmas": [0.1]}}
WORK_DIR = OutputKind("a study work directory", "python -m dssp_sim.experiment",
                      entries=("data", "runs", "models", "evals", "logs"), signature=lambda p: (p / "logs").is_dir())
"""``--work``: data/, runs/, models/, evals/, logs/ (continued by the next run; older ones are recognised by logs/)."""
REPORT_SUFFIXES = (".md", ".json", ".png")
RECORD_DIR = "record"
"""Under ``--report``: evals/NAME.json and seconds/STAGE.seconds of every finished stage (see the module's docstring)."""
VARIANT_LABELS = {
    "dssp": "DSSP (full history)", "reactive": "reactive baseline (short window: N recent states)",
    "no_timestep_decoupling": "w/o timestep decoupling", "no_recent_states": "w/o recent states",
    "no_dynamics_loss": "w/o dynamics loss", "transformer_denoiser": "w/ Transformer denoiser",
    "window10": "w/o full history (window T_h = 10)", "window3": "window T_h = 3",
}
# Table 5's rows: the main variants under the paper's names, then the ablations.
TABLE5_LABELS = {"dssp": "full (DSSP)", "reactive": "w/o history (reactive baseline)"}


def _run(cmd: list[str], log: Path) -> None:
    """Run one stage as its own process, its output in ``log``; a failure stops the study with that log."""
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "w") as f:
        code = subprocess.call(cmd, stdout=f, stderr=subprocess.STDOUT, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    if code != 0:
        tail = log.read_text().strip().splitlines()[-3:]
        raise SystemExit(f"error: {' '.join(cmd[:4])} ... failed (exit {code}); see {log}: {' | '.join(tail)}")


def stage(done: Path, what: str, cmd: list[str], log: Path, record: Path | None = None) -> None:
    """Run ``cmd`` unless it completed before: ``done`` exists and so does the stage's time (written only when
    its command succeeded, so a stage stopped halfway is run again). ``record``: keep the stage's time there too."""
    if done.exists() and log.with_suffix(".seconds").exists():
        print(f"  {what}: done before ({done})")
    else:
        t0 = time.perf_counter()
        _run(cmd, log)
        seconds = time.perf_counter() - t0
        atomic_write_text(log.with_suffix(".seconds"), f"{seconds:.1f}\n")  # summed by the report
        print(f"  {what}: {seconds:.0f} s")
    keep(record, log.with_suffix(".seconds"), "seconds")


def keep(record: Path | None, path: Path, kind: str) -> None:
    """Copy a finished stage's file (its time: ``kind`` "seconds"; its evaluation: "evals") into ``record``."""
    if record is not None:
        (record / kind).mkdir(parents=True, exist_ok=True)
        if not (record / kind / path.name).is_file() or (record / kind / path.name).read_text() != path.read_text():
            atomic_write_text(record / kind / path.name, path.read_text())


def recorded(record: Path | None, name: str) -> dict | None:
    """The evaluation ``name`` kept in ``record``, or None."""
    path = record / "evals" / f"{name}.json" if record is not None else None
    return json.loads(path.read_text()) if path is not None and path.is_file() else None


def train_command(data: Path, run_dir: Path, plan: dict, task: str, seed: int, flags: list[str], log: Path) -> list[str]:
    """The training stage's command: a new run, or ``--resume`` of one stopped halfway (its checkpoint is there,
    the stage's time is not), so an interrupted study loses at most the steps since the last checkpoint."""
    if (run_dir / "checkpoint").is_dir() and not log.with_suffix(".seconds").exists():
        return [sys.executable, "-m", "dssp_train.cli.train", "--data", str(data), "--out", str(run_dir), "--resume", "--no-progress"]
    return [sys.executable, "-m", "dssp_train.cli.train", "--data", str(data), "--out", str(run_dir), "--preset", plan["preset"],
            "--steps", str(plan["steps"][task]), "--seed", str(seed), "--no-progress", "--force", *flags]


def stage_seconds(work: Path, record: Path | None = None) -> float:
    """Compute time of every stage of the study so far, resumed and parallel runs included: the stage times of
    ``work`` and of ``record`` (kept there from other machines), each stage counted once."""
    files = {f.name: f for d in (record / "seconds" if record else None, work / "logs") if d and d.is_dir()
             for f in d.glob("*.seconds")}
    return sum(float(f.read_text()) for f in files.values())


def collect_stage(work: Path, task: str, n_demos: int, record: Path | None = None) -> Path:
    """The study's ``n_demos`` demonstrations of ``task`` in ``work/data`` (collected unless done before; a
    collection stopped halfway is collected again, not appended to): the dataset's path."""
    data, log = work / "data" / f"{task}.zarr", work / "logs" / f"collect_{task}.log"
    if data.exists() and not log.with_suffix(".seconds").exists():
        shutil.rmtree(data)  # the study's own partial dataset
    stage(data / "meta", f"collect {n_demos} demos", [sys.executable, "-m", "dssp_sim.sim_cli", "collect", "--task", task,
          "--episodes", str(n_demos), "--out", str(data), "--no-progress"], log, record)
    return data


def study_tasks(work: Path, plan: dict, tasks: list[str] | None, kind: OutputKind, others: tuple[str, ...] = (),
                record: Path | None = None):
    """Check ``tasks`` (names of the plan's tasks, or of ``others``), claim ``work`` for a study of ``kind``, and yield
    (task, dataset) for each of the plan's tasks to run (all without ``tasks``): ``dataset()`` collects the task's
    demonstrations on its first call (none when every stage that needs them is recorded) and returns their path."""
    unknown = sorted(set(tasks or []) - set(plan["demos"]) - set(others))
    if unknown:
        raise SystemExit(f"error: unknown task(s) {unknown}; the plan has {[*plan['demos'], *others]}")
    claim_dir(work, kind=kind, flag="--work", resume=True)
    for task, n_demos in plan["demos"].items():
        if not tasks or task in tasks:
            print(f"{task}:")
            yield task, functools.cache(functools.partial(collect_stage, work, task, n_demos, record))


def train_stage(work: Path, data: Path, run_dir: Path, plan: dict, task: str, seed: int, flags: list[str], what: str,
                name: str | None = None, record: Path | None = None) -> None:
    """Train ``run_dir`` (the plan's preset and steps for ``task``) unless done before; resumed if stopped halfway.
    Its log is ``work/logs/train_{name}.log`` (default: the run's name)."""
    log = work / "logs" / f"train_{name or run_dir.name}.log"
    stage(run_dir / "checkpoint", what, train_command(data, run_dir, plan, task, seed, flags, log), log, record)


def eval_name(name: str, sigma: float) -> str:
    """An evaluation's name: the model's, with the noise level when there is noise."""
    return f"{name}_noise{sigma:g}" if sigma else name


def model_runs(plan: dict, task: str) -> list[tuple[int, str, list[str], list[float]]]:
    """(seed, variant, training flags, noise levels it is evaluated at) of every model of ``task``, seed by seed: the
    main variants on the task's seeds, the ablations on its ablation seeds; σ = 0 for all, and the robustness test's
    σs for its models."""
    rob = plan["robustness"]
    seeds = dict.fromkeys([*plan["seeds"][task], *plan["ablation_seeds"].get(task, [])])
    return [(seed, variant, flags, [0.0, *(rob["sigmas"] if (task, seed) == (rob["task"], rob["seed"]) and variant in rob["variants"] else [])])
            for seed in seeds for variant, flags in [
                *(plan["variants"].items() if seed in plan["seeds"][task] else []),
                *(plan["ablations"].items() if seed in plan["ablation_seeds"].get(task, []) else [])]]


def run_study(work: Path, plan: dict, threads: int | None = None, tasks: list[str] | None = None,
              record: Path | None = None, seeds: list[int] | None = None) -> dict:
    """Run (or resume) the study's stages for ``tasks`` (default: every task of the plan) and training ``seeds``
    (default: all). A model whose evaluations are all in ``record`` is neither trained nor exported again."""
    py = sys.executable
    results: dict = {"plan": plan, "evals": {}, "robustness": {}}
    for task, dataset in study_tasks(work, plan, tasks, WORK_DIR, record=record):
        for seed, variant, flags, sigmas in model_runs(plan, task):
            if seeds is not None and seed not in seeds:
                continue
            name = f"{task}_{variant}_s{seed}"
            run_dir, model_dir = work / "runs" / name, work / "models" / name
            if not all(recorded(record, eval_name(name, sigma)) for sigma in sigmas):
                train_stage(work, dataset(), run_dir, plan, task, seed, flags, f"train {variant} seed {seed}", record=record)
                stage(model_dir / "dssp_model.json", f"export {variant} seed {seed}", [py, "-m", "export.to_onnx", str(run_dir),
                       "-o", str(model_dir), "--force", *plan.get("export_flags", [])], work / "logs" / f"export_{name}.log", record)
            for sigma in sigmas:
                results["robustness" if sigma else "evals"][eval_name(name, sigma)] = _evaluate(
                    work, record, model_dir, task, plan, name, sigma, threads)
    return results


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


def _evaluate(work: Path, record: Path | None, model_dir: Path, task: str, plan: dict, name: str, sigma: float,
              threads: int | None) -> dict:
    name = eval_name(name, sigma)
    kept = recorded(record, name)
    if kept is not None:
        print(f"  eval {name}: recorded")
        return kept
    out = work / "evals" / f"{name}.json"
    cmd = [sys.executable, "-m", "dssp_sim.sim_cli", "eval", "--model", str(model_dir), "--task", task, "--episodes",
           str(plan["eval_episodes"]), "--seed", str(plan["eval_seed"]), "--noise", str(sigma), "--json", str(out), "--no-progress"]
    if threads:
        cmd += ["--threads", str(threads)]
    stage(out, f"eval {name}", cmd, work / "logs" / f"eval_{name}.log", record)
    keep(record, out, "evals")
    return json.loads(out.read_text())


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
    ``pending``: the evaluations not run yet (a report from the record, ``--report-only``), listed and marked "pending"."""
    check_output_files(report_files(report_dir), force=force, flag="--report")
    table = summarise(results)
    plan = results["plan"]
    lines = [
        "# Memory tasks in simulation: DSSP against the reactive baseline, the ablations, robustness",
        "",
        f"Produced by `python -m dssp_sim.experiment` ({seconds / 60:.0f} min of stage time on this 2-core machine, "
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
            lines.append(f"| {task} | {VARIANT_LABELS.get(variant, variant)} | {pct(row['k'], row['n'])} | {seeds} | {reasons} |")
    ablation_tasks = [t for t in plan["ablation_seeds"] if t in table and any(v in table[t] for v in plan["ablations"])]
    if ablation_tasks:
        seeds = ", ".join(f"`{t}` seeds {plan['ablation_seeds'][t]}" for t in ablation_tasks)
        lines += ["", f"Ablations (paper Table 5, and Table 3's window): each row one change to DSSP, trained and evaluated "
                  f"as above ({seeds}; rows pooled over those seeds only). The Transformer history encoder of Table 3 is "
                  "not here: it does not export (over the full history its state grows).", "",
                  "| model | " + " | ".join(f"`{t}`" for t in ablation_tasks) + " |", "|---|" + "---|" * len(ablation_tasks)]
        for variant in [*plan["variants"], *plan["ablations"]]:
            cells = []
            for task in ablation_tasks:
                names = [f"{task}_{variant}_s{seed}" for seed in plan["ablation_seeds"][task]]
                rs = [results["evals"][n] for n in names if n in results["evals"]]
                cells.append(pct(sum(r["successes"] for r in rs), sum(r["n"] for r in rs)) + ("" if len(rs) == len(names) else
                             f" (seeds so far: {len(rs)} of {len(names)})") if rs else "pending")
            lines.append(f"| {TABLE5_LABELS.get(variant, VARIANT_LABELS.get(variant, variant))} | " + " | ".join(cells) + " |")
    if results["robustness"]:
        rob = plan["robustness"]
        rms = _z_rms(results, rob)
        lines += ["", f"Robustness (paper Table 4): Gaussian noise σ on the N most recent state tokens at inference, "
                  f"task `{rob['task']}`, training seed {rob['seed']}. σ is in the tokens' units"
                  + (f"; their RMS per element is {rms:.2f} (DSSP, noise-free), so σ / RMS is in the second column." if rms else "."),
                  "", "| σ | σ / RMS | " + " | ".join(VARIANT_LABELS.get(v, v) for v in rob["variants"]) + " |",
                  "|---:|---:|" + "---|" * len(rob["variants"])]
        for sigma in [0.0, *rob["sigmas"]]:
            cells = [pct(r["successes"], r["n"]) if r else "pending" for r in (_rob_result(results, rob, v, sigma) for v in rob["variants"])]
            lines.append(f"| {sigma:g} | {sigma / rms:.2f} | " if rms else f"| {sigma:g} | — | ")
            lines[-1] += " | ".join(cells) + " |"
    if pending:
        lines += ["", f"**Partial report**: {len(pending)} evaluation(s) of the plan are pending (not run yet): "
                  + ", ".join(f"`{n}`" for n in pending) + ". Rows pool the seeds run so far."]
    lines += ["", f"![success rates]({REPORT_NAME}.png)", ""]
    md, js, png = report_files(report_dir)
    write_output_text(md, "\n".join(lines), force=force, flag="--report")
    write_output_text(js, json.dumps({"summary": table, **results, "pending": list(pending)}, indent=2) + "\n",
                      force=force, flag="--report")
    _plot(results, table, png, force)
    return md


def _bars(ax, groups: list[str], series: list[tuple[str, list[tuple[int, int]]]], title: str) -> None:
    """Grouped bars of success % with Wilson intervals: ``series`` [(label, [(k, n) per group])]."""
    import numpy as np

    width = 0.8 / max(len(series), 1)
    for i, (label, counts) in enumerate(series):
        rates, errs = [], [[], []]
        for k, n in counts:
            p = k / max(n, 1)
            lo, hi = wilson_interval(k, n)
            rates.append(100 * p)
            errs[0].append(100 * (p - lo))
            errs[1].append(100 * (hi - p))
        ax.bar(np.arange(len(groups)) + (i - (len(series) - 1) / 2) * width, rates, width, yerr=errs, capsize=3, label=label)
    ax.set(xticks=np.arange(len(groups)), xticklabels=groups, ylabel="success %", ylim=(0, 105), title=title)
    ax.legend(fontsize=7)


def _plot(results: dict, table: dict, path: Path, force: bool = False) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plan = results["plan"]
    tasks = list(table)
    ablation_tasks = [t for t in plan["ablation_seeds"] if t in table and any(v in table[t] for v in plan["ablations"])]
    panels = 1 + bool(ablation_tasks) + bool(results["robustness"])
    fig, axes = plt.subplots(1, panels, figsize=(5.5 * panels, 4), squeeze=False)
    axes = list(axes[0])
    counts = lambda task, v: (table[task].get(v, {"k": 0})["k"], table[task].get(v, {"n": 0})["n"])  # noqa: E731
    _bars(axes.pop(0), tasks, [(VARIANT_LABELS.get(v, v), [counts(t, v) for t in tasks]) for v in plan["variants"]],
          "Closed-loop success (95 % Wilson)")
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
            ax.plot([s / rms for s, _ in done], [100 * r["success_rate"] for _, r in done], "o-", label=VARIANT_LABELS.get(variant, variant))
        ax.set(xlabel="σ / RMS of the recent state tokens", ylabel="success %", ylim=(0, 105), title=f"Robustness ({rob['task']})")
        ax.legend(fontsize=7)
    fig.tight_layout()
    write_output_figure(path, fig, force=force, flag="--report")


def main(argv: list[str] | None = None) -> int:
    p = ArgumentParser(prog="python -m dssp_sim.experiment", description=__doc__.split("\n\n")[0])
    p.add_argument("--work", type=Path, default=Path("runs/sim_experiment"), help="datasets, runs, models, evaluations")
    p.add_argument("--report", type=Path, default=Path("reports/sim"), help="where the report goes")
    p.add_argument("--quick", action="store_true", help="a tiny plan (tests): 3 demos, 20 steps, 1 episode")
    p.add_argument("--threads", type=int, help="ONNX Runtime threads for the evaluations")
    p.add_argument("--tasks", nargs="+", metavar="TASK", help="run only these tasks' stages (default: all, then the report)")
    p.add_argument("--seeds", nargs="+", type=int, metavar="SEED", help="run only the models of these training seeds "
                   "(with --tasks: split one task's models across processes; no report)")
    p.add_argument("--force", action="store_true", help="replace the report's files if they exist")
    p.add_argument("--report-only", action="store_true", help="run no stage: write the report from the record "
                   f"(--report/{RECORD_DIR}), the evaluations not run yet listed as pending")
    args = p.parse_args(argv)
    plan = QUICK_PLAN if args.quick else PLAN
    partial = bool(args.tasks) and set(args.tasks) != set(plan["demos"]) or args.seeds is not None
    record = args.report / RECORD_DIR
    known = {seed for t in plan["demos"] for seed in [*plan["seeds"][t], *plan["ablation_seeds"].get(t, [])]}
    if args.seeds is not None and set(args.seeds) - known:
        p.error(f"--seeds {sorted(set(args.seeds) - known)}: the plan trains seeds {sorted(known)}")
    if args.report_only and partial:
        p.error("--report-only writes the whole report from the record; drop --tasks and --seeds")

    def _main() -> int:
        if not partial:  # before any stage: a report that may not be replaced stops the study now
            check_output_files(report_files(args.report), force=args.force, flag="--report")
        if args.report_only:
            results, pending = recorded_results(plan, record)
            if not results["evals"]:
                raise DSSPError(f"{record} holds no evaluation of this plan; run the study first (without --report-only)")
            md = write_report(results, args.report, stage_seconds(args.work, record), force=args.force, pending=pending)
            print(md.read_text())
            return 0
        results = run_study(args.work, plan, args.threads, args.tasks, record, args.seeds)
        if partial:
            print(f"stages of {args.tasks or 'every task'}{f' seeds {args.seeds}' if args.seeds else ''} done (kept in {record}); "
                  "run without --tasks and --seeds for the report")
            return 0
        md = write_report(results, args.report, stage_seconds(args.work, record), force=args.force)
        print(md.read_text())
        return 0

    from dssp_data.cli_runner import run_cli

    return run_cli(_main)


if __name__ == "__main__":
    sys.exit(main())

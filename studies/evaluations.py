"""Running a study's stages and keeping what its evaluations found in the study's record.

A record keeps, of each closed-loop evaluation (``dssp-sim eval --json``), what a report needs (:func:`compact`):
its counts, failure reasons, memory decisions, graphs and latency, the state-token noise and the tokens' RMS, and
each episode's scene seed, outcome, steps and memory decision; of a latency profile (``dssp-profile --json``), its
graphs and latency. The per-tick details stay in the work folder. A study whose report sums its compute time also
keeps each finished stage's seconds (``seconds/NAME.seconds``). A report rebuilt from the record is written by
:func:`write_md_and_json`.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

from dssp_core.cli_runner import ArgumentParser, run_cli
from dssp_core.files import atomic_write_text
from studies import protocol
from studies.runner import Runner, Stage

KEPT = (
    "model",  # the model it scored (dssp_sim.evaluate.scored_model)
    "task",
    "n",
    "successes",
    "failure_reasons",
    "decisions",
    "precision",
    "kernel",
    "latency_ms",
    "state_token_noise",
    "z_rms",
    "smoothing",
    "injected_delay_ms",
    "injected_delay_ticks",
    "rtc_delay_ticks",
    "limit_excludes_holds",
    "boundary_jerk",
)


def compact(result: dict) -> dict:
    """What the record keeps of one evaluation, or of one profile (it has no episodes; module docstring)."""
    kept = {k: result[k] for k in KEPT if k in result}
    if "episodes" in result:
        kept["episodes"] = [
            {
                "seed": e["seed"],
                "success": e["success"],
                "reason": e["reason"],
                "steps": e["steps"],
                "decision": e.get("decision", {}),
                **({"holds": e["holds"]} if "holds" in e else {}),
            }
            for e in result["episodes"]
        ]
    return kept


def run_and_keep(
    work: Path, record: Path, stage_list: list[Stage], workers: int, what: str, seconds: bool = False
) -> None:
    """Run the stages in ``work`` (``workers`` at a time) and keep each finished stage's evaluations (its ``outputs``)
    in ``record`` at the same relative paths as soon as it finishes, and again at the end for any finished before
    (a resumed run) — also when a stage fails or the study is stopped. ``seconds``: keep each finished stage's seconds
    too (``record/seconds/NAME.seconds``, from its done marker)."""
    (work / "evals").mkdir(parents=True, exist_ok=True)
    runner = Runner(work, workers=workers)
    code = protocol.code_commit()  # each evaluation kept names the code that made it, beside the model it scored

    def keep(s: Stage) -> None:
        if not runner.done(s.name):
            return
        for output in s.outputs:
            if (work / output).is_file():
                (record / output).parent.mkdir(parents=True, exist_ok=True)
                kept = {**compact(json.loads((work / output).read_text())), "code_commit": code}
                atomic_write_text(record / output, json.dumps(kept, indent=1) + "\n")
        if seconds:
            (record / "seconds").mkdir(parents=True, exist_ok=True)
            atomic_write_text(
                record / "seconds" / f"{s.name}.seconds",
                f"{json.loads(runner.marker(s.name).read_text())['seconds']:.1f}\n",
            )

    print(f"{len(stage_list)} stage(s) for {what}, {workers} at a time")
    try:
        runner.run(stage_list, on_done=keep)
    finally:
        for s in stage_list:
            keep(s)


def write_md_and_json(report: Path, name: str, lines: list[str], figures: dict) -> Path:
    """A report rebuilt from its record: ``report/NAME.md`` (``lines``) and ``report/NAME.json`` (``figures``, keys
    sorted); returns the ``.md``."""
    report.mkdir(parents=True, exist_ok=True)
    md = report / f"{name}.md"
    atomic_write_text(md, "\n".join(lines))
    atomic_write_text(report / f"{name}.json", json.dumps(figures, indent=1, sort_keys=True) + "\n")
    return md


def study_main(
    argv: list[str] | None,
    name: str,
    doc: str,
    plan: dict,
    quick_plan: dict,
    split: str,
    stages: Callable[[dict, list[str], Path], list[Stage]],
    write_report: Callable[[dict, Path, Path], Path],
) -> int:
    """The command of a study whose stages evaluate on one ``split`` and whose report is rebuilt from its record
    (``python -m studies.NAME [--tasks T ...] [--workers 2] [--work runs/NAME] [--report reports/NAME]
    [--report-only] [--quick]``): its provenance noted, its stages run and their evaluations kept
    (:func:`run_and_keep`), then the report written and printed."""
    folder = name.removesuffix("_study")
    p = ArgumentParser(prog=f"python -m studies.{name}", description=doc.split("\n\n")[0])
    p.add_argument("--tasks", nargs="+", metavar="TASK", help="default: every task of the plan")
    p.add_argument("--workers", type=int, default=2, help="stages side by side, one thread each (default 2)")
    p.add_argument(
        "--work", type=Path, default=Path(f"runs/{folder}"), help="datasets, runs, models, evaluations, logs"
    )
    p.add_argument("--report", type=Path, default=Path(f"reports/{folder}"), help="the report and its record")
    p.add_argument("--report-only", action="store_true", help="run nothing: rebuild the report from the record")
    p.add_argument("--quick", action="store_true", help="a tiny plan (tests)")
    args = p.parse_args(argv)
    plan = quick_plan if args.quick else plan
    tasks = args.tasks or list(plan["tasks"])
    if set(tasks) - set(plan["tasks"]):
        p.error(
            f"--tasks: {', '.join(sorted(set(tasks) - set(plan['tasks'])))} not in the plan ({', '.join(plan['tasks'])})"
        )

    def _main() -> int:
        record = args.report / "record"
        if not args.report_only:
            protocol.note_provenance(record, plan, split, allow_changes=args.quick)
            run_and_keep(args.work, record, stages(plan, tasks, record), args.workers, ", ".join(tasks))
        print(write_report(plan, record, args.report).read_text())
        return 0

    return run_cli(_main)

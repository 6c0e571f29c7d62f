"""Running a study's stages and keeping what its evaluations found in the study's record.

A record keeps, of each closed-loop evaluation (``dssp-sim eval --json``), what a report needs (:func:`compact`):
its counts, failure reasons, memory decisions, graphs and latency, the state-token noise and the tokens' RMS, and
each episode's scene seed, outcome, steps and memory decision; of a latency profile (``dssp-profile --json``), its
graphs and latency. The per-tick details stay in the work folder. A study whose report sums its compute time also
keeps each finished stage's seconds (``seconds/NAME.seconds``).
"""

from __future__ import annotations

import json
from pathlib import Path

from dssp_core.files import atomic_write_text
from studies.runner import Runner, Stage

KEPT = ("task", "n", "successes", "failure_reasons", "decisions", "precision", "kernel", "latency_ms",
        "state_token_noise", "z_rms", "smoothing", "injected_delay_ms", "injected_delay_ticks", "rtc_delay_ticks",
        "boundary_jerk")


def compact(result: dict) -> dict:
    """What the record keeps of one evaluation, or of one profile (it has no episodes; module docstring)."""
    kept = {k: result[k] for k in KEPT if k in result}
    if "episodes" in result:
        kept["episodes"] = [{"seed": e["seed"], "success": e["success"], "reason": e["reason"], "steps": e["steps"],
                             "decision": e.get("decision", {}), **({"holds": e["holds"]} if "holds" in e else {})}
                            for e in result["episodes"]]
    return kept


def run_and_keep(work: Path, record: Path, stage_list: list[Stage], workers: int, what: str, seconds: bool = False) -> None:
    """Run the stages in ``work`` (``workers`` at a time) and keep every finished stage's evaluations (its
    ``outputs``) in ``record`` at the same relative paths — also when a stage fails or the study is stopped.
    ``seconds``: keep each finished stage's seconds too (``record/seconds/NAME.seconds``, from its done marker)."""
    (work / "evals").mkdir(parents=True, exist_ok=True)
    runner = Runner(work, workers=workers)
    print(f"{len(stage_list)} stage(s) for {what}, {workers} at a time")
    try:
        runner.run(stage_list)
    finally:
        for s in stage_list:
            for output in s.outputs:
                if runner.done(s.name) and (work / output).is_file():
                    (record / output).parent.mkdir(parents=True, exist_ok=True)
                    atomic_write_text(record / output, json.dumps(compact(json.loads((work / output).read_text())), indent=1) + "\n")
            if seconds and runner.done(s.name):
                (record / "seconds").mkdir(parents=True, exist_ok=True)
                atomic_write_text(record / "seconds" / f"{s.name}.seconds",
                                  f"{json.loads(runner.marker(s.name).read_text())['seconds']:.1f}\n")

"""The Quick-start demo: the whole chain on the embedded simulation, no hardware.

    dssp-demo --out runs/demo [--steps 3000] [--demos 50] [--episodes 20] [--force]

1. collect expert demonstrations of ``tap`` (press a spring-loaded button exactly three times, return
   home: after each press the scene looks the same, so counting needs memory);
2. train DSSP (``sim`` preset) and the reactive baseline (the same code without the history encoder),
   same data, budget and seed;
3. export both to model directories (ONNX, parity checked);
4. evaluate each in closed loop through the robot's chain (simulated depth → RealSense software device →
   point-cloud pipeline → ONNX runtime → safety → Piper CAN → MuJoCo arm) on unseen episodes;
5. print the success rates (95 % Wilson intervals) and DSSP's control-loop latency table.

The stages run on :class:`studies.runner.Runner`, the two models side by side, each stage its own process on one
thread (``dssp-train``, ``python -m export.to_onnx``, ``dssp-sim eval``); their output is shown line by line behind
``[STAGE]`` and kept in ``logs/``. A stage that fails stops the demo with one line naming it and a copy of its log
(outside ``--out``); Ctrl-C stops the stages too. ``results.json`` in ``--out`` holds every figure. ``--out``
must be new or empty; a previous demo there is replaced only with ``--force`` (moved aside while the new one runs,
deleted when it is complete, put back if it fails); anything else there is never touched
(:mod:`dssp_core.output_guard`).
"""

from __future__ import annotations

import json
import os
import shutil
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

from dssp_core import machine
from dssp_core.cli_runner import ArgumentParser, run_cli
from dssp_core.errors import DSSPError
from dssp_core.files import atomic_write_text
from dssp_core.output_guard import OutputDir, OutputKind
from dssp_sim import sim_cli
from dssp_sim.evaluate import print_latency
from dssp_sim.sim_cli import positive_int
from dssp_train.cli import train
from studies.runner import Runner, Stage, StageFailed

TASK = "tap"
VARIANTS = {"dssp": ("DSSP (full history)", []), "reactive": ("reactive baseline (no history)", ["--no-history"])}
DEMO_DIR = OutputKind(
    "a demo directory",
    "dssp-demo",
    entries=(
        f"{TASK}.zarr",
        *VARIANTS,
        *(f"{name}_model" for name in VARIANTS),
        "evals",
        "logs",
        "done",
        "results.json",
    ),
)
"""``dssp-demo --out``: the dataset, both runs and model directories, their evaluations, logs, the stages' done
markers, results.json."""


def stages(steps: int, demos: int, episodes: int, seed: int) -> list[Stage]:
    """Collect, then for each model: train → export → evaluate (paths relative to ``--out``)."""
    from export import to_onnx  # deferred: loads torch, which a stage's process imports after setting its threads

    data = f"{TASK}.zarr"
    out = [
        Stage(
            "collect",
            sim_cli.main,
            ("collect", "--task", TASK, "--episodes", str(demos), "--out", data, "--seed", str(seed), "--no-progress"),
        )
    ]
    for name, (_, flags) in VARIANTS.items():
        model = f"{name}_model"
        evaluate = ("eval", "--model", model, "--task", TASK, "--episodes", str(episodes), "--seed", str(1000 + seed))
        out += [
            Stage(
                f"train_{name}",
                train.main,
                ("--data", data, "--out", name, "--preset", "sim", "--steps", str(steps), "--seed", str(seed), *flags),
                after=("collect",),
            ),
            Stage(f"export_{name}", to_onnx.main, (name, "-o", model, "--threads", "1"), after=(f"train_{name}",)),
            Stage(
                f"eval_{name}",
                sim_cli.main,
                (*evaluate, "--threads", "1", "--json", f"evals/{name}.json"),
                after=(f"export_{name}",),
            ),
        ]
    return out


def run_demo(
    out: Path, steps: int = 3000, demos: int = 50, episodes: int = 20, seed: int = 0, force: bool = False
) -> dict:
    with OutputDir(out, DEMO_DIR, force=force, staged=False) as target:
        results = _run_demo(Path(out), steps, demos, episodes, seed)
        target.commit()
    return results


def _run_demo(out: Path, steps: int, demos: int, episodes: int, seed: int) -> dict:
    t_start = time.perf_counter()
    print(
        f"collect {demos} expert demonstrations of '{TASK}', then for each model, side by side: train ({steps} steps, "
        f"sim preset) → export (parity checked) → evaluate ({episodes} closed-loop episodes)",
        flush=True,
    )
    (out / "evals").mkdir(exist_ok=True)
    try:
        ran = Runner(out, workers=len(VARIANTS), echo=True, say=lambda line: print(line, flush=True)).run(
            stages(steps, demos, episodes, seed)
        )
    except StageFailed as failed:  # --out goes on failure: keep the log where the message says
        fd, kept = tempfile.mkstemp(prefix=f"dssp-demo-{failed.stage}-", suffix=".log")
        os.close(fd)
        if failed.log.is_file():
            shutil.copyfile(failed.log, kept)
        raise DSSPError(f"{failed.stage} failed (exit {failed.code}); its log: {kept}: {failed.last}") from None
    timings = {f"{name}_s": seconds for name, seconds in ran.items()}
    evals = {name: json.loads((out / "evals" / f"{name}.json").read_text()) for name in VARIANTS}
    timings["total_s"] = time.perf_counter() - t_start
    print(
        f"\nTask '{TASK}', {episodes} unseen episodes each, closed loop through camera → cloud → runtime → safety → CAN → arm:\n"
    )
    print(results_table(evals))
    print("\nDSSP's control loop, every tick of its evaluation (one ONNX Runtime thread):")
    print_latency(evals["dssp"]["latency_ms"])
    print(f"\ntotal {timings['total_s'] / 60:.1f} min; {out / 'results.json'} holds every figure")
    for name, r in evals.items():  # the model directories by their names in --out (the record may move)
        r["model_dir"] = f"{name}_model"
    results = {
        "task": TASK,
        "steps": steps,
        "demos": demos,
        "episodes": episodes,
        "seed": seed,
        "timings": timings,
        "machine": machine.describe(),
        "evals": evals,
    }
    atomic_write_text(out / "results.json", json.dumps(results, indent=2) + "\n")
    return results


def results_table(evals: dict) -> str:
    """The demo's table (Markdown) from its evaluations (``results.json``'s ``evals``): the demo prints it, and the
    README shows it rebuilt from the committed record (``python -m studies.rebuild``)."""
    lines = ["| model | success | 95 % Wilson interval | graphs | failures |", "|---|---:|---|---|---|"]
    for name, r in evals.items():
        lo, hi = r["wilson95"]
        failures = ", ".join(f"{k} × {v}" for k, v in Counter(r["failure_reasons"]).most_common()) or "—"
        graphs = f"{r.get('precision', '?')}, {r.get('kernel', '?')}"
        lines.append(
            f"| {VARIANTS[name][0]} | {r['successes']}/{r['n']} = {100 * r['success_rate']:.0f} % | "
            f"{100 * lo:.0f}–{100 * hi:.0f} % | {graphs} | {failures} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = ArgumentParser(
        prog="dssp-demo",
        description="The whole chain on the simulated Piper: collect, train DSSP and the "
        "reactive baseline, export, evaluate (tap).",
    )
    p.add_argument("--out", type=Path, required=True, help="working directory (new or empty; make demo: runs/demo)")
    p.add_argument("--force", action="store_true", help="replace a previous demo in --out")
    p.add_argument("--steps", type=positive_int, default=3000, help="training steps per model (default 3000)")
    p.add_argument("--demos", type=positive_int, default=50, help="expert demonstrations (default 50)")
    p.add_argument("--episodes", type=positive_int, default=20, help="evaluation episodes per model (default 20)")
    args = p.parse_args(sys.argv[1:] if argv is None else argv)

    def demo() -> int:
        run_demo(args.out, steps=args.steps, demos=args.demos, episodes=args.episodes, force=args.force)
        return 0

    return run_cli(demo)


if __name__ == "__main__":
    sys.exit(main())

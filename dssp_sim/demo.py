"""The Quick-start demo: the whole chain on the embedded simulation, no hardware.

    dssp-sim demo --out runs/demo [--steps 3000] [--demos 50] [--episodes 20]

1. collect expert demonstrations of ``tap`` (press a spring-loaded button exactly three times, return
   home: after each press the scene looks the same, so counting needs memory);
2. train DSSP (``sim`` preset) and the reactive baseline (the same code without the history encoder),
   same data, budget and seed;
3. export both to model directories (ONNX, parity checked);
4. evaluate each in closed loop through the robot's chain (simulated depth → RealSense software device →
   point-cloud pipeline → ONNX runtime → safety → Piper CAN → MuJoCo arm) on unseen episodes;
5. print the success rates (95 % Wilson intervals) and DSSP's control-loop latency table.
``results.json`` in ``--out`` holds every figure. ``--out`` must be new or empty; a previous demo there is
replaced only with ``--force`` (moved aside while the new one runs, deleted when it is complete, put back
if it fails); anything else there is never touched (:mod:`dssp_data.output_guard`).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

from dssp_data.files import atomic_write_text
from dssp_data.errors import DSSPError
from dssp_data.output_guard import OutputDir, OutputKind

TASK = "tap"
VARIANTS = {"dssp": ("DSSP (full history)", []), "reactive": ("reactive baseline (no history)", ["--no-history"])}
DEMO_DIR = OutputKind("a demo directory", "dssp-sim demo",
                      entries=(f"{TASK}.zarr", *VARIANTS, *(f"{name}_model" for name in VARIANTS), "results.json"))
"""``dssp-sim demo --out``: the dataset, both runs and model directories, results.json."""


def run_demo(out: Path, steps: int = 3000, demos: int = 50, episodes: int = 20, seed: int = 0,
             force: bool = False) -> dict:
    with OutputDir(out, DEMO_DIR, force=force, staged=False) as target:
        results = _run_demo(Path(out), steps, demos, episodes, seed)
        target.commit()
    return results


def _run_demo(out: Path, steps: int, demos: int, episodes: int, seed: int) -> dict:
    from dssp_sim.evaluate import print_latency
    from dssp_sim.collect import collect
    from dssp_sim.evaluate import evaluate
    from dssp_train.cli.train import main as train_main
    from export.to_onnx import main as export_main

    t_start = time.perf_counter()
    timings = {}
    print(f"[1/4] collecting {demos} expert demonstrations of '{TASK}'")
    t0 = time.perf_counter()
    result = collect(TASK, demos, out / f"{TASK}.zarr", seed=seed)
    if result.kept < demos:
        raise DSSPError(f"only {result.kept} of {demos} expert episodes succeeded")
    timings["collect_s"] = time.perf_counter() - t0
    evals = {}
    for i, (name, (label, flags)) in enumerate(VARIANTS.items()):
        print(f"[2/4] training {label}: {steps} steps (sim preset)")
        t0 = time.perf_counter()
        code = train_main(["--data", str(out / f"{TASK}.zarr"), "--out", str(out / name), "--preset", "sim",
                           "--steps", str(steps), "--seed", str(seed), *flags])
        if code != 0:
            raise DSSPError(f"training {name} failed (exit {code})")
        timings[f"train_{name}_s"] = time.perf_counter() - t0
        print(f"[3/4] exporting {label}")
        t0 = time.perf_counter()
        code = export_main([str(out / name), "-o", str(out / f"{name}_model")])
        if code != 0:
            raise DSSPError(f"export of {name} failed its parity check (exit {code})")
        timings[f"export_{name}_s"] = time.perf_counter() - t0
        print(f"[4/4] evaluating {label}: {episodes} closed-loop episodes")
        t0 = time.perf_counter()
        evals[name] = evaluate(out / f"{name}_model", TASK, episodes, seed=1000 + seed)
        timings[f"eval_{name}_s"] = time.perf_counter() - t0
    timings["total_s"] = time.perf_counter() - t_start
    print(f"\nTask '{TASK}', {episodes} unseen episodes each, closed loop through camera → cloud → runtime → safety → CAN → arm:\n")
    print("| model | success | 95 % Wilson interval | failures |")
    print("|---|---:|---|---|")
    for name, r in evals.items():
        lo, hi = r.interval()
        failures = ", ".join(f"{k} × {v}" for k, v in r.reasons().most_common()) or "—"
        print(f"| {VARIANTS[name][0]} | {r.successes}/{len(r.episodes)} = {100 * r.success_rate:.0f} % | {100 * lo:.0f}–{100 * hi:.0f} % | {failures} |")
    print("\nDSSP's control loop, every tick of its evaluation:")
    print_latency(evals["dssp"].latency_ms)
    print(f"\ntotal {timings['total_s'] / 60:.1f} min; {out / 'results.json'} holds every figure")
    results = {"task": TASK, "steps": steps, "demos": demos, "episodes": episodes, "seed": seed, "timings": timings,
               "evals": {k: v.to_dict() for k, v in evals.items()}}
    atomic_write_text(out / "results.json", json.dumps(results, indent=2) + "\n")
    return results

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
Stages 2–4 run the two models side by side, each as its own process on one thread (``dssp-train``,
``python -m export.to_onnx``, ``dssp-sim eval``): their output is shown line by line behind ``[dssp]`` or
``[reactive]`` and kept in ``logs/``. A process that fails stops the demo with one line naming the stage
and a copy of its log; Ctrl-C stops the processes too.
``results.json`` in ``--out`` holds every figure. ``--out`` must be new or empty; a previous demo there is
replaced only with ``--force`` (moved aside while the new one runs, deleted when it is complete, put back
if it fails); anything else there is never touched (:mod:`dssp_data.output_guard`).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path

from dssp_data import machine
from dssp_data.files import atomic_write_text
from dssp_data.errors import DSSPError
from dssp_data.output_guard import OutputDir, OutputKind

TASK = "tap"
VARIANTS = {"dssp": ("DSSP (full history)", []), "reactive": ("reactive baseline (no history)", ["--no-history"])}
DEMO_DIR = OutputKind("a demo directory", "dssp-sim demo",
                      entries=(f"{TASK}.zarr", *VARIANTS, *(f"{name}_model" for name in VARIANTS), "evals", "logs",
                               "results.json"))
"""``dssp-sim demo --out``: the dataset, both runs and model directories, their evaluations, logs, results.json."""
PROGRESS_EVERY_S = 15.0
"""A child's progress bar (a line ended by a carriage return) is shown at most this often."""
_print_lock = threading.Lock()


def run_demo(out: Path, steps: int = 3000, demos: int = 50, episodes: int = 20, seed: int = 0,
             force: bool = False) -> dict:
    with OutputDir(out, DEMO_DIR, force=force, staged=False) as target:
        results = _run_demo(Path(out), steps, demos, episodes, seed)
        target.commit()
    return results


def _run_demo(out: Path, steps: int, demos: int, episodes: int, seed: int) -> dict:
    from dssp_sim.collect import collect
    from dssp_sim.evaluate import print_latency

    py = sys.executable
    t_start = time.perf_counter()
    timings = {}
    print(f"[1/2] collecting {demos} expert demonstrations of '{TASK}'", flush=True)
    t0 = time.perf_counter()
    data = out / f"{TASK}.zarr"
    result = collect(TASK, demos, data, seed=seed)
    if result.kept < demos:
        raise DSSPError(f"only {result.kept} of {demos} expert episodes succeeded")
    timings["collect_s"] = time.perf_counter() - t0
    print(f"[2/2] for each model, side by side: train ({steps} steps, sim preset) → export (parity checked) → "
          f"evaluate ({episodes} closed-loop episodes)", flush=True)
    (out / "evals").mkdir(exist_ok=True)
    chains = {name: [
        ("train", [py, "-m", "dssp_train.cli.train", "--data", str(data), "--out", str(out / name), "--preset", "sim",
                   "--steps", str(steps), "--seed", str(seed), *flags]),
        ("export", [py, "-m", "export.to_onnx", str(out / name), "-o", str(out / f"{name}_model"), "--threads", "1"]),
        ("eval", [py, "-m", "dssp_sim.sim_cli", "eval", "--model", str(out / f"{name}_model"), "--task", TASK,
                  "--episodes", str(episodes), "--seed", str(1000 + seed), "--threads", "1",
                  "--json", str(out / "evals" / f"{name}.json")]),
    ] for name, (_, flags) in VARIANTS.items()}
    timings.update(run_side_by_side(chains, out / "logs"))
    evals = {name: json.loads((out / "evals" / f"{name}.json").read_text()) for name in VARIANTS}
    timings["total_s"] = time.perf_counter() - t_start
    print(f"\nTask '{TASK}', {episodes} unseen episodes each, closed loop through camera → cloud → runtime → safety → CAN → arm:\n")
    print(results_table(evals))
    print("\nDSSP's control loop, every tick of its evaluation (one ONNX Runtime thread):")
    print_latency(evals["dssp"]["latency_ms"])
    print(f"\ntotal {timings['total_s'] / 60:.1f} min; {out / 'results.json'} holds every figure")
    for name, r in evals.items():  # the model directories by their names in --out (the record may move)
        r["model_dir"] = f"{name}_model"
    results = {"task": TASK, "steps": steps, "demos": demos, "episodes": episodes, "seed": seed, "timings": timings,
               "machine": machine.describe(), "evals": evals}
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
        lines.append(f"| {VARIANTS[name][0]} | {r['successes']}/{r['n']} = {100 * r['success_rate']:.0f} % | "
                     f"{100 * lo:.0f}–{100 * hi:.0f} % | {graphs} | {failures} |")
    return "\n".join(lines)


class _Child:
    """One command as its own process (one intra-op thread), its output shown behind ``[name] `` and kept in ``log``."""

    def __init__(self, name: str, cmd: list[str], log: Path):
        self.name, self.log = name, log
        env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
        self.started = time.perf_counter()
        self.seconds: float | None = None
        self.proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=env)
        self.pump = threading.Thread(target=self._pump, name=f"demo-{name}", daemon=True)
        self.pump.start()

    def _show(self, text: str, f) -> None:
        f.write(text + "\n")
        f.flush()
        with _print_lock:
            print(f"[{self.name}] {text}", flush=True)

    def _pump(self) -> None:
        """Complete lines are shown as they come; progress bars (ended by ``\\r``) every PROGRESS_EVERY_S."""
        buffer, bar, shown = b"", None, 0.0
        with open(self.log, "w", encoding="utf-8") as f:
            while chunk := os.read(self.proc.stdout.fileno(), 65536):
                buffer += chunk
                held = b"\r" if buffer.endswith(b"\r") else b""  # perhaps the first half of \r\n
                *parts, buffer = re.split(rb"(\r\n|\n|\r)", buffer[: len(buffer) - len(held)])
                buffer += held
                for text, end in zip(parts[::2], parts[1::2]):
                    line = text.decode("utf-8", "replace").rstrip()
                    if end == b"\r":
                        bar = line
                        if line and time.monotonic() - shown >= PROGRESS_EVERY_S:
                            self._show(line, f)
                            bar, shown = None, time.monotonic()
                    else:  # a complete line: it also ends a bar (tqdm closes with its final state)
                        bar = None
                        if line:
                            self._show(line, f)
            for line in (bar, buffer.decode("utf-8", "replace").rstrip()):  # the last state of a bar, an unended line
                if line:
                    self._show(line, f)

    def poll(self) -> int | None:
        code = self.proc.poll()
        if code is not None and self.seconds is None:
            self.seconds = time.perf_counter() - self.started
            self.pump.join(timeout=10)
        return code

    def stop(self) -> None:
        """Terminate the process if it still runs (SIGTERM, then SIGKILL after 10 s)."""
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.pump.join(timeout=2)
        self.proc.stdout.close()


def run_side_by_side(chains: dict[str, list[tuple[str, list[str]]]], logs: Path) -> dict[str, float]:
    """Run each chain's commands one after the other, the chains at once; returns ``{f"{stage}_{name}_s": seconds}``.
    The first command that fails stops the others and raises one line with the stage, the exit code, its last line
    and a copy of its log outside ``--out`` (the demo directory is removed on failure); Ctrl-C stops them all."""
    logs.mkdir(parents=True, exist_ok=True)
    seconds: dict[str, float] = {}
    pending = {name: list(steps) for name, steps in chains.items()}
    running: dict[str, tuple[str, _Child]] = {}
    try:
        while pending or running:
            for name in list(pending):
                if name not in running:
                    stage, cmd = pending[name].pop(0)
                    running[name] = (stage, _Child(name, cmd, logs / f"{stage}_{name}.log"))
                    if not pending[name]:
                        del pending[name]
            for name, (stage, child) in list(running.items()):
                code = child.poll()
                if code is None:
                    continue
                del running[name]
                child.stop()
                if code != 0:
                    raise DSSPError(_failure(stage, child, code))
                seconds[f"{stage}_{name}_s"] = child.seconds
            time.sleep(0.2)
        return seconds
    finally:
        for _, child in running.values():
            child.stop()


def _failure(stage: str, child: _Child, code: int) -> str:
    lines = child.log.read_text(encoding="utf-8", errors="replace").strip().splitlines()
    fd, kept = tempfile.mkstemp(prefix=f"dssp-demo-{stage}-{child.name}-", suffix=".log")
    os.close(fd)
    shutil.copyfile(child.log, kept)
    last = f": {lines[-1]}" if lines else ""
    return f"{stage} of {child.name} failed (exit {code}); its log: {kept}{last}"

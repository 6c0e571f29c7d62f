"""What the control loop itself costs per tick, without the model: dssp-run's tick minus the model's work.

    python benchmarks/loop_overhead.py [--model MODEL_DIR] [--ticks 400] [--repeats 3]
                                       [--compare PATH ...] [--json PATH [--force]]

``dssp-run --camera tabletop --can sim`` runs ``--ticks`` ticks (one ONNX Runtime thread, no status line, a fixed
diffusion seed) and its episode log gives, per tick, the whole tick (``tick_ms``: camera and feedback read, point
cloud, the model, the safety layer, the CAN send, the subscribers) and the model's part (``observe_ms`` +
``chunk_ms``). The loop's **overhead** is the difference, and **the loop's own part** that less the point cloud
(``cloud_ms``): reading the devices, the safety layer, the CAN send, the subscribers. Their p50 and p99 over
every tick of every repeat are reported, beside the whole tick's. Without ``--model`` a tiny model for the rig is trained first
(``dssp_train.data.rig_reach``, preset ``tiny``, 20 steps) and each checkout exports it with its own exporter.

``--compare PATH``: the same measurement of another checkout of this project (e.g. ``git worktree add
/tmp/before COMMIT``), its packages first on ``PYTHONPATH``, in the same run and alternated with this one,
repeat by repeat, so that both see the same machine; the ratio is theirs. The loop runs in real time on
the simulated devices' threads, so the figures are the machine's: compare within one run only.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the benchmarks' shared helpers
from bench_output import check_json, emit  # noqa: E402

from dssp_core import machine  # noqa: E402
from dssp_core.cli_runner import ArgumentParser, run_cli
from dssp_core.errors import ConfigError

ROOT = Path(__file__).resolve().parent.parent
RUN = "import sys; from hardware.cli.run import main; sys.exit(main(sys.argv[1:]))"


def build_run(root: Path) -> Path:
    """A tiny training run for one simulated Piper (the tests' ``arm_export``): its run directory."""
    import contextlib
    import io

    from dssp_train.cli.train import main as train_main
    from dssp_train.data.rig_reach import write_rig_reach

    data = write_rig_reach(root / "arm.zarr")
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        if (
            train_main(
                [
                    "--data",
                    str(data),
                    "--out",
                    str(root / "run"),
                    "--preset",
                    "tiny",
                    "--steps",
                    "20",
                    "--set",
                    "train.val_every=20",
                    "--no-progress",
                ]
            )
            != 0
        ):
            raise ConfigError("training the benchmark's tiny model failed")
    return root / "run"


def export_with(tree: Path, run: Path, out: Path) -> Path:
    """``run`` exported by checkout ``tree``'s own exporter: a model directory its runtime reads (checkouts may write
    different manifest formats)."""
    env = {**os.environ, "PYTHONPATH": str(tree) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    done = subprocess.run(
        [sys.executable, "-m", "export.to_onnx", str(run), "-o", str(out), "--skip-verify"],
        cwd=tree,
        env=env,
        capture_output=True,
        text=True,
    )
    if done.returncode != 0:
        raise ConfigError(
            f"exporting the benchmark's tiny model with {tree} failed: {done.stderr.strip().splitlines()[-1:]}"
        )
    return out


def commit_of(tree: Path) -> str:
    """The checkout's commit (short, with ``+changes`` when its work tree differs), or its path."""
    head = subprocess.run(["git", "-C", str(tree), "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
    if head.returncode != 0:
        return str(tree)
    dirty = subprocess.run(
        ["git", "-C", str(tree), "status", "--porcelain", "--untracked-files=no"], capture_output=True, text=True
    )
    return head.stdout.strip() + ("+changes" if dirty.stdout.strip() else "")


def one_run(tree: Path, model: Path, ticks: int, log_dir: Path) -> list[dict]:
    """``dssp-run`` of checkout ``tree`` for ``ticks`` ticks; every tick's record from its episode log."""
    env = {
        **os.environ,
        "PYTHONPATH": str(tree) + os.pathsep + os.environ.get("PYTHONPATH", ""),
        "OMP_NUM_THREADS": "1",
    }
    argv = [
        "--model",
        str(model),
        "--camera",
        "tabletop",
        "--can",
        "sim",
        "--max-steps",
        str(ticks),
        "--log-dir",
        str(log_dir),
        "--seed",
        "0",
        "--threads",
        "1",
        "--quiet",
        "--no-can-log",
    ]
    done = subprocess.run([sys.executable, "-c", RUN, *argv], cwd=tree, env=env, capture_output=True, text=True)
    if done.returncode != 0:
        raise ConfigError(f"dssp-run of {tree} failed ({done.returncode}): {done.stderr.strip().splitlines()[-1:]}")
    with open(log_dir / "ticks.jsonl") as f:
        return [json.loads(line) for line in f]


def overheads(records: list[dict]) -> tuple[list[float], list[float], list[float]]:
    """(whole tick, overhead, the loop's own part) in ms of the ticks that ran the model: overhead = tick − model
    (observe + chunk); the loop's own part = overhead − the point cloud (reads, safety, send, subscribers)."""
    whole, over, own = [], [], []
    for r in records:
        if r.get("observe_ms") is None:
            continue  # a held tick ran no model: nothing to subtract
        model = r["observe_ms"] + (r.get("chunk_ms") or 0.0)
        whole.append(r["tick_ms"])
        over.append(r["tick_ms"] - model)
        own.append(r["tick_ms"] - model - r["cloud_ms"])
    return whole, over, own


def figures(values: list[float]) -> dict:
    v = np.asarray(values, np.float64)
    return {"p50": round(float(np.median(v)), 4), "p99": round(float(np.percentile(v, 99)), 4), "n": int(v.size)}


def measure(trees: dict[str, Path], models: dict[str, Path], ticks: int, repeats: int) -> dict:
    samples = {name: ([], [], []) for name in trees}
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(repeats):
            for i, (name, tree) in enumerate(trees.items()):  # alternated: both see the same machine
                for kept, new in zip(
                    samples[name], overheads(one_run(tree, models[name], ticks, Path(tmp) / f"{i}-{k}"))
                ):
                    kept.extend(new)
    rows = [
        {"tree": name, "tick_ms": figures(w), "overhead_ms": figures(o), "loop_ms": figures(own)}
        for name, (w, o, own) in samples.items()
    ]
    return {"machine": machine.describe(), "ticks": ticks, "repeats": repeats, "rows": rows}


def markdown(report: dict) -> str:
    lines = [
        "| checkout | the loop's own p50 ms | p99 ms | overhead (with the cloud) p50 ms | p99 ms | whole tick p50 ms "
        "| p99 ms | ticks with the model |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in report["rows"]:
        own, o, t = r["loop_ms"], r["overhead_ms"], r["tick_ms"]
        lines.append(
            f"| {r['tree']} | {own['p50']:.3f} | {own['p99']:.3f} | {o['p50']:.3f} | {o['p99']:.3f} | "
            f"{t['p50']:.3f} | {t['p99']:.3f} | {o['n']} |"
        )
    m = report["machine"]
    lines += [
        "",
        f"{report['repeats']} runs of {report['ticks']} ticks each, alternated; {m.get('cpu')} "
        f"({m.get('cores')} cores), onnxruntime {m.get('onnxruntime')}; overhead = "
        "tick − (observe + chunk); the loop's own part = overhead − the point cloud.",
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = ArgumentParser(prog="python benchmarks/loop_overhead.py", description=__doc__.split("\n\n")[0])
    p.add_argument("--model", type=Path, help="a model for one Piper (default: a tiny one, trained here)")
    p.add_argument("--ticks", type=int, default=400, help="ticks per run (default 400)")
    p.add_argument("--repeats", type=int, default=3, help="runs per checkout (default 3)")
    p.add_argument(
        "--compare",
        type=Path,
        nargs="*",
        default=[],
        metavar="PATH",
        help="other checkouts of this project, measured in the same run",
    )
    p.add_argument("--json", type=Path)
    p.add_argument("--force", action="store_true")
    args = p.parse_args(argv)

    def _main() -> int:
        if args.ticks < 10 or args.repeats < 1:
            raise ConfigError("--ticks must be at least 10 and --repeats at least 1")
        for tree in args.compare:
            if not (tree / "hardware" / "run_loop.py").is_file():
                raise ConfigError(f"--compare {tree}: not a checkout of this project (no hardware/run_loop.py)")
        check_json(args.json, args.force)
        trees = {commit_of(t): t.resolve() for t in [ROOT, *args.compare]}
        with tempfile.TemporaryDirectory() as tmp:
            run = None if args.model else build_run(Path(tmp))
            models = {
                name: args.model or export_with(tree, run, Path(tmp) / f"model-{i}")
                for i, (name, tree) in enumerate(trees.items())
            }
            report = measure(trees, models, args.ticks, args.repeats)
        return emit(report, markdown(report), args.json, args.force)

    return run_cli(_main)


if __name__ == "__main__":
    sys.exit(main())

"""Export figures per preset: export time, graph sizes and node counts, parity and its time, ORT vs torch latency.

    python benchmarks/export_report.py [--preset tiny robotwin] [--run RUN_DIR] [--out runs/export_report]
                                       [--verify-steps 1000] [--threads N] [--quantize] [--set model.F=V]
                                       [--json PATH] [--force]

For each preset without ``--run``, a run directory with an untrained policy is made by hand
(S = A = 14, normalisers fitted on random data, saved with the checkpoint helpers) — export and parity
do not depend on training. Parity is the exporter's verification (:mod:`export.verify`: the graphs
streamed, the PyTorch reference in batch); its time split (reference, streaming, batch checks) is in
``verification.seconds``. The latency figures are measured separately, one backend at a time, batch 1
(ONNX Runtime fp32 and int8, PyTorch eager through the streaming API): median over repeated calls after
a warm-up.

``--out`` must be new or empty; a previous report directory of this script (marked ``.dssp-output.json``)
is replaced only with ``--force`` (moved aside meanwhile, deleted once the new one is complete, put back if it
fails); anything else is never touched.
An explicit ``--json`` file is new or, with ``--force``, replaced.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

from dssp_core.cli_runner import run_cli
from dssp_core.output_guard import OutputDir, OutputKind, check_output_file, write_output_text
from dssp_deploy.latency import time_calls
from dssp_deploy.manifest import FUSED, read_graph, read_manifest
from dssp_deploy.sessions import default_threads, open_session
from dssp_train.config import apply_overrides, load_preset
from dssp_train.model.policy import DSSPPolicy
from dssp_train.training import checkpoint as ckpt
from export.to_onnx import export_model, format_summary

REPORT_DIR = OutputKind(
    "an export report directory", "benchmarks/export_report.py", entries=("*_run", "*_model", "report.json")
)
"""``--out``: PRESET_run/ (untrained runs), PRESET_model/ (their exports), report.json."""


def make_untrained_run(
    preset: str, run_dir: Path, state_dim: int = 14, action_dim: int = 14, seed: int = 0, overrides: list[str] = ()
) -> Path:
    """A run directory (config.json, model.safetensors) holding an untrained ``preset`` policy (``overrides``:
    ``section.field=value`` items, as dssp-train's ``--set``)."""
    config = apply_overrides(load_preset(preset), list(overrides))
    config.model.state_dim, config.model.action_dim = state_dim, action_dim
    torch.manual_seed(seed)
    policy = DSSPPolicy(config.model)
    rng = np.random.default_rng(seed)
    policy.fit_normalizers(
        rng.uniform(-1, 1, (16, config.model.n_points, config.model.point_dim)).astype(np.float32),
        rng.uniform(-1, 1, (256, state_dim)).astype(np.float32),
        rng.uniform(-1, 1, (256, action_dim)).astype(np.float32),
    )
    run_dir.mkdir(parents=True, exist_ok=True)
    ckpt.save_config(run_dir, config)
    ckpt.save_tensors(
        run_dir / "model.safetensors", policy.state_dict(), {"format_version": ckpt.FORMAT_VERSION, "step": "0"}
    )
    return run_dir


def median_ms(fn, repeats: int, warmup: int = 3) -> float:
    return round(float(np.median(time_calls(fn, repeats, warmup))), 3)


def latency(model_dir: Path, run_dir: Path, threads: int, repeats: int) -> dict[str, dict[str, float]]:
    """Median ms per history step and per chunk, batch 1: ORT (every ONNX graph set present: fp32, fused,
    quantized) and torch eager."""
    from dssp_train.model.streaming import StreamingPolicy
    from dssp_train.training.checkpoint import load_policy

    manifest = read_manifest(model_dir)  # checked: facts, interface, file names inside the model directory
    feeds = {}
    for graph in ("history_step", "denoiser"):
        feeds[graph] = {
            s["name"]: np.random.default_rng(0)
            .standard_normal([1 if d == "B" else manifest.contract.n_points if d == "P" else d for d in s["shape"]])
            .astype(np.float32)
            for s in manifest.graphs[graph]["inputs"]
        }
    out = {}
    for kind in manifest.graphs["denoiser"]["files"]:
        files = {g: manifest.graphs[g]["files"].get(kind) for g in feeds}
        if kind.startswith("onnx") and all(files.values()):
            fused = kind.endswith(FUSED)
            sessions = {
                g: open_session(read_graph(model_dir, manifest, g, kind)[1], threads, fused=fused) for g in files
            }
            out[kind] = {
                g: median_ms(lambda g=g: sessions[g].run(None, feeds[g]), repeats if g == "denoiser" else 10 * repeats)
                for g in feeds
            }
    torch.set_num_threads(threads)
    policy, _ = load_policy(run_dir)
    stream = StreamingPolicy(policy)
    pc, pos = feeds["history_step"]["point_cloud"], feeds["history_step"]["agent_pos"]
    stream.observe(pc, pos)
    noise = feeds["denoiser"]["noise"]
    k = manifest.contract.denoise_steps
    out["torch_eager"] = {
        "history_step": median_ms(lambda: stream.observe(pc, pos), 10 * repeats),
        "denoiser": median_ms(lambda: stream.act(noise=noise, num_steps=k), repeats),
    }
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--preset", nargs="+", default=["tiny", "robotwin"])
    p.add_argument("--run", help="export this run directory instead of untrained presets")
    p.add_argument("--out", default="runs/export_report")
    p.add_argument("--verify-steps", type=int, default=1000)
    p.add_argument("--threads", type=int, default=default_threads())
    p.add_argument("--repeats", type=int, default=20)
    p.add_argument("--quantize", action="store_true", help="also write and measure the int8 and int4 graphs")
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="SECTION.FIELD=VALUE",
        help="a config field of the untrained runs, e.g. model.denoiser_mlp=none (the 28.1 M robotwin)",
    )
    p.add_argument("--json", help="write the figures here (default OUT/report.json)")
    p.add_argument(
        "--force", action="store_true", help="replace a previous report in --out and an existing --json file"
    )
    args = p.parse_args(argv)
    return run_cli(lambda: _report(args))


def _report(args) -> int:
    if args.json:
        check_output_file(args.json, force=args.force, flag="--json")
    jobs = [(Path(args.run).name, Path(args.run))] if args.run else [(name, None) for name in args.preset]
    report = {}
    with OutputDir(args.out, REPORT_DIR, force=args.force, staged=False) as target:  # the report names its paths
        out = target.path
        for name, run_dir in jobs:
            if run_dir is None:
                run_dir = make_untrained_run(name, out / f"{name}_run", overrides=args.set)
            model_dir = out / f"{name}_model"
            print(f"== {name}: {run_dir} -> {model_dir}", flush=True)
            summary = export_model(
                run_dir,
                model_dir,
                verify_steps=args.verify_steps,
                threads=args.threads,
                quantize=("int8", "int4") if args.quantize else (),
            )
            print(format_summary(summary), flush=True)
            if summary.get("verification"):
                split = ", ".join(f"{k} {v} s" for k, v in summary["verification"]["seconds"].items())
                print(f"verification time: {split}", flush=True)
            summary["latency_isolated_ms"] = latency(model_dir, run_dir, args.threads, args.repeats)
            print(json.dumps(summary["latency_isolated_ms"]), flush=True)
            report[name] = summary
        text = json.dumps(report, indent=2) + "\n"
        if not args.json:
            write_output_text(out / "report.json", text, force=False)
        target.commit()
    path = Path(args.json) if args.json else Path(args.out) / "report.json"
    if args.json:
        write_output_text(path, text, force=args.force, flag="--json")
    print(f"figures written to {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

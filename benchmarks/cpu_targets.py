"""The CPU targets of one exported model in one run, with the fused Mamba kernel and without it.

    python benchmarks/cpu_targets.py MODEL_DIR --checkpoint RUN_DIR [--threads N] [--precision fp32|int8|int4]
                                     [--k1-model DIR] [--quick] [--json PATH] [--plot PATH] [--force]

Batch 1, the model's point count, ``--threads`` ONNX Runtime threads (default: all CPUs; torch gets the same).
For each graph set — the fused Mamba kernel's (``*.fused.onnx``) and the standard one — measures:

- the denoiser chunk (K DDIM steps) at ``--precision`` (default: the runtime's default), p50;
- the history step in fp32, p50 and p99;
- the tick with the next chunk prefetched (``dssp-profile``'s real-time loop: history on one thread, the
  chunk on the others), its p99 against the history step's p99 on the same sessions;

and once: PyTorch eager (``--checkpoint``, the run the model was exported from) per chunk and per
history step. The roofline: this machine's read bandwidth (one core, numpy summing 256 MiB), and per graph set and
precision the bytes of denoiser weights one chunk reads (``dssp_deploy.profile.roofline``: K passes, the first
step carrying the prefix; K + 1 in a model exported before it did), the floor they imply, the achieved chunk and the ratio — on a
CPU with VNNI also the fused int8 chunk with the AVX2 paths forced (``DSSP_QGEMM_PATH=avx2 DSSP_SCAN_PATH=avx2``).
``--k1-model`` (the same run exported with ``--denoise-steps 1``, the distilled samplers' shape) adds its fused
chunk on each path, the prefix and the step in one pass over the weights. ``--plot`` draws achieved against floor.
Ratios are of medians measured in this run. DSSP against DP3, like for like, is ``benchmarks/dp3_comparison.py``.
Prints the targets table (the robotwin preset's targets on a 2-core CPU); ``--json`` writes every figure.
The runtime-only figures, without torch, are ``dssp-profile MODEL_DIR``.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_output import check_json, emit  # noqa: E402
from torch_comparison import check_source, eager_samples  # noqa: E402

from dssp_core import machine  # noqa: E402
from dssp_core.cli_runner import ArgumentParser, run_cli  # noqa: E402
from dssp_core.errors import ConfigError  # noqa: E402
from dssp_deploy.latency import LatencyStats, memory_read_gbs, time_calls  # noqa: E402
from dssp_deploy.manifest import PRECISIONS, Manifest, file_kind, read_manifest  # noqa: E402
from dssp_deploy.onnx_policy import DEFAULT_PRECISION, OnnxPolicy  # noqa: E402
from dssp_deploy.profile import paths_and_threads, prefetch_ticks, random_observation, roofline  # noqa: E402
from dssp_deploy.sessions import check_threads, default_threads  # noqa: E402
from studies.protocol import code_commit  # noqa: E402

FULL = {"history": 300, "chunks": 30, "prefetch_ticks": 300, "torch_iterations": 10}
QUICK = {"history": 20, "chunks": 3, "prefetch_ticks": 20, "torch_iterations": 2}
NO_SPIN = "+no-spin"  # the fused graphs with the chunk's threads sleeping between its operators (--no-spin)
TARGETS = {  # robotwin preset, 1024 points, batch 1, 2 threads, p50
    "chunk_ms": (25.0, 50.0),  # (target, required)
    "history_step_fp32_ms": 1.5,
    "ort_vs_eager_chunk": 5.0,
    "prefetch_tick_p99_over_history_p99": 1.5,
    "chunk_over_floor": 1.5,
}
FORCED_AVX2 = {"DSSP_QGEMM_PATH": "avx2", "DSSP_SCAN_PATH": "avx2"}
FORCED = "fused, avx2 forced"
FUSED = "fused"
K1 = ", K = 1"  # the one-step model's rows (--k1-model)


def runtime_figures(model_dir: Path, precision: str, threads: int, settings: dict) -> dict:
    """Per graph set (fused, standard): chunk and history step at ``precision`` and fp32 (``dssp-profile``'s
    paths-and-threads rows, at ``threads``), and the prefetched tick."""
    rng = np.random.default_rng(0)
    timing = {"matrix_iterations": settings["history"], "matrix_chunks": settings["chunks"]}
    out: dict = {}
    for p in dict.fromkeys([precision, "fp32"]):
        for row in paths_and_threads(model_dir, p, threads, timing, rng):
            no_spin = threads > 1 and not row["spinning"]
            if row["threads"] == threads and (row["kernel"] == "fused" or not no_spin):
                key = row["kernel"] + (NO_SPIN if no_spin else "")
                out.setdefault(key, {"precision": {}})["precision"][p] = row
    for (
        kernel,
        r,
    ) in out.items():  # the prefetched chunk: as the runtime runs it (spinning when it has 2 threads or more)
        r["prefetch"] = (
            None
            if kernel.endswith(NO_SPIN)
            else prefetch_ticks(model_dir, precision, kernel, threads, settings["prefetch_ticks"], rng)
        )
    return out


def has_vnni() -> bool:
    """Whether this CPU has VNNI (its int8 products' fastest path), so that forcing AVX2 measures another path."""
    flags = set(machine.cpu()[1])
    return bool({"avx512_vnni", "avx_vnni"} & flags) and "avx2" in flags


def fused_chunk(model_dir: Path, precision: str, threads: int, chunks: int, env: dict[str, str] | None = None) -> float:
    """The fused chunk's p50 (ms), with ``env`` set while the session is made (e.g. the AVX2 paths forced)."""
    import os

    saved = {k: os.environ.get(k) for k in env or {}}
    os.environ.update(env or {})
    try:
        policy = OnnxPolicy(model_dir, threads=threads, precision=precision, kernel="fused")
        pc, pos = random_observation(policy, np.random.default_rng(0))
        policy.observe(pc, pos)
        return LatencyStats.of(time_calls(lambda: policy.act(seed=0), chunks)).p50
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def roofline_figures(
    model_dir: Path,
    manifest: Manifest,
    runtime: dict,
    precision: str,
    threads: int,
    settings: dict,
    read_gbs: float,
    k1_model: Path | None,
) -> dict:
    """{graph set: {precision: roofline row}} for every chunk measured, the forced AVX2 one on a VNNI CPU, and the
    one-step model's fused chunk (``--k1-model``) on each path."""
    out = {}
    for kernel, r in runtime.items():
        fused = kernel.startswith("fused")
        out[kernel] = {
            p: roofline(model_dir, manifest, file_kind(p, fused), row["chunk_p50"], read_gbs)
            for p, row in r["precision"].items()
        }
    paths = {FUSED: None} | ({FORCED: FORCED_AVX2} if "fused" in runtime and has_vnni() else {})
    for name, env in paths.items():
        if name == FORCED:
            chunk = fused_chunk(model_dir, precision, threads, settings["chunks"], env)
            out[FORCED] = {precision: roofline(model_dir, manifest, file_kind(precision, True), chunk, read_gbs)}
        if k1_model is not None:
            k1 = read_manifest(k1_model)
            chunk = fused_chunk(k1_model, precision, threads, settings["chunks"], env)
            out[name + K1] = {precision: roofline(k1_model, k1, file_kind(precision, True), chunk, read_gbs)}
    return out


def measure(
    model_dir: Path, checkpoint: Path, threads: int, precision: str, quick: bool, k1_model: Path | None = None
) -> dict:
    settings = QUICK if quick else FULL
    torch.set_num_threads(threads)
    manifest = read_manifest(model_dir)
    read_gbs = memory_read_gbs()
    runtime = runtime_figures(model_dir, precision, threads, settings)
    lines = roofline_figures(model_dir, manifest, runtime, precision, threads, settings, read_gbs, k1_model)
    policy = OnnxPolicy(model_dir, threads=threads, precision=precision, kernel="standard", warmup=0)
    pc, pos = (torch.from_numpy(a) for a in random_observation(policy, np.random.default_rng(0)))
    eager = eager_samples(
        checkpoint,
        manifest,
        pc,
        pos,
        {"iterations": settings["history"], "torch_iterations": settings["torch_iterations"]},
    )
    eager = {k: LatencyStats.of(v).to_dict() for k, v in eager.items()}
    return {
        "model_dir": str(model_dir),
        "checkpoint": str(checkpoint),
        "threads": threads,
        "precision": precision,
        "settings": settings,
        "runtime": runtime,
        "eager_torch": eager,
        "targets": TARGETS,
        "machine": machine.describe(),
        "denoise_steps": manifest.contract.denoise_steps,
        "torch_threads": torch.get_num_threads(),
        "read_gbs": read_gbs,
        "roofline": lines,
        "code_commit": code_commit(),
        "model_source": manifest.data["source"],
        "k1_model": str(k1_model) if k1_model else None,
    }


def rows(runtime: dict, eager: dict, precision: str, lines: dict) -> list[dict]:
    """The targets table, computed from a record's measurements (``runtime``, ``eager_torch``, ``roofline``): per
    figure, the value on each graph set and the target."""

    def per_kernel(fn):
        return {k: fn(r) for k, r in runtime.items()}

    chunk = per_kernel(lambda r: r["precision"][precision]["chunk_p50"])
    out = [
        {
            "figure": f"chunk, K = {{k}}, {precision}, p50 ms",
            "values": chunk,
            "target": "<= 25 (required <= 50)",
            "met": {k: v <= TARGETS["chunk_ms"][0] for k, v in chunk.items()},
            "required_met": {k: v <= TARGETS["chunk_ms"][1] for k, v in chunk.items()},
        },
        {
            "figure": "history step, fp32, p50 ms",
            "values": per_kernel(lambda r: r["precision"]["fp32"]["history_step_p50"]),
            "target": "<= 1.5",
        },
        {
            "figure": f"history step, {precision}, p50 ms",
            "values": per_kernel(lambda r: r["precision"][precision]["history_step_p50"]),
            "target": "<= 1",
        },
        {  # like for like: eager PyTorch runs fp32, so ONNX Runtime's fp32 graphs
            "figure": "ONNX Runtime vs eager PyTorch per chunk, both fp32 (eager / ORT)",
            "values": per_kernel(lambda r: eager["denoiser_chunk"]["p50"] / r["precision"]["fp32"]["chunk_p50"]),
            "target": ">= 5x",
        },
        {
            "figure": "tick p99 with prefetch / history step p99",
            "values": per_kernel(lambda r: r["prefetch"]["tick_p99_over_history_p99"] if r["prefetch"] else None),
            "target": "<= 1.5x",
        },
        {
            "figure": f"chunk floor, {precision}: the denoiser's weights read as often as the chunk reads them, ms",
            "values": {k: lines[k][precision]["floor_ms"] for k in runtime},
            "target": "",
        },
        {
            "figure": f"chunk / floor, {precision}",
            "values": {k: lines[k][precision]["ratio"] for k in runtime},
            "target": "<= 1.5x",
        },
    ]
    if FUSED + K1 in lines:
        out.insert(
            1,
            {
                "figure": f"chunk, K = 1, {precision}, p50 ms",
                "values": {FUSED: lines[FUSED + K1][precision]["chunk_ms"]},
                "target": "<= 3",
            },
        )
    return out


def markdown(report: dict) -> str:
    kernels = list(report["runtime"])
    k = report["denoise_steps"]
    head = {
        "fused": "fused Mamba kernel",
        "fused" + NO_SPIN: "fused, --no-spin",
        "standard": "standard graphs",
        FORCED: "fused, AVX2 paths forced",
        FUSED + K1: "fused, K = 1",
        FORCED + K1: "fused, AVX2 paths forced, K = 1",
    }
    m = report["machine"]
    lines = [
        f"Model: {Path(report['model_dir']).name} — batch 1, {report['threads']} thread(s), medians of one run; {m['cpu']} "
        f"({m['cores']} cores, {', '.join(m['cpu_flags']) or 'no AVX2'}), onnxruntime {m.get('onnxruntime')}",
        "",
        "| figure | " + " | ".join(head[k] for k in kernels) + " | target |",
        "|---|" + "---:|" * len(kernels) + "---|",
    ]
    table = rows(report["runtime"], report["eager_torch"], report["precision"], report["roofline"])
    for row in table:
        cells = " | ".join(f"{row['values'][k]:.2f}" if row["values"].get(k) is not None else "-" for k in kernels)
        lines.append(f"| {row['figure'].format(k=k)} | {cells} | {row['target']} |")
    if report.get("roofline"):
        lines += [
            "",
            f"Roofline: read bandwidth {report['read_gbs']:.1f} GB/s (one core, numpy summing 256 MiB); a chunk "
            f"reads the denoiser's weights once per DDIM step (K = {k}), and once more where the cached prefix runs "
            "apart from the first step (reads: as the exporter counted them in each graph):",
            "",
            "| graphs | precision | weights MiB | reads | floor ms | chunk p50 ms | chunk / floor |",
            "|---|---|---:|---:|---:|---:|---:|",
        ]
        for kernel, by_precision in report["roofline"].items():
            for p, r in by_precision.items():
                lines.append(
                    f"| {head.get(kernel, kernel)} | {p} | {r['weights_mib']:.1f} | {r['passes']} | {r['floor_ms']:.2f} | "
                    f"{r['chunk_ms']:.2f} | {r['ratio']:.2f} |"
                )
    eager = report["eager_torch"]
    lines += [
        "",
        f"PyTorch eager (fp32, {report['torch_threads']} threads): chunk {eager['denoiser_chunk']['p50']:.1f} ms, "
        f"history step {eager['history_step']['p50']:.2f} ms",
    ]
    for kernel, r in report["runtime"].items():
        pf = r["prefetch"]
        if pf is None:
            continue
        if not pf["possible"]:
            lines.append(f"{head[kernel]}: prefetch not possible ({pf['reason']})")
            continue
        lines.append(
            f"{head[kernel]}: prefetched tick p50 {pf['tick']['p50']:.2f} / p99 {pf['tick']['p99']:.2f} ms, history step alone p99 "
            f"{pf['history_step_alone']['p99']:.2f} ms, chunks late {pf['chunks_late']} of {pf['ticks']} ticks"
        )
    return "\n".join(lines)


def plot_roofline(report: dict, path: Path, force: bool) -> None:
    """Each chunk measured against its floor (bars: achieved, floor; the ratio on top), as a PNG."""
    import matplotlib  # deferred: loads matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from dssp_core.output_guard import write_output_file

    rows = [
        (f"{kernel}\n{p}", r) for kernel, by_precision in report["roofline"].items() for p, r in by_precision.items()
    ]
    fig, ax = plt.subplots(figsize=(1.6 * len(rows) + 2, 4))
    x = np.arange(len(rows))
    ax.bar(x - 0.2, [r["chunk_ms"] for _, r in rows], 0.4, label="chunk p50")
    ax.bar(x + 0.2, [r["floor_ms"] for _, r in rows], 0.4, label=f"floor ({report['read_gbs']:.1f} GB/s)")
    for i, (_, r) in enumerate(rows):
        ax.annotate(f"{r['ratio']:.2f}x", (x[i] - 0.2, r["chunk_ms"]), ha="center", va="bottom", fontsize=8)
    ax.set_xticks(x, [label for label, _ in rows], fontsize=8)
    ax.set_ylabel("ms per chunk")
    m = report["machine"]
    ax.set_title(
        f"{Path(report['model_dir']).name}: {m['cpu']} ({', '.join(m['cpu_flags'])}), {report['threads']} threads",
        fontsize=9,
    )
    ax.legend(fontsize=8)
    fig.tight_layout()
    write_output_file(path, lambda tmp: fig.savefig(tmp, format="png", dpi=100), force=force, flag="--plot")
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    p = ArgumentParser(prog="cpu_targets.py", description=__doc__.split("\n\n")[0])
    p.add_argument("model_dir", type=Path, help="a model directory (python -m export.to_onnx)")
    p.add_argument(
        "--checkpoint", type=Path, required=True, help="the run directory it was exported from (PyTorch eager)"
    )
    p.add_argument("--threads", type=int, help="ONNX Runtime and torch threads (default: all CPUs)")
    p.add_argument(
        "--precision",
        choices=list(PRECISIONS),
        default=DEFAULT_PRECISION,
        help=f"the chunk's graphs (default {DEFAULT_PRECISION})",
    )
    p.add_argument("--quick", action="store_true", help="short run (tests)")
    p.add_argument("--json", type=Path, help="write every figure here (a new file; --force replaces one)")
    p.add_argument(
        "--plot", type=Path, help="draw each chunk against its floor (a PNG; a new file, --force replaces one)"
    )
    p.add_argument("--k1-model", type=Path, help="the same run exported with --denoise-steps 1: its fused chunk too")
    p.add_argument("--force", action="store_true", help="replace an existing --json or --plot file")
    args = p.parse_args(argv)

    def _main() -> int:
        check_threads(args.threads)
        check_json(args.json, args.force)
        check_json(args.plot, args.force)
        check_source(args.model_dir, args.checkpoint, read_manifest(args.model_dir))
        if args.k1_model is not None:
            k1 = read_manifest(args.k1_model)
            check_source(args.k1_model, args.checkpoint, k1)
            if k1.contract.denoise_steps != 1:
                raise ConfigError(
                    f"--k1-model {args.k1_model} runs {k1.contract.denoise_steps} DDIM steps, not 1; export it with "
                    "python -m export.to_onnx RUN_DIR -o DIR --denoise-steps 1 --timestep-spacing trailing"
                )
        report = measure(
            args.model_dir,
            args.checkpoint,
            args.threads or default_threads(),
            args.precision,
            args.quick,
            args.k1_model,
        )
        if args.plot:
            plot_roofline(report, args.plot, args.force)
        return emit(report, markdown(report), args.json, args.force)

    return run_cli(_main)


if __name__ == "__main__":
    sys.exit(main())

"""``dssp-profile``: CPU latency and memory of an exported DSSP model, in numbers and a plot.

    dssp-profile MODEL_DIR [--checkpoint RUN_DIR] [--precision fp32|int8] [--quick] [--threads N] [--json PATH] [--plot PATH] [--force]

Measures, for the model directory given (batch 1, the model's point count):
- per component — history step, denoiser chunk (K DDIM steps), the chunk tick (both) — p50/p95/p99/max
  over many calls after warm-up, and the resident memory;
- a history-length sweep from 10 to 10,000 steps: the cost of one history update at each length and the
  memory (DSSP's claim: constant);
- in the same run, when torch is importable: PyTorch eager (needs ``--checkpoint``) and TorchScript
  (``*.pt`` in the model directory) of the same model, and a causal Transformer history encoder of the
  same width over the full history (paper Table 3's alternative), whose per-step cost grows;
- achieved GFLOP/s against this machine's own float32 GEMM peak (numpy), and the chunk's floor on this
  machine: its flops at that peak, and — when the denoiser's weights exceed the last-level cache, so each
  of the K DDIM steps reads them from memory again — K x weight bytes at the measured read bandwidth.
Prints a Markdown table; ``--json`` writes every figure (ms, MiB); ``--plot`` a PNG. Both are new files or,
with ``--force``, replace existing ones (checked before profiling; written to a temporary name and renamed).
"""

from __future__ import annotations

import json
import platform
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from dssp_deploy.flops import chunk_flops, history_step_flops
from dssp_deploy.latency import (
    LatencyStats,
    gemm_peak_gflops,
    last_level_cache_bytes,
    memory_read_gbs,
    resident_memory_mib,
    time_calls,
)
from dssp_deploy.manifest import DENOISER_GRAPH, HISTORY_GRAPH, PRECISIONS, ModelDirError, graph_file, read_graph
from dssp_deploy.op_breakdown import elementwise_share, op_type_breakdown
from dssp_deploy.onnx_policy import OnnxPolicy
from dssp_data.cli_runner import ArgumentParser

FULL = {"iterations": 300, "chunk_iterations": 100, "torch_iterations": 30, "sweep": [10, 100, 1000, 3000, 10000], "window": 50, "transformer_max": 3000}
QUICK = {"iterations": 20, "chunk_iterations": 5, "torch_iterations": 5, "sweep": [10, 100, 300], "window": 10, "transformer_max": 300}
# The runtime's latency targets for the robotwin preset (1024 points, batch 1) on a 2-core CPU.
TARGETS = {
    "history_step_p50_ms": 1.5,
    "history_step_p95_ms": 2.5,
    "denoiser_chunk_p50_ms": 25.0,
    "history_growth_10k": 0.05,  # per-step cost at the longest history vs the shortest
    "ort_vs_eager_chunk": 3.0,  # ORT at least this many times faster than eager PyTorch
}


def random_observation(policy: OnnxPolicy, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    n_points = policy.manifest["model_config"]["n_points"]
    return (
        rng.standard_normal((1, n_points, policy.point_dim), dtype=np.float32),
        rng.standard_normal((1, policy.state_dim), dtype=np.float32),
    )


def profile_components(policy: OnnxPolicy, settings: dict, rng) -> dict[str, Any]:
    pc, pos = random_observation(policy, rng)
    policy.reset()
    history = time_calls(lambda: policy.observe(pc, pos), settings["iterations"])
    chunk = time_calls(lambda: policy.act(seed=0), settings["chunk_iterations"])
    tick = time_calls(lambda: (policy.observe(pc, pos), policy.act(seed=0)), settings["chunk_iterations"])
    return {"history_step": history, "denoiser_chunk": chunk, "chunk_tick": tick}


def history_sweep(step, lengths: list[int], window: int) -> list[dict[str, float]]:
    """Per-step cost and resident memory at each history length; ``step()`` adds one observation."""
    rows, done = [], 0
    for length in lengths:
        while done < length - window:
            step()
            done += 1
        samples = time_calls(step, window, warmup=0)
        done += window
        rows.append({"length": length, "p50_ms": float(np.median(samples)), "rss_mib": resident_memory_mib()})
    return rows


def check_source(model_dir: Path, checkpoint: Path, manifest: dict) -> None:
    """``--checkpoint`` must be the run the model was exported from: its weights file's sha256 is the manifest's."""
    import hashlib

    source = manifest["source"]
    path = Path(checkpoint) / source["weights"]
    try:
        digest = hashlib.sha256(path.read_bytes()).hexdigest()
    except OSError as exc:
        raise ModelDirError(f"--checkpoint {checkpoint}: {path} cannot be read ({exc.strerror or exc}); give the run "
                            f"directory {model_dir} was exported from") from None
    if digest != source["sha256"]:
        raise ModelDirError(f"--checkpoint {checkpoint} is not the run {model_dir} was exported from ({source['weights']} "
                            f"sha256 {digest[:12]}…, the model's source {source['sha256'][:12]}… of run "
                            f"{source.get('run', '?')!r} step {source['step']}); give that run, or export this one")


def torch_comparisons(model_dir: Path, checkpoint: Path | None, manifest: dict, settings: dict, threads: int | None):
    """Eager PyTorch, TorchScript and a causal Transformer history encoder, when torch is available."""
    try:
        import torch
    except ImportError:
        return {"skipped": "torch is not installed: no PyTorch comparison"}
    if threads:
        torch.set_num_threads(threads)
    out: dict[str, Any] = {}
    m = manifest["model_config"]
    rng = torch.Generator().manual_seed(0)
    pc = torch.randn(1, m["n_points"], m["point_dim"], generator=rng)
    pos = torch.randn(1, m["state_dim"], generator=rng)
    if checkpoint is not None:
        from dssp_train.model.streaming import StreamingPolicy
        from dssp_train.training.checkpoint import load_policy

        check_source(model_dir, checkpoint, manifest)
        policy, _ = load_policy(checkpoint, weights=manifest["source"]["weights"])
        stream = StreamingPolicy(policy)
        with torch.inference_mode():
            out["eager_history_step"] = time_calls(lambda: stream.observe(pc, pos), settings["iterations"])
            out["eager_denoiser_chunk"] = time_calls(
                lambda: stream.act(seed=0, num_steps=manifest["denoise_steps"]), settings["torch_iterations"]
            )
    files = {g: manifest["graphs"][g]["files"].get("torchscript") for g in ("history_step", "denoiser")}
    if all(files.values()):
        import io

        history = torch.jit.load(io.BytesIO(read_graph(model_dir, manifest, "history_step", "torchscript")[1]))
        denoiser = torch.jit.load(io.BytesIO(read_graph(model_dir, manifest, "denoiser", "torchscript")[1]))
        state_specs = [s for s in manifest["graphs"]["history_step"]["inputs"] if s["name"] in manifest["history_state"]]
        state = [torch.zeros([1, *s["shape"][1:]]) for s in state_specs]
        with torch.inference_mode():
            out["torchscript_history_step"] = time_calls(lambda: history(pc, pos, *state), settings["iterations"])
            inputs = []
            if manifest["use_history"]:
                inputs.append(torch.zeros(1, m["d_model"]))
            if manifest["use_recent_states"]:
                inputs.append(torch.zeros(1, m["n_obs_steps"], m["d_model"]))
            noise = torch.randn(1, m["horizon"], m["action_dim"], generator=rng)
            out["torchscript_denoiser_chunk"] = time_calls(lambda: denoiser(*inputs, noise), settings["torch_iterations"])
    # Paper Table 3's alternative: a causal Transformer over the full history (same width and depth).
    from dssp_train.model.history_encoder import CausalTransformer

    heads = 8 if m["d_model"] % 8 == 0 else 4
    net = CausalTransformer(m["d_model"], m["n_history_layers"], heads).eval()
    rows = []
    for length in (n for n in settings["sweep"] if n <= settings["transformer_max"]):
        past = torch.randn(1, length - 1, m["d_model"], generator=rng)

        def transformer_step():
            with torch.inference_mode():
                net(torch.cat([past, torch.randn(1, 1, m["d_model"])], dim=1))[:, -1]

        samples = time_calls(transformer_step, 3, warmup=1)
        rows.append({"length": length, "p50_ms": float(np.median(samples)), "rss_mib": resident_memory_mib()})
    out["transformer_sweep"] = rows
    return out


def run_profile(model_dir: Path, checkpoint: Path | None, quick: bool, threads: int | None, precision: str = "fp32") -> dict[str, Any]:
    settings = QUICK if quick else FULL
    rng = np.random.default_rng(0)
    rss_before = resident_memory_mib()
    policy = OnnxPolicy(model_dir, threads=threads, precision=precision)
    rss_loaded = resident_memory_mib()
    manifest = policy.manifest
    m = manifest["model_config"]
    components = profile_components(policy, settings, rng)
    stats = {k: LatencyStats.of(v).to_dict() for k, v in components.items()}

    pc, pos = random_observation(policy, rng)
    policy.reset()
    sweep = history_sweep(lambda: policy.observe(pc, pos), settings["sweep"], settings["window"])

    peak = gemm_peak_gflops()
    flops = {"history_step": history_step_flops(m, m["n_points"]), "denoiser_chunk": chunk_flops(m, manifest["denoise_steps"])}
    achieved = {k: flops[k] / (stats[k]["p50"] / 1e3) / 1e9 for k in flops}
    floor = chunk_floor(model_dir, manifest, flops["denoiser_chunk"], peak, PRECISIONS[precision])
    breakdown = graph_breakdowns(policy, model_dir, threads, runs=2 if quick else 5)
    comparisons = torch_comparisons(model_dir, checkpoint, manifest, settings, threads)
    comp_stats = {k: LatencyStats.of(v).to_dict() for k, v in comparisons.items() if isinstance(v, list) and k != "transformer_sweep"}
    return {
        "model_dir": str(model_dir),
        "precision": precision,
        "machine": {"processor": platform.processor() or platform.machine(), "threads": threads, "gemm_peak_gflops": peak},
        "settings": {"quick": quick, **settings},
        "memory_mib": {"before_load": rss_before, "after_load": rss_loaded, "after_profile": resident_memory_mib()},
        "latency_ms": stats,
        "samples_ms": components,
        "history_sweep": sweep,
        "flops": flops,
        "achieved_gflops": achieved,
        "fraction_of_peak": {k: v / peak for k, v in achieved.items()},
        "chunk_floor": floor,
        "torch": {**comp_stats, "transformer_sweep": comparisons.get("transformer_sweep"), "skipped": comparisons.get("skipped")},
        "op_breakdown": breakdown,
    }


def chunk_floor(model_dir: Path, manifest: dict, chunk_flops_: int, peak_gflops: float, fmt: str = "onnx") -> dict[str, Any]:
    """The least time one chunk can take here: compute at the GEMM peak, or re-reading the weights per DDIM step.

    The denoiser graph's file is almost entirely its weights; the K DDIM steps run every layer in turn, so
    when the weights do not fit in the last-level cache each step streams them from memory again."""
    weights = graph_file(model_dir, manifest, DENOISER_GRAPH, fmt).stat().st_size
    cache = last_level_cache_bytes()
    bandwidth = memory_read_gbs()
    steps = manifest["denoise_steps"]
    streams = cache is None or weights > cache
    stream_ms = steps * weights / (bandwidth * 1e9) * 1e3 if streams else None
    compute_ms = chunk_flops_ / (peak_gflops * 1e9) * 1e3
    return {"compute_ms": compute_ms, "weights_mib": weights / 2**20, "cache_mib": cache / 2**20 if cache else None,
            "read_gbs": bandwidth, "denoise_steps": steps, "weight_stream_ms": stream_ms,
            "floor_ms": max(compute_ms, stream_ms or 0.0)}


def graph_breakdowns(policy: OnnxPolicy, model_dir: Path, threads: int | None, runs: int) -> dict[str, list[dict]]:
    """Per graph, kernel time by operator type (ONNX Runtime's profiler), on the inputs of a live episode."""
    rng = np.random.default_rng(1)
    pc, pos = random_observation(policy, rng)
    policy.reset()
    policy.observe(pc, pos)
    history_feeds = {"point_cloud": pc, "agent_pos": pos, **policy.state} if policy.use_history else {"point_cloud": pc, "agent_pos": pos}
    denoiser_feeds = {**policy.denoiser_inputs(), "noise": policy.noise(1, seed=0)}
    manifest, fmt = policy.manifest, PRECISIONS[policy.precision]
    return {
        "history_step": op_type_breakdown(graph_file(model_dir, manifest, HISTORY_GRAPH, fmt), history_feeds, threads, runs),
        "denoiser_chunk": op_type_breakdown(graph_file(model_dir, manifest, DENOISER_GRAPH, fmt), denoiser_feeds, threads, runs),
    }


def target_rows(report: dict[str, Any]) -> list[tuple[str, float, float, bool, str]]:
    """(figure, measured, target, met, how far) for each target the run has a figure for."""
    lat, sweep, torch_stats = report["latency_ms"], report["history_sweep"], report["torch"]
    rows = []

    def upper(name, measured, target, unit):
        met = measured <= target
        rows.append((name, measured, target, met, "met" if met else f"{measured / target:.2f}x the target ({measured - target:+.3g} {unit})".replace(" )", ")")))

    upper("history step p50 ms", lat["history_step"]["p50"], TARGETS["history_step_p50_ms"], "ms")
    upper("history step p95 ms", lat["history_step"]["p95"], TARGETS["history_step_p95_ms"], "ms")
    upper("denoiser chunk p50 ms", lat["denoiser_chunk"]["p50"], TARGETS["denoiser_chunk_p50_ms"], "ms")
    floor = report["chunk_floor"]["floor_ms"]
    if floor > TARGETS["denoiser_chunk_p50_ms"]:
        rows[-1] = (*rows[-1][:4], rows[-1][4] + f"; this machine's floor for it is {floor:.3g} ms")
    growth = abs(sweep[-1]["p50_ms"] / sweep[0]["p50_ms"] - 1)
    upper(f"history step cost change {sweep[0]['length']} → {sweep[-1]['length']} steps (fraction)", growth, TARGETS["history_growth_10k"], "")
    if "eager_denoiser_chunk" in torch_stats:
        ratio = torch_stats["eager_denoiser_chunk"]["p50"] / lat["denoiser_chunk"]["p50"]
        met = ratio >= TARGETS["ort_vs_eager_chunk"]
        rows.append(("ORT vs eager per chunk (x faster)", ratio, TARGETS["ort_vs_eager_chunk"], met, "met" if met else f"{ratio / TARGETS['ort_vs_eager_chunk']:.2f}x the target"))
    return rows


def markdown(report: dict[str, Any]) -> str:
    lat, torch_stats = report["latency_ms"], report["torch"]
    lines = [
        f"Model: {report['model_dir']} ({report['precision']} graphs) — GEMM peak {report['machine']['gemm_peak_gflops']:.0f} GFLOP/s (numpy float32)",
        "",
        "| component | p50 ms | p95 ms | p99 ms | max ms | GFLOP/s | of peak |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for key, label in (("history_step", "history step (ORT)"), ("denoiser_chunk", "denoiser chunk (ORT)"), ("chunk_tick", "chunk tick: both (ORT)")):
        s = lat[key]
        gf = report["achieved_gflops"].get(key)
        extra = f"{gf:.1f} | {100 * report['fraction_of_peak'][key]:.1f} %" if gf is not None else " | "
        lines.append(f"| {label} | {s['p50']:.2f} | {s['p95']:.2f} | {s['p99']:.2f} | {s['max']:.2f} | {extra} |")
    for key, label in (
        ("eager_history_step", "history step (PyTorch eager)"),
        ("eager_denoiser_chunk", "denoiser chunk (PyTorch eager)"),
        ("torchscript_history_step", "history step (TorchScript)"),
        ("torchscript_denoiser_chunk", "denoiser chunk (TorchScript)"),
    ):
        if key in torch_stats:
            s = torch_stats[key]
            lines.append(f"| {label} | {s['p50']:.2f} | {s['p95']:.2f} | {s['p99']:.2f} | {s['max']:.2f} | | |")
    if "eager_denoiser_chunk" in torch_stats:
        ratio = torch_stats["eager_denoiser_chunk"]["p50"] / lat["denoiser_chunk"]["p50"]
        lines += ["", f"ONNX Runtime vs PyTorch eager per chunk: {ratio:.1f}x faster (p50, same run)"]
    lines += ["", "| history length | DSSP step p50 ms | RSS MiB | Transformer (full history) step p50 ms |", "|---:|---:|---:|---:|"]
    tf = {r["length"]: r for r in (torch_stats.get("transformer_sweep") or [])}
    for r in report["history_sweep"]:
        t = tf.get(r["length"])
        lines.append(f"| {r['length']} | {r['p50_ms']:.3f} | {r['rss_mib']:.0f} | {t['p50_ms']:.2f} |" if t else f"| {r['length']} | {r['p50_ms']:.3f} | {r['rss_mib']:.0f} | |")
    sweep = report["history_sweep"]
    growth = sweep[-1]["p50_ms"] / sweep[0]["p50_ms"] - 1
    lines += ["", f"DSSP per-step cost at {sweep[-1]['length']} steps vs {sweep[0]['length']}: {100 * growth:+.1f} %; "
              f"memory {sweep[-1]['rss_mib'] - sweep[0]['rss_mib']:+.1f} MiB"]
    mem = report["memory_mib"]
    lines.append(f"Resident memory: {mem['before_load']:.0f} MiB before load, {mem['after_load']:.0f} after, {mem['after_profile']:.0f} at the end")
    if torch_stats.get("skipped"):
        lines.append(torch_stats["skipped"])
    f = report["chunk_floor"]
    stream = (f"{f['weights_mib']:.1f} MiB of weights{' > ' + format(f['cache_mib'], '.0f') + ' MiB last-level cache' if f['cache_mib'] else ''}, "
              f"re-read by each of the {f['denoise_steps']} DDIM steps at {f['read_gbs']:.1f} GB/s = {f['weight_stream_ms']:.1f} ms"
              if f["weight_stream_ms"] is not None else f"{f['weights_mib']:.1f} MiB of weights stay in the {f['cache_mib']:.0f} MiB last-level cache")
    lines.append(f"Chunk floor on this machine: {f['floor_ms']:.1f} ms — compute at the GEMM peak {f['compute_ms']:.1f} ms; {stream}")
    for graph, label in (("history_step", "history step"), ("denoiser_chunk", "denoiser chunk")):
        rows = report["op_breakdown"][graph]
        top = ", ".join(f"{r['op']} {100 * r['share']:.0f} % ({r['nodes']} nodes)" for r in rows[:5])
        lines.append(f"Where the {label} goes (ORT profiler, kernel time): {top}; elementwise/copy ops {100 * elementwise_share(rows):.0f} %")
    lines += ["", "| target (robotwin preset, 2-core CPU) | measured | target | |", "|---|---:|---:|---|"]
    for name, measured, target, _, how in target_rows(report):
        lines.append(f"| {name} | {measured:.3g} | {target:.3g} | {how} |")
    return "\n".join(lines)


def plot(report: dict[str, Any], path: Path, force: bool = False) -> None:
    try:
        import matplotlib
    except ImportError:
        raise SystemExit("error: --plot needs matplotlib (pip install matplotlib)") from None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4))
    sweep = report["history_sweep"]
    ax1.plot([r["length"] for r in sweep], [r["p50_ms"] for r in sweep], "o-", label="DSSP (Mamba, ORT)")
    tf = report["torch"].get("transformer_sweep")
    if tf:
        ax1.plot([r["length"] for r in tf], [r["p50_ms"] for r in tf], "s-", label="causal Transformer, full history (torch)")
    ax1.set(xscale="log", yscale="log", xlabel="history length (steps)", ylabel="one history update, p50 ms", title="Per-step cost vs history")
    ax1.legend()
    samples = [report["samples_ms"][k] for k in ("history_step", "denoiser_chunk")]
    bins = np.geomspace(min(map(min, samples)) * 0.9, max(map(max, samples)) * 1.1, 50)
    for values, label in zip(samples, ("history step", "denoiser chunk")):
        ax2.hist(values, bins=bins, alpha=0.6, label=label)
    ax2.set(xscale="log", xlabel="latency ms", ylabel="calls", title="Latency distribution (ORT)")
    ax2.xaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
    ax2.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax2.legend()
    fig.tight_layout()
    from dssp_data.output_guard import write_output_file

    write_output_file(path, lambda tmp: fig.savefig(tmp, format="png", dpi=100), force=force, flag="--plot")
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    from dssp_data.cli_runner import run_cli

    p = ArgumentParser(prog="dssp-profile", description="CPU latency and memory of an exported DSSP model.")
    p.add_argument("model_dir", type=Path)
    p.add_argument("--checkpoint", type=Path, help="the run directory it was exported from, for the PyTorch eager comparison")
    p.add_argument("--quick", action="store_true", help="short run (tests, CI)")
    p.add_argument("--precision", choices=sorted(PRECISIONS), default="fp32",
                   help="which graphs to time: fp32, or int8 (export --quantize int8); PyTorch runs in fp32")
    p.add_argument("--threads", type=int, help="ONNX Runtime (and torch) intra-op threads (default: all CPUs)")
    p.add_argument("--json", type=Path, help="write every figure here")
    p.add_argument("--plot", type=Path, help="write a PNG here")
    p.add_argument("--force", action="store_true", help="replace existing --json and --plot files")
    args = p.parse_args(argv)

    def _main() -> int:
        from dssp_deploy.sessions import check_threads
        from dssp_data.output_guard import check_output_file, write_output_text

        check_threads(args.threads)
        if args.checkpoint is not None:  # before minutes of profiling
            from dssp_deploy.manifest import read_manifest

            check_source(args.model_dir, args.checkpoint, read_manifest(args.model_dir))
        for path, flag in ((args.json, "--json"), (args.plot, "--plot")):
            if path is not None:
                check_output_file(path, force=args.force, flag=flag)
        t0 = time.perf_counter()
        report = run_profile(args.model_dir, args.checkpoint, args.quick, args.threads, args.precision)
        report["profile_seconds"] = time.perf_counter() - t0
        print(markdown(report))
        if args.json:
            write_output_text(args.json, json.dumps(report, indent=2) + "\n", force=args.force, flag="--json")
        if args.plot:
            plot(report, args.plot, force=args.force)
        return 0

    return run_cli(_main)


if __name__ == "__main__":
    sys.exit(main())

"""``dssp-profile``: CPU latency and memory of an exported DSSP model, in numbers and a plot.

    dssp-profile MODEL_DIR [--precision fp32|int8|int4] [--kernel auto|fused|standard] [--quick] [--threads N]
                           [--json PATH] [--plot PATH] [--force]

Measures, for the model directory given (batch 1, the model's point count), with ONNX Runtime and numpy only:
- per component — history step, denoiser chunk (K DDIM steps), the chunk tick (both) — p50/p95/p99/max
  over many calls after warm-up, and the resident memory;
- a history-length sweep from 10 to 10,000 steps: the cost of one history update at each length and the
  memory (DSSP's claim: constant);
- achieved GFLOP/s against this machine's own float32 GEMM peak (numpy), and the chunk's floor on this
  machine: its flops at that peak, and — when the denoiser's weights exceed the last-level cache, so each
  of the K DDIM steps reads them from memory again (the first step carries the prefix) — K x weight bytes at
  the measured read bandwidth, as the exporter counted the reads (:func:`weight_passes`, :func:`roofline`).
- paths and threads: history step and chunk p50 on the fused Mamba kernel's graphs and on the standard
  ones, each at 1 thread and at ``--threads`` (default: all CPUs), with the speed-up of the threads — to
  extrapolate to a robot computer with more cores;
- the tick with the next chunk prefetched in the background (the control loop's ``prefetch``): the
  history step gets one thread and the chunk the others; the tick's p99 against the history step's p99.
Prints a Markdown table; ``--json`` writes every figure (ms, MiB); ``--plot`` a PNG. Both are new files or,
with ``--force``, replace existing ones (checked before profiling; written to a temporary name and renamed).
The same model under PyTorch eager and TorchScript, and a causal Transformer history encoder over the full
history, are measured against these figures by ``benchmarks/torch_comparison.py``.
"""

from __future__ import annotations

import json
import platform
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from dssp_core.cli_runner import ArgumentParser, run_cli
from dssp_core.output_guard import check_output_file, write_output_figure, write_output_text
from dssp_core.schema import DEFAULT_CONTROL_RATE_HZ
from dssp_deploy.control_loop import ChunkedControl
from dssp_deploy.flops import chunk_flops, history_step_flops
from dssp_deploy.latency import (
    LatencyStats,
    effective_cache_bytes,
    gemm_peak_gflops,
    last_level_cache_bytes,
    memory_read_gbs,
    read_bandwidth_by_size,
    resident_memory_mib,
    time_calls,
)
from dssp_deploy.manifest import (
    DENOISER_GRAPH,
    HISTORY_GRAPH,
    Manifest,
    file_kind,
    graph_file,
    read_graph_files,
    read_manifest,
)
from dssp_deploy.onnx_policy import OnnxPolicy, add_runtime_arguments, choose_graphs
from dssp_deploy.op_breakdown import elementwise_share, op_type_breakdown
from dssp_deploy.schedules import Plain
from dssp_deploy.sessions import check_threads, default_threads

FULL = {
    "iterations": 300,
    "chunk_iterations": 100,
    "sweep": [10, 100, 1000, 3000, 10000],
    "window": 50,
    "matrix_iterations": 100,
    "matrix_chunks": 20,
    "prefetch_ticks": 300,
}
QUICK = {
    "iterations": 20,
    "chunk_iterations": 5,
    "sweep": [10, 100, 300],
    "window": 10,
    "matrix_iterations": 10,
    "matrix_chunks": 3,
    "prefetch_ticks": 24,
}
# The runtime's latency targets for the robotwin preset (1024 points, batch 1) on a 2-core CPU.
TARGETS = {
    "history_step_p50_ms": 1.5,
    "history_step_p95_ms": 2.5,
    "denoiser_chunk_p50_ms": 25.0,
    "history_growth_10k": 0.05,  # per-step cost at the longest history vs the shortest
    "prefetch_tick_p99_over_history_p99": 1.5,
}


def random_observation(policy: OnnxPolicy, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """point_cloud (1, P, point_dim), agent_pos (1, S) drawn from the training ranges (the runtime refuses others)."""
    return policy.example_observation(rng)


def profile_components(policy: OnnxPolicy, settings: dict, rng) -> dict[str, Any]:
    pc, pos = random_observation(policy, rng)
    policy.reset()
    history = time_calls(lambda: policy.observe(pc, pos), settings["iterations"])
    chunk = time_calls(lambda: policy.act(seed=0), settings["chunk_iterations"])
    tick = time_calls(lambda: (policy.observe(pc, pos), policy.act(seed=0)), settings["chunk_iterations"])
    return {"history_step": history, "denoiser_chunk": chunk, "chunk_tick": tick}


def paths_and_threads(model_dir: Path, precision: str, threads: int, settings: dict, rng) -> list[dict[str, Any]]:
    """History step and chunk p50 per graph set (fused when the kernel loads, standard) at 1 and ``threads`` threads
    (the chunk's threads spinning during a chunk, the default), and with ``threads`` > 1 once more with ``--no-spin``."""
    rows = []
    kernels = ["fused", "standard"] if choose_graphs(read_manifest(model_dir), precision)[0] else ["standard"]
    for kernel in kernels:
        for n, spinning in [(1, None)] + ([(threads, None), (threads, False)] if threads > 1 else []):
            policy = OnnxPolicy(model_dir, threads=n, precision=precision, kernel=kernel, spinning=spinning)
            pc, pos = random_observation(policy, rng)
            policy.reset()
            history = LatencyStats.of(time_calls(lambda: policy.observe(pc, pos), settings["matrix_iterations"]))
            chunk = LatencyStats.of(time_calls(lambda: policy.act(seed=0), settings["matrix_chunks"]))
            rows.append(
                {
                    "kernel": kernel,
                    "threads": n,
                    "spinning": policy.spinning,
                    "history_step_p50": history.p50,
                    "history_step_p99": history.p99,
                    "chunk_p50": chunk.p50,
                }
            )
    for row in rows:
        one = next(r for r in rows if r["kernel"] == row["kernel"] and r["threads"] == 1)
        row["history_speedup_vs_1"] = one["history_step_p50"] / row["history_step_p50"]
        row["chunk_speedup_vs_1"] = one["chunk_p50"] / row["chunk_p50"]
    return rows


def prefetch_ticks(model_dir: Path, precision: str, kernel: str, threads: int, ticks: int, rng) -> dict[str, Any]:
    """Real-time ticks at the model's control rate with the next chunk prefetched: the tick's latency against
    the history step's, measured on the same sessions (history on one thread, the chunk on the others)."""

    policy = OnnxPolicy(model_dir, threads=threads, precision=precision, kernel=kernel, background_chunks=True)
    pc, pos = random_observation(policy, rng)
    policy.reset()
    alone = LatencyStats.of(time_calls(lambda: policy.observe(pc, pos), max(ticks, 20)))
    rate = policy.contract.control_rate_hz or DEFAULT_CONTROL_RATE_HZ
    try:
        loop = ChunkedControl(policy, Plain(prefetch=True), control_rate_hz=rate, seed=0)
    except ValueError as exc:  # the chunk is too slow to be started early enough at this rate
        return {
            "rate_hz": rate,
            "ticks": 0,
            "possible": False,
            "reason": str(exc),
            "threads": dict(policy.threads),
            "history_step_alone": alone.to_dict(),
            "tick_p99_over_history_p99": None,
        }
    period = 1.0 / rate
    tick_ms, waited, next_at = [], 0, time.perf_counter()
    for _ in range(ticks):
        t0 = time.perf_counter()
        _, info = loop.tick(pc, pos)
        tick_ms.append((time.perf_counter() - t0) * 1e3)
        waited += info.over_budget
        next_at += period
        time.sleep(max(0.0, next_at - time.perf_counter()))
    loop.reset()
    ticks_stats = LatencyStats.of(tick_ms)
    return {
        "rate_hz": rate,
        "ticks": ticks,
        "possible": True,
        "lead_ticks": loop.schedule.lead,
        "threads": dict(policy.threads),
        "history_step_alone": alone.to_dict(),
        "tick": ticks_stats.to_dict(),
        "chunks_late": int(waited),
        "tick_p99_over_history_p99": ticks_stats.p99 / alone.p99,
    }


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


def run_profile(
    model_dir: Path,
    quick: bool,
    threads: int | None,
    precision: str | None = None,
    kernel: str = "auto",
    spinning: bool | None = None,
) -> dict[str, Any]:
    """Every figure of one profiling run of the model directory (see the module's docstring)."""
    settings = QUICK if quick else FULL
    rng = np.random.default_rng(0)
    rss_before = resident_memory_mib()
    policy = OnnxPolicy(model_dir, threads=threads, precision=precision, kernel=kernel, spinning=spinning)
    precision = policy.precision  # the default resolved
    rss_loaded = resident_memory_mib()
    manifest = policy.manifest
    m = manifest.model_config
    components = profile_components(policy, settings, rng)
    stats = {k: LatencyStats.of(v).to_dict() for k, v in components.items()}

    pc, pos = random_observation(policy, rng)
    policy.reset()
    sweep = history_sweep(lambda: policy.observe(pc, pos), settings["sweep"], settings["window"])

    peak = gemm_peak_gflops()
    flops = {
        "history_step": history_step_flops(m, m["n_points"]),
        "denoiser_chunk": chunk_flops(m, manifest.contract.denoise_steps),
    }
    achieved = {k: flops[k] / (stats[k]["p50"] / 1e3) / 1e9 for k in flops}
    floor = chunk_floor(model_dir, manifest, flops["denoiser_chunk"], peak, file_kind(precision, policy.fused))
    breakdown = graph_breakdowns(policy, model_dir, threads, runs=2 if quick else 5)
    used, note = policy.kernel, policy.kernel_note
    n_threads = threads or default_threads()
    matrix = paths_and_threads(model_dir, precision, n_threads, settings, rng)
    prefetch = prefetch_ticks(model_dir, precision, used, n_threads, settings["prefetch_ticks"], rng)
    return {
        "model_dir": str(model_dir),
        "precision": precision,
        "kernel": used,
        "kernel_note": note,
        "paths_and_threads": matrix,
        "prefetch": prefetch,
        "machine": {
            "processor": platform.processor() or platform.machine(),
            "threads": threads,
            "gemm_peak_gflops": peak,
        },
        "settings": {"quick": quick, **settings},
        "memory_mib": {"before_load": rss_before, "after_load": rss_loaded, "after_profile": resident_memory_mib()},
        "latency_ms": stats,
        "samples_ms": components,
        "history_sweep": sweep,
        "flops": flops,
        "achieved_gflops": achieved,
        "fraction_of_peak": {k: v / peak for k, v in achieved.items()},
        "chunk_floor": floor,
        "op_breakdown": breakdown,
    }


def weight_passes(manifest: Manifest, fmt: str = "onnx") -> int:
    """How often one chunk of the denoiser's ``fmt`` graph reads every weight, as the exporter counted it in the
    graph (``weight_reads``); for a model exported before it counted: once per DDIM step, and once more for the
    prefix when its state is computed once and serves the K steps (the timestep decoupled, K > 1)."""
    reads = manifest.files.get(manifest.graphs[DENOISER_GRAPH]["files"].get(fmt), {}).get("weight_reads")
    if reads:
        return reads
    steps = manifest.contract.denoise_steps
    return steps + 1 if steps > 1 and manifest.model.timestep_decoupled else steps


def roofline(model_dir: Path, manifest: Manifest, fmt: str, chunk_ms: float, read_gbs: float) -> dict[str, Any]:
    """One chunk against the least time reading its weights allows: the denoiser graph's bytes (``fmt``'s file: its
    weights, nearly all of it) read :func:`weight_passes` times at ``read_gbs``; ``ratio`` = achieved / floor."""
    weights = graph_file(model_dir, manifest, DENOISER_GRAPH, fmt).stat().st_size
    passes = weight_passes(manifest, fmt)
    floor = passes * weights / (read_gbs * 1e9) * 1e3
    return {
        "graph": fmt,
        "weights_mib": weights / 2**20,
        "passes": passes,
        "read_gbs": read_gbs,
        "floor_ms": floor,
        "chunk_ms": chunk_ms,
        "ratio": chunk_ms / floor,
    }


def chunk_floor(
    model_dir: Path,
    manifest: Manifest,
    chunk_flops_: int,
    peak_gflops: float,
    fmt: str = "onnx",
) -> dict[str, Any]:
    """The least time one chunk can take here: compute at the GEMM peak, or re-reading the weights per DDIM step.

    The peak is numpy's float32 GEMM's, so it bounds an fp32 graph only: int8 products run several times faster
    (``vpdpbusd`` multiplies four int8 pairs where an FMA multiplies one float pair), so an int8 or int4 graph gets no
    compute term (``compute_ms`` None) and its floor is the weights' stream; None where neither applies (its weights
    stay in the cache).

    The denoiser graph's file is almost entirely its weights; the K DDIM steps run every layer in turn, so
    when the weights do not fit in the last-level cache each step streams them from memory again. The cache
    is the smaller of the CPU's last-level cache and the one this process measurably gets (on a shared
    machine other tenants hold the rest: :func:`dssp_deploy.latency.effective_cache_bytes`)."""
    weights = graph_file(model_dir, manifest, DENOISER_GRAPH, fmt).stat().st_size
    cpu_cache = last_level_cache_bytes()
    probe = read_bandwidth_by_size()
    effective = effective_cache_bytes(probe)
    cache = min(c for c in (cpu_cache, effective) if c) if (cpu_cache or effective) else None
    bandwidth = memory_read_gbs()
    steps = manifest.contract.denoise_steps
    streams = cache is None or weights > cache
    passes = weight_passes(manifest, fmt)
    stream_ms = passes * weights / (bandwidth * 1e9) * 1e3 if streams else None
    fp32 = fmt in (file_kind("fp32"), file_kind("fp32", fused=True))
    compute_ms = chunk_flops_ / (peak_gflops * 1e9) * 1e3 if fp32 else None
    known = [ms for ms in (compute_ms, stream_ms) if ms is not None]
    return {
        "compute_ms": compute_ms,
        "weights_mib": weights / 2**20,
        "cache_mib": cache / 2**20 if cache else None,
        "cpu_cache_mib": cpu_cache / 2**20 if cpu_cache else None,
        "read_gbs_by_mib": dict(probe),
        "read_gbs": bandwidth,
        "denoise_steps": steps,
        "weight_passes": passes,
        "weight_stream_ms": stream_ms,
        "floor_ms": max(known) if known else None,
    }


def graph_breakdowns(policy: OnnxPolicy, model_dir: Path, threads: int | None, runs: int) -> dict[str, list[dict]]:
    """Per graph, kernel time by operator type (ONNX Runtime's profiler), on the inputs of a live episode."""
    rng = np.random.default_rng(1)
    pc, pos = random_observation(policy, rng)
    policy.reset()
    policy.observe(pc, pos)
    history_feeds = (
        {"point_cloud": pc, "agent_pos": pos, **policy.state}
        if policy.manifest.model.use_history
        else {"point_cloud": pc, "agent_pos": pos}
    )
    denoiser_feeds = {**policy.denoiser_inputs(), "noise": policy.noise(1, seed=0)}
    manifest, fmt = policy.manifest, file_kind(policy.precision, policy.fused)
    breakdowns = {}
    for name, graph, feeds in (
        ("history_step", HISTORY_GRAPH, history_feeds),
        ("denoiser_chunk", DENOISER_GRAPH, denoiser_feeds),
    ):
        path, data, external = read_graph_files(
            model_dir, manifest, graph, fmt
        )  # the checked bytes, as the runtime loads them
        breakdowns[name] = op_type_breakdown(
            path, feeds, threads, runs, fused=policy.fused, model=data, external=external
        )
    return breakdowns


def target_rows(report: dict[str, Any]) -> list[tuple[str, float, float, bool, str]]:
    """(figure, measured, target, met, how far) for each target the run has a figure for."""
    lat, sweep = report["latency_ms"], report["history_sweep"]
    rows = []

    def upper(name, measured, target, unit):
        met = measured <= target
        rows.append(
            (
                name,
                measured,
                target,
                met,
                "met"
                if met
                else f"{measured / target:.2f}x the target ({measured - target:+.3g} {unit})".replace(" )", ")"),
            )
        )

    upper("history step p50 ms", lat["history_step"]["p50"], TARGETS["history_step_p50_ms"], "ms")
    upper("history step p95 ms", lat["history_step"]["p95"], TARGETS["history_step_p95_ms"], "ms")
    upper("denoiser chunk p50 ms", lat["denoiser_chunk"]["p50"], TARGETS["denoiser_chunk_p50_ms"], "ms")
    floor = report["chunk_floor"]["floor_ms"]
    if floor is not None and floor > TARGETS["denoiser_chunk_p50_ms"]:
        rows[-1] = (*rows[-1][:4], rows[-1][4] + f"; this machine's floor for it is {floor:.3g} ms")
    growth = abs(sweep[-1]["p50_ms"] / sweep[0]["p50_ms"] - 1)
    upper(
        f"history step cost change {sweep[0]['length']} → {sweep[-1]['length']} steps (fraction)",
        growth,
        TARGETS["history_growth_10k"],
        "",
    )
    if report["prefetch"]["possible"]:
        upper(
            "tick p99 with prefetch / history step p99",
            report["prefetch"]["tick_p99_over_history_p99"],
            TARGETS["prefetch_tick_p99_over_history_p99"],
            "",
        )
    return rows


def markdown(report: dict[str, Any]) -> str:
    lat = report["latency_ms"]
    lines = [
        f"Model: {report['model_dir']} ({report['precision']} graphs, {report['kernel_note']}) — "
        f"GEMM peak {report['machine']['gemm_peak_gflops']:.0f} GFLOP/s (numpy float32)",
        "",
        "| component | p50 ms | p95 ms | p99 ms | max ms | GFLOP/s | of peak |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for key, label in (
        ("history_step", "history step (ORT)"),
        ("denoiser_chunk", "denoiser chunk (ORT)"),
        ("chunk_tick", "chunk tick: both (ORT)"),
    ):
        s = lat[key]
        gf = report["achieved_gflops"].get(key)
        extra = f"{gf:.1f} | {100 * report['fraction_of_peak'][key]:.1f} %" if gf is not None else " | "
        lines.append(f"| {label} | {s['p50']:.2f} | {s['p95']:.2f} | {s['p99']:.2f} | {s['max']:.2f} | {extra} |")
    lines += [
        "",
        "| graphs | threads | history step p50 ms | p99 ms | chunk p50 ms | history speed-up | chunk speed-up |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in report["paths_and_threads"]:
        spin = ", --no-spin" if r["threads"] > 1 and not r["spinning"] else ""
        lines.append(
            f"| {r['kernel']}{spin} | {r['threads']} | {r['history_step_p50']:.2f} | {r['history_step_p99']:.2f} | {r['chunk_p50']:.2f} | "
            f"{r['history_speedup_vs_1']:.2f}x | {r['chunk_speedup_vs_1']:.2f}x |"
        )
    pf = report["prefetch"]
    if not pf["possible"]:
        lines += ["", f"Prefetch: not possible here ({pf['reason']})"]
    else:
        lines += [
            "",
            f"Prefetch: {pf['ticks']} real-time ticks at {pf['rate_hz']:g} Hz, each chunk started {pf['lead_ticks']} tick(s) early "
            f"(history {pf['threads']['history_step']} thread, chunk {pf['threads']['denoiser']}): tick p50 {pf['tick']['p50']:.2f} ms, "
            f"p99 {pf['tick']['p99']:.2f} ms against the history step alone p99 {pf['history_step_alone']['p99']:.2f} ms "
            f"({pf['tick_p99_over_history_p99']:.2f}x); chunks late: {pf['chunks_late']}",
        ]
    lines += ["", "| history length | DSSP step p50 ms | RSS MiB |", "|---:|---:|---:|"]
    for r in report["history_sweep"]:
        lines.append(f"| {r['length']} | {r['p50_ms']:.3f} | {r['rss_mib']:.0f} |")
    sweep = report["history_sweep"]
    growth = sweep[-1]["p50_ms"] / sweep[0]["p50_ms"] - 1
    lines += [
        "",
        f"DSSP per-step cost at {sweep[-1]['length']} steps vs {sweep[0]['length']}: {100 * growth:+.1f} %; "
        f"memory {sweep[-1]['rss_mib'] - sweep[0]['rss_mib']:+.1f} MiB",
    ]
    mem = report["memory_mib"]
    lines.append(
        f"Resident memory: {mem['before_load']:.0f} MiB before load, {mem['after_load']:.0f} after, {mem['after_profile']:.0f} at the end"
    )
    f = report["chunk_floor"]
    cache = (
        f"{f['cache_mib']:.0f} MiB of cache this process gets (measured; the CPU's last-level cache: "
        f"{f['cpu_cache_mib']:.0f} MiB)"
        if f.get("cpu_cache_mib") and f["cache_mib"] != f["cpu_cache_mib"]
        else f"{f['cache_mib']:.0f} MiB last-level cache"
        if f["cache_mib"]
        else ""
    )
    stream = (
        f"{f['weights_mib']:.1f} MiB of weights{' > ' + cache if cache else ''}, "
        f"read {f['weight_passes']} times a chunk ({f['denoise_steps']} DDIM steps"
        f"{' and the prefix' if f['weight_passes'] > f['denoise_steps'] else ''}) "
        f"at {f['read_gbs']:.1f} GB/s = {f['weight_stream_ms']:.1f} ms"
        if f["weight_stream_ms"] is not None
        else f"{f['weights_mib']:.1f} MiB of weights stay in the {cache}"
    )
    compute = (
        f"compute at the GEMM peak {f['compute_ms']:.1f} ms"
        if f["compute_ms"] is not None
        else "no compute term (the float32 GEMM peak does not bound int8 or int4 products)"
    )
    floor = f"{f['floor_ms']:.1f} ms" if f["floor_ms"] is not None else "not known here"
    lines.append(f"Chunk floor on this machine: {floor} — {compute}; {stream}")
    for graph, label in (("history_step", "history step"), ("denoiser_chunk", "denoiser chunk")):
        rows = report["op_breakdown"][graph]
        top = ", ".join(f"{r['op']} {100 * r['share']:.0f} % ({r['nodes']} nodes)" for r in rows[:5])
        lines.append(
            f"Where the {label} goes (ORT profiler, kernel time): {top}; elementwise/copy ops {100 * elementwise_share(rows):.0f} %"
        )
    lines += ["", "| target (robotwin preset, 2-core CPU) | measured | target | |", "|---|---:|---:|---|"]
    for name, measured, target, _, how in target_rows(report):
        lines.append(f"| {name} | {measured:.3g} | {target:.3g} | {how} |")
    return "\n".join(lines)


def plot(report: dict[str, Any], path: Path, force: bool = False) -> None:
    try:
        import matplotlib  # optional: matplotlib, only for --plot
    except ImportError:
        raise SystemExit("error: --plot needs matplotlib (pip install matplotlib)") from None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # deferred: loads matplotlib
    import matplotlib.ticker  # deferred: loads matplotlib

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4))
    sweep = report["history_sweep"]
    ax1.plot([r["length"] for r in sweep], [r["p50_ms"] for r in sweep], "o-", label="DSSP (Mamba, ORT)")
    ax1.set(
        xscale="log",
        yscale="log",
        xlabel="history length (steps)",
        ylabel="one history update, p50 ms",
        title="Per-step cost vs history",
    )
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

    write_output_figure(path, fig, force=force, flag="--plot")


def main(argv: list[str] | None = None) -> int:
    p = ArgumentParser(prog="dssp-profile", description="CPU latency and memory of an exported DSSP model.")
    p.add_argument("model_dir", type=Path)
    p.add_argument("--quick", action="store_true", help="short run (tests, CI)")
    add_runtime_arguments(p)
    p.add_argument("--threads", type=int, help="ONNX Runtime intra-op threads (default: all CPUs)")
    p.add_argument("--json", type=Path, help="write every figure here")
    p.add_argument("--plot", type=Path, help="write a PNG here")
    p.add_argument("--force", action="store_true", help="replace existing --json and --plot files")
    args = p.parse_args(argv)

    def _main() -> int:
        check_threads(args.threads)
        for path, flag in ((args.json, "--json"), (args.plot, "--plot")):
            if path is not None:
                check_output_file(path, force=args.force, flag=flag)
        t0 = time.perf_counter()
        report = run_profile(
            args.model_dir, args.quick, args.threads, args.precision, args.kernel, False if args.no_spin else None
        )
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

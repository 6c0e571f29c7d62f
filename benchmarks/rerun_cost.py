"""What the Rerun views cost the control loop, per tick, on this machine.

    python benchmarks/rerun_cost.py [--ticks 300] [--control-rate 10] [--block 25] [--json PATH [--force]]

A paced loop at ``--control-rate`` Hz does each tick's real work — a 640x480 L515-like depth frame from the simulated
tabletop camera through ``dssp_data.pointcloud.frame_to_cloud`` (1024 points) — and, in alternate blocks of
``--block`` ticks, also queues that tick's views as ``dssp-run`` does (depth, cloud, a 7-value state and
command, a 16-step chunk every 8 ticks, held, latencies; saved to a temporary .rrd), so both conditions see
the same machine load. Prints the p50 / p95 of the tick's work with and without the views, their difference
(the views' cost to the loop: the call itself plus the worker thread's share of the interpreter), the call's
own p50 / p95 / max, and the ticks dropped. Rendering the frames is not timed.
"""

from __future__ import annotations

import argparse
import platform
import tempfile
import time
from pathlib import Path

import numpy as np
from bench_output import check_json, emit

from dssp_core.cli_runner import run_cli
from dssp_core.schema import DEFAULT_CONTROL_RATE_HZ
from dssp_data.pointcloud import PointCloudConfig, frame_to_cloud
from dssp_data.pointcloud.depth_frame import DepthFrame
from dssp_data.rerun_views import open_views
from hardware.camera.tabletop import SimCamera


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ticks", type=int, default=300, help="ticks per condition")
    ap.add_argument(
        "--control-rate", type=float, default=DEFAULT_CONTROL_RATE_HZ, help="loop rate in Hz (default: the toolkit's)"
    )
    ap.add_argument("--block", type=int, default=25, help="ticks per alternating block")
    ap.add_argument(
        "--json", type=Path, help="also write the figures to this JSON file (a new one; --force replaces one)"
    )
    ap.add_argument("--force", action="store_true", help="replace an existing --json file")
    args = ap.parse_args(argv)
    return run_cli(lambda: _measure(args))


def _measure(args) -> int:
    check_json(args.json, args.force)
    cam = SimCamera(seed=0)
    config, pose = PointCloudConfig(), cam.camera_to_base
    frames = [
        DepthFrame(
            depth=cam.render(i / cam.fps)[0],
            depth_unit=cam.depth_unit,
            intrinsics=cam.intrinsics,
            timestamp=0.0,
            frame_number=i,
        )
        for i in range(32)
    ]
    rng = np.random.default_rng(0)
    work = {"off": [], "on": []}
    call = []
    with tempfile.TemporaryDirectory() as tmp:
        views = open_views("rerun-cost", None, Path(tmp) / "cost.rrd")
        views.camera(cam.intrinsics.to_dict(), pose)
        period, next_tick, tick = 1.0 / args.control_rate, time.perf_counter(), 0
        for i in range(2 * args.ticks):
            on = (i // args.block) % 2 == 1
            t0 = time.perf_counter()
            frame = frames[i % len(frames)]
            cloud, _ = frame_to_cloud(frame, config, pose)
            if on:
                state = rng.uniform(-0.5, 0.5, 7)
                c0 = time.perf_counter()
                views.tick(
                    tick,
                    depth=frame.depth,
                    depth_unit=frame.depth_unit,
                    cloud=cloud,
                    state=state,
                    command=state + 0.01,
                    chunk=np.tile(state, (16, 1)) if tick % 8 == 0 else None,
                    held=False,
                    events=[],
                    latency_ms={"cloud": 1.0, "observe": 1.0, "chunk": None, "tick": 2.0},
                )
                call.append(1e3 * (time.perf_counter() - c0))
                tick += 1
            work["on" if on else "off"].append(1e3 * (time.perf_counter() - t0))
            next_tick += period
            time.sleep(max(0.0, next_tick - time.perf_counter()))
        counts = views.close()
    p = {k: (float(np.percentile(v, 50)), float(np.percentile(v, 95))) for k, v in work.items()}
    report = {
        "machine": {"cpus": __import__("os").cpu_count(), "processor": platform.processor() or platform.machine()},
        "ticks_per_condition": args.ticks,
        "rate_hz": args.control_rate,
        "tick_work_ms": {k: {"p50": v[0], "p95": v[1]} for k, v in p.items()},
        "cost_ms_p50": p["on"][0] - p["off"][0],
        "cost_ms_p95": p["on"][1] - p["off"][1],
        "call_ms": {"p50": float(np.median(call)), "p95": float(np.percentile(call, 95)), "max": float(np.max(call))},
        **counts,
    }
    md = "\n".join(
        [
            f"Rerun views' cost per tick ({args.ticks} ticks per condition at "
            f"{args.control_rate:g} Hz, alternating blocks of {args.block}):",
            "",
            "| | p50 ms | p95 ms |",
            "|---|---:|---:|",
            f"| tick work without views | {p['off'][0]:.3f} | {p['off'][1]:.3f} |",
            f"| tick work with views | {p['on'][0]:.3f} | {p['on'][1]:.3f} |",
            f"| **cost of the views** | **{report['cost_ms_p50']:.3f}** | {report['cost_ms_p95']:.3f} |",
            f"| the views.tick() call alone | {report['call_ms']['p50']:.3f} | "
            f"{report['call_ms']['p95']:.3f} (max {report['call_ms']['max']:.3f}) |",
            "",
            f"ticks logged {counts['logged']}, dropped {counts['dropped']}",
        ]
    )
    return emit(report, md, args.json, args.force)


if __name__ == "__main__":
    raise SystemExit(main())

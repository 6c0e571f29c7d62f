"""Point-cloud pipeline cost on this machine: a 640x480 L515-like depth frame -> 1024 points.

    python benchmarks/pointcloud_time.py [--repeats 100] [--color] [--json PATH [--force]]

Frames come from the simulated tabletop camera's renderer (``hardware.camera.tabletop``: table, boxes, 1 mm
depth noise, 0.2 % invalid pixels; a new noise draw per frame), seen from the simulated camera pose, and
go through ``dssp_data.pointcloud.frame_to_cloud`` with the default ``PointCloudConfig``. Prints the
config and a Markdown table of p50 / p95 milliseconds per stage and in total over the repeats (after a
few warm-up frames; the first call, which builds the per-camera ray cache, is reported on its own).
Rendering is not part of the measured pipeline. Needs numpy and fpsample only.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

import numpy as np

from dssp_core.cli_runner import run_cli
from dssp_core.output_guard import check_output_file, write_output_text
from dssp_data.pointcloud import PointCloudConfig, frame_to_cloud
from dssp_data.pointcloud.depth_frame import DepthFrame
from dssp_data.pointcloud.pipeline import STAGES
from hardware.camera.tabletop import SimCamera


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=100)
    ap.add_argument("--warmup", type=int, default=5)
    ap.add_argument("--color", action="store_true", help="use_color=True (RGB channels, (P, 6) clouds)")
    ap.add_argument("--json", help="also write the figures to this JSON file (a new one; --force replaces one)")
    ap.add_argument("--force", action="store_true", help="replace an existing --json file")
    args = ap.parse_args(argv)
    return run_cli(lambda: _measure(args))


def _measure(args) -> int:
    if args.json:
        check_output_file(args.json, force=args.force, flag="--json")  # before measuring

    cam = SimCamera(seed=0, color=args.color)
    config = PointCloudConfig(use_color=args.color)
    pose = cam.camera_to_base

    def next_frame(i: int) -> DepthFrame:
        depth, color = cam.render(i / cam.fps)
        return DepthFrame(
            depth=depth,
            depth_unit=cam.depth_unit,
            intrinsics=cam.intrinsics,
            timestamp=time.monotonic(),
            frame_number=i,
            color=color,
        )

    t = time.perf_counter()
    _, first_info = frame_to_cloud(next_frame(0), config, pose)
    first_ms = (time.perf_counter() - t) * 1000
    for i in range(args.warmup):
        frame_to_cloud(next_frame(1 + i), config, pose)

    rows: dict[str, list[float]] = {k: [] for k in (*STAGES, "total", "wall")}
    render_ms, infos = [], []
    for i in range(args.repeats):
        t = time.perf_counter()
        frame = next_frame(100 + i)
        render_ms.append((time.perf_counter() - t) * 1000)
        t = time.perf_counter()
        cloud, info = frame_to_cloud(frame, config, pose)
        rows["wall"].append((time.perf_counter() - t) * 1000)
        for k in (*STAGES, "total"):
            rows[k].append(info.timings_ms[k])
        infos.append(info)
    assert cloud.shape == (config.n_points, config.point_dim)

    def pct(values, q):
        return float(np.percentile(values, q))

    intr = cam.intrinsics
    print(f"# Point cloud pipeline: {intr.width}x{intr.height} depth -> {config.n_points} points")
    print(
        f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, Python "
        f"{platform.python_version()}, numpy {np.__version__}; {args.repeats} frames after {args.warmup} warm-up"
    )
    print(f"config: {json.dumps(config.to_dict())}")
    n = {k: int(np.median([getattr(i, k) for i in infos])) for k in ("n_valid", "n_in_crop", "n_after_voxel")}
    print(
        f"points (median): {intr.width * intr.height} pixels -> {n['n_valid']} valid -> {n['n_in_crop']} in "
        f"crop -> {n['n_after_voxel']} after voxel -> {config.n_points}"
    )
    print()
    print("| stage | p50 ms | p95 ms |")
    print("|---|---:|---:|")
    for k in STAGES:
        print(f"| {k} | {pct(rows[k], 50):.2f} | {pct(rows[k], 95):.2f} |")
    print(f"| **total** | **{pct(rows['total'], 50):.2f}** | **{pct(rows['total'], 95):.2f}** |")
    print(f"| total, wall clock around the call | {pct(rows['wall'], 50):.2f} | {pct(rows['wall'], 95):.2f} |")
    print()
    print(
        f"first call (builds the ray cache): {first_ms:.1f} ms; sim rendering (not in the pipeline): "
        f"p50 {pct(render_ms, 50):.2f} ms"
    )
    target = 10.0
    verdict = "meets" if pct(rows["wall"], 50) <= target else "MISSES"
    print(f"target p50 <= {target:g} ms: {verdict}")

    if args.json:
        out = {
            "config": config.to_dict(),
            "repeats": args.repeats,
            "first_call_ms": first_ms,
            "first_info": first_info.to_dict(),
            "points_median": n,
            "p50_ms": {k: pct(v, 50) for k, v in rows.items()},
            "p95_ms": {k: pct(v, 95) for k, v in rows.items()},
        }
        write_output_text(args.json, json.dumps(out, indent=2), force=args.force, flag="--json")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

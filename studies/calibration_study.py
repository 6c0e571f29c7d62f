"""The calibration figures: ``dssp-sim calibrate`` in both modes on the MuJoCo twin, recorded, and the report rebuilt
from the record.

    python -m studies.calibration_study [--report reports/calibration] [--poses 12] [--force]   # run both modes
    python -m studies.calibration_study --report-only                                           # from the record

Each mode (eye-to-hand: the board on the flange, the workcell's fixed camera; eye-in-hand: a wrist camera, the board
on the table) runs ``dssp-sim calibrate --auto N`` (:mod:`dssp_sim.calibration_twin`) with ``--json``, which keeps
the calibration's record: each view's corners, reprojection and residual, the result, the methods' disagreement and
the distance of the result from the twin's true pose. The report (``calibration.md``, ``calibration.json``,
``calibration.png``: each view's residual) and the hardware README's ``calibration`` block are rebuilt from those
records by ``python -m studies.rebuild``. The twin is deterministic (simulated time, rendered images), so a rerun
gives the same record.
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

from dssp_core.cli_runner import ArgumentParser, run_cli
from dssp_core.errors import DSSPError
from dssp_core.files import atomic_write_text

MODES = ("eye-to-hand", "eye-in-hand")
RECORD_DIR = "record"
BOUND = (2.0, 0.5)
"""mm, deg: what the twin's result must stay within of the true pose (the tests assert it too)."""


def run(report: Path, poses: int, force: bool) -> None:
    """Calibrate the twin in both modes; their records go to ``report/record/MODE.json``."""
    from dssp_sim.calibration_twin import calibrate_main  # deferred: loads mujoco, cv2

    record = report / RECORD_DIR
    record.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        for mode in MODES:
            argv = [
                "--mode",
                mode,
                "--auto",
                str(poses),
                "--out",
                str(Path(tmp) / f"{mode}.json"),
                "--json",
                str(record / f"{mode}.json"),
            ] + (["--force"] if force else [])
            if calibrate_main(argv) != 0:
                raise DSSPError(f"dssp-sim calibrate --mode {mode} failed (its lines are above); nothing else was run")


def load(record: Path) -> dict[str, dict]:
    """MODE -> its record, for the modes recorded."""
    return {
        mode: json.loads((record / f"{mode}.json").read_text()) for mode in MODES if (record / f"{mode}.json").is_file()
    }


def summary_table(records: dict[str, dict]) -> str:
    """One row per mode: views used, OpenCV's method, the distance from the true pose, residuals, disagreement."""
    lines = [
        "| mode | result | views used | method | from the true pose | residuals (RMS) | worst view | methods' largest disagreement |",
        "|---|---|---:|---|---:|---:|---:|---:|",
    ]
    for mode, r in records.items():
        used = [v for v in r["views"] if "residual_mm" in v]
        worst = max(used, key=lambda v: v["residual_mm"])
        dis_mm = max((d[0] for d in r["disagreement"].values()), default=0.0)
        dis_deg = max((d[1] for d in r["disagreement"].values()), default=0.0)
        truth = r["truth_error"]
        lines.append(
            f"| {mode} | {r['result']} | {len(used)} / {len(r['views'])} | {r['method']} | "
            + (f"{truth[0]:.2f} mm / {truth[1]:.3f}°" if truth else "—")
            + f" | {r['rms_mm']:.2f} mm / {r['rms_deg']:.3f}° | {worst['residual_mm']:.2f} mm / {worst['residual_deg']:.3f}° "
            f"| {dis_mm:.2f} mm / {dis_deg:.3f}° |"
        )
    return "\n".join(lines) + "\n"


def readme_table(record: Path) -> str:
    """The hardware README's ``calibration`` block."""
    records = load(record)
    if not records:
        return "(not run yet: python -m studies.calibration_study)\n"
    return summary_table(records) + (
        f"\nThe twin's bound: {BOUND[0]:g} mm / {BOUND[1]:g}° from the true pose, in each mode "
        f"({'held' if all(within(r) for r in records.values()) else 'NOT held'}).\n"
    )


def within(r: dict) -> bool:
    return r["truth_error"] is not None and r["truth_error"][0] <= BOUND[0] and r["truth_error"][1] <= BOUND[1]


def write_report(record: Path, out: Path, shown_record: str = "reports/calibration/record") -> Path:
    """``calibration.md``, ``calibration.json`` and ``calibration.png`` in ``out`` from the records; returns the .md."""
    records = load(record)
    if not records:
        raise DSSPError(f"{record} holds no calibration record; run python -m studies.calibration_study")
    out.mkdir(parents=True, exist_ok=True)
    lines = [
        "# Hand-eye calibration on the MuJoCo twin",
        "",
        f"Rebuilt from `{shown_record}` by `python -m studies.calibration_study --report-only` (the records: "
        "`python -m studies.calibration_study`, which runs `dssp-sim calibrate --auto N --json` in each mode). "
        "The twin knows the camera's true pose, so each result is compared with it; on a real robot only the "
        "residuals and the methods' disagreement are there to judge by (hardware/README.md, Calibration).",
        "",
        summary_table(records).rstrip("\n"),
        "",
        "![each view's residual, both modes](calibration.png)",
        "",
    ]
    for mode, r in records.items():
        b = r["board"]
        lines += [
            f"## {mode}",
            "",
            f"{r['rig']}; board {b['squares_x']} x {b['squares_y']} squares of {1e3 * b['square_m']:g} mm "
            f"({b['dictionary']}); poses: {r['poses']}; the arm moved at {r['rate_hz']:g} Hz through the safety "
            f"layer; rotation spread about a second axis {r['rotation_spread_deg']:.1f}°.",
            "",
            "| pose | corners | reprojection px | residual mm | residual ° |",
            "|---:|---:|---:|---:|---:|",
        ]
        for v in r["views"]:
            if "residual_mm" in v:
                lines.append(
                    f"| {v['pose']} | {v['corners']} | {v['reprojection_px']:.2f} | {v['residual_mm']:.2f} | "
                    f"{v['residual_deg']:.3f} |"
                )
            else:
                lines.append(f"| {v['pose']} | {v['corners']} | refused: {v['refused']} | | |")
        lines += [
            "",
            f"{r['result']} ({r['method']}):",
            "",
            "```",
            *("[" + ", ".join(f"{x: .6f}" for x in row) + "]" for row in r["transform"]),
            "```",
            "",
        ]
    md = out / "calibration.md"
    atomic_write_text(md, "\n".join(lines))
    summary = {
        mode: {k: r[k] for k in ("result", "method", "truth_error", "rms_mm", "rms_deg", "rotation_spread_deg")}
        | {"views": len(r["views"]), "within_bound": within(r)}
        for mode, r in records.items()
    }
    atomic_write_text(
        out / "calibration.json", json.dumps({"bound_mm_deg": list(BOUND), "modes": summary}, indent=2) + "\n"
    )
    _plot(records, out / "calibration.png")
    return md


def _plot(records: dict[str, dict], path: Path) -> None:
    import matplotlib  # deferred: loads matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # deferred: loads matplotlib

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.2))
    for (mode, r), marker in zip(records.items(), ("o", "s")):
        used = [v for v in r["views"] if "residual_mm" in v]
        poses = [v["pose"] for v in used]
        axes[0].plot(poses, [v["residual_mm"] for v in used], marker=marker, label=mode)
        axes[1].plot(poses, [v["residual_deg"] for v in used], marker=marker, label=mode)
    axes[0].set(xlabel="pose", ylabel="residual (mm)", title="board centre: chain vs. camera")
    axes[1].set(xlabel="pose", ylabel="residual (°)", title="board rotation: chain vs. camera")
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.set_ylim(bottom=0)
    axes[0].legend()
    fig.tight_layout()
    with tempfile.NamedTemporaryFile(suffix=".png", dir=path.parent, delete=False) as tmp:
        fig.savefig(tmp.name, dpi=100)
    plt.close(fig)
    Path(tmp.name).replace(path)


def main(argv: list[str] | None = None) -> int:
    p = ArgumentParser(prog="python -m studies.calibration_study", description=__doc__.split("\n\n")[0])
    p.add_argument("--report", type=Path, default=Path("reports/calibration"), help="the report and its record")
    p.add_argument("--poses", type=int, default=12, help="poses per mode (dssp-sim calibrate --auto N; default 12)")
    p.add_argument("--force", action="store_true", help="replace the records there")
    p.add_argument("--report-only", action="store_true", help="run nothing: rebuild the report from the record")
    args = p.parse_args(argv)

    def _main() -> int:
        if not args.report_only:
            run(args.report, args.poses, args.force)
        md = write_report(args.report / RECORD_DIR, args.report)
        print(f"wrote {md}")
        return 0

    return run_cli(_main)


if __name__ == "__main__":
    sys.exit(main())

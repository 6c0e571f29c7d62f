"""Every reported figure rebuilt from its committed record, by one command; ``--check`` changes nothing and
fails on any difference (the test suite runs it: it reads records, it reruns nothing).

    python -m studies.rebuild [--check] [--root .]

What it rebuilds (:data:`SOURCES`):

- ``reports/memory/``: the memory-task study's report of each split its record holds
  (:mod:`studies.memory_tasks`, ``record/evals``);
- ``reports/metaworld/`` and ``reports/metaworld_cue/``: the MetaWorld study's reports (:mod:`studies.metaworld`, its
  memory variant with ``--memory``) from their records (``record/plan.json``, ``record/evals``);
- ``reports/sim/`` and ``reports/distill/``: the earlier simulation and distillation studies' reports from
  their records (``record/evals``, ``record/seconds``; their plots too, not compared byte for byte: the
  tables and the JSON are);
- the READMEs' figure blocks (the top one's and each package's), each between ``<!-- figures: NAME -->`` and ``<!-- /figures -->``: ``demo``
  (the Quick start's table, from ``reports/demo/results.json``), ``sim_paired`` (the earlier simulation
  study's comparisons with DSSP and their exact paired tests, from ``reports/sim/record``), and the CPU tables
  ``cpu_targets``, ``dp3_paper``, ``dp3_sim``, ``gpu_train_paper`` (rendered by the benchmark scripts' own
  ``markdown`` from their records in ``reports/cpu/`` and ``reports/gpu/``), ``memory_test`` (the memory study's
  test-split tables, from its record), ``metaworld`` (the MetaWorld study's
  per-group table beside the paper's, from ``reports/metaworld/record`` once it holds a plan).

- ``reports/sampling/``: the sampling study's report (:mod:`studies.sampling`), and the README's ``sampling``
  block.
- ``reports/calibration/``: the calibration twin's report (:mod:`studies.calibration_study`), and the hardware
  README's ``calibration`` block.
- ``reports/delay/``: the delay study's report (:mod:`studies.delay_study`), and the README's ``delay`` block.
"""

from __future__ import annotations

import contextlib
import functools
import importlib.util
import io
import json
import re
import shutil
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path

from dssp_core.cli_runner import ArgumentParser, run_cli
from dssp_core.errors import DSSPError
from dssp_core.files import atomic_write_text
from studies import (
    baseline_tuning,
    calibration_study,
    delay_fair,
    delay_study,
    distill_study,
    memory_fair,
    memory_tasks,
    metaworld,
    sampling,
    sim_study,
)
from studies.demo import results_table
from studies.stats import describe_p, holm, paired_exact_test

BLOCK = re.compile(r"(<!-- figures: (?P<name>[a-z0-9_]+) -->\n)(?P<body>.*?)(<!-- /figures -->)", re.S)


def _memory(root: Path, out: Path) -> list[str]:
    record = root / "reports/memory" / memory_tasks.RECORD_DIR
    written = []
    for split in ("validation", "test"):
        if any((record / "evals").glob(f"*_{split}.json")):
            with contextlib.redirect_stdout(io.StringIO()):
                md = memory_tasks.write_report(
                    memory_tasks.PLAN, record, out, split, shown_record="reports/memory/record"
                )
            written += [md.name, md.with_suffix(".json").name]
    return written


def _fair_plan(root: Path) -> dict:
    """The fair memory study's plan, with the batch and learning rates chosen on validation seeds under ``root``."""
    return memory_fair.fair_plan(root / baseline_tuning.CHOICES.relative_to(baseline_tuning.ROOT))


def _memory_fair(root: Path, out: Path) -> list[str]:
    record = root / "reports/memory_fair" / memory_tasks.RECORD_DIR
    written = []
    for split in ("validation", "test"):
        if any((record / "evals").glob(f"*_{split}.json")):
            md = memory_tasks.write_report(
                _fair_plan(root),
                record,
                out,
                split,
                shown_record="reports/memory_fair/record",
                naming=memory_fair.NAMING,
            )
            written += [md.name, md.with_suffix(".json").name]
    return written


def _sim(root: Path, out: Path) -> list[str]:
    record = root / "reports/sim" / sim_study.RECORD_DIR
    results, pending = sim_study.recorded_results(sim_study.PLAN, record)
    with contextlib.redirect_stdout(io.StringIO()):
        md = sim_study.write_report(
            results, out, sim_study.stage_seconds(out / "no-work", record), force=True, pending=pending
        )
    return [md.name, md.with_suffix(".json").name]


def _distill(root: Path, out: Path) -> list[str]:
    record = root / "reports/distill" / distill_study.RECORD_DIR
    evals, latency, pending = distill_study.recorded_results(distill_study.PLAN, record)
    with contextlib.redirect_stdout(io.StringIO()):
        md = distill_study.write_report(
            evals,
            latency,
            distill_study.PLAN,
            out,
            distill_study.stage_seconds(out / "no-work", record),
            force=True,
            pending=pending,
        )
    return [md.name, md.with_suffix(".json").name]


def _sampling(root: Path, out: Path) -> list[str]:
    record = root / "reports/sampling" / sampling.RECORD_DIR
    md = sampling.write_report(sampling.PLAN, record, out, shown_record="reports/sampling/record")
    return [md.name, md.with_suffix(".json").name]


def _delay(root: Path, out: Path) -> list[str]:
    record = root / "reports/delay" / delay_study.RECORD_DIR
    md = delay_study.write_report(delay_study.PLAN, record, out, shown_record="reports/delay/record")
    return [md.name, md.with_suffix(".json").name]


def _baseline_tuning(root: Path, out: Path) -> list[str]:
    record = root / "reports/baseline_tuning/record"
    if not (record / "evals").is_dir():
        return []
    md = baseline_tuning.write_report(baseline_tuning.PLAN, record, out, shown_record="reports/baseline_tuning/record")
    return [md.name, md.with_suffix(".json").name]


def _delay_fair(root: Path, out: Path) -> list[str]:
    record = root / "reports/delay_fair/record"
    if not (record / "evals").is_dir():
        return []
    md = delay_study.write_report(
        delay_fair.FAIR_PLAN, record, out, shown_record="reports/delay_fair/record", command="studies.delay_fair"
    )
    return [md.name, md.with_suffix(".json").name]


def _calibration(root: Path, out: Path) -> list[str]:
    record = root / "reports/calibration" / calibration_study.RECORD_DIR
    if not calibration_study.load(record):
        return []
    md = calibration_study.write_report(record, out)
    return [md.name, md.with_suffix(".json").name]


def _metaworld(folder: str) -> Callable[[Path, Path], list[str]]:
    def build(root: Path, out: Path) -> list[str]:
        record = root / folder / metaworld.RECORD_DIR
        if not (record / "plan.json").is_file():
            return []
        md = metaworld.write_report(
            json.loads((record / "plan.json").read_text()), record, out, shown_record=f"{folder}/record"
        )
        return [md.name, md.with_suffix(".json").name]

    return build


SOURCES: dict[str, Callable[[Path, Path], list[str]]] = {
    "reports/memory": _memory,
    "reports/memory_fair": _memory_fair,
    "reports/metaworld": _metaworld("reports/metaworld"),
    "reports/metaworld_cue": _metaworld("reports/metaworld_cue"),
    "reports/sim": _sim,
    "reports/distill": _distill,
    "reports/sampling": _sampling,
    "reports/calibration": _calibration,
    "reports/delay": _delay,
    "reports/baseline_tuning": _baseline_tuning,
    "reports/delay_fair": _delay_fair,
}
"""Report folder -> a function writing its rebuilt files into a folder, returning the names to compare."""


SIM_COMPARED = (
    "reactive",
    "window10",
    "no_timestep_decoupling",
    "no_recent_states",
    "no_dynamics_loss",
    "transformer_denoiser",
)


def sim_paired_table(record: Path) -> str:
    """The earlier simulation study's comparisons with DSSP, paired on its scenes (seeds 1000…), from its record: each
    model's success, the difference and the exact paired test (:mod:`studies.stats`)."""

    def grid(task: str, variant: str, seeds: list[int]) -> list[list[int]] | None:
        rows = [sim_study.recorded(record, f"{task}_{variant}_s{seed}") for seed in seeds]
        if any(r is None for r in rows):
            return None
        scenes = [[e["seed"] for e in r["episodes"]] for r in rows]
        if any(s != scenes[0] for s in scenes):
            raise DSSPError(f"{record}: {task}/{variant} seeds were evaluated on different scenes")
        return [[int(e["success"]) for e in r["episodes"]] for r in rows]

    rows = []
    plan = sim_study.PLAN
    for task in plan["demos"]:
        seeds = sorted(set(plan["seeds"][task]) | set(plan["ablation_seeds"].get(task, [])))
        for variant in SIM_COMPARED:
            used = [s for s in seeds if sim_study.recorded(record, f"{task}_{variant}_s{s}")]
            base, other = grid(task, "dssp", used), grid(task, variant, used)
            if not used or base is None or other is None:
                continue
            a, b = sum(map(sum, base)) / (len(used) * len(base[0])), sum(map(sum, other)) / (len(used) * len(other[0]))
            rows.append(
                (
                    f"| {task} | {len(used)} × {len(base[0])} | {sim_study.VARIANT_LABELS.get(variant, variant)} | "
                    f"{100 * a:.0f} % | {100 * b:.0f} % | {100 * (b - a):+.0f} | ",
                    paired_exact_test(other, base),
                )
            )
    lines = [
        "| task | training seeds × scenes | model | DSSP | model's | Δ | paired exact test (Holm over the table) |",
        "|---|---|---|---:|---:|---:|---|",
        *(row + describe_p(p, holm_p=h) + " |" for (row, p), h in zip(rows, holm([p for _, p in rows]))),
    ]
    return "\n".join(lines) + "\n"


def memory_table(
    record: Path, split: str, plan: dict = memory_tasks.PLAN, naming: memory_tasks.Naming = memory_tasks.MEMORY
) -> str:
    """A memory study's tables of ``split`` for the tasks run so far (rows not yet evaluated left out): the first
    study's by default, the fair study's with its ``plan`` and ``naming``."""
    lines, figures = memory_tasks.report_lines(plan, record, split, naming=naming)
    out: list[str] = []
    for task, rows in figures["tasks"].items():
        if not rows:
            continue
        start = lines.index(f"## {task}") + 2
        end = next(i for i, line in enumerate(lines[start:]) if not line.startswith("|"))
        table = [line for line in lines[start : start + end] if "| pending |" not in line]
        section = lines[start + end : next((i for i in range(start, len(lines)) if lines[i].startswith("## ")), None)]
        pending = [line for line in section if line.startswith("Pending rows: ")]  # Holm over a partial family
        out += [f"`{task}`, {split} split:", "", *table, *(["", *pending] if pending else []), ""]
    return "\n".join(out) if out else "(no task evaluated yet)\n"


@functools.cache
def benchmark(root: Path, name: str):
    """The benchmark script ``benchmarks/NAME.py`` as a module (its ``markdown(report)`` renders its record), loaded
    once."""

    folder = str(root / "benchmarks")
    if folder not in sys.path:
        sys.path.insert(0, folder)  # the scripts import their shared helpers by name
    spec = importlib.util.spec_from_file_location(f"bench_{name}", root / "benchmarks" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def readme_blocks(root: Path) -> dict[str, str]:
    """NAME -> the README figure block's body, rebuilt from its record."""
    demo = json.loads((root / "reports/demo/results.json").read_text())
    blocks = {
        "demo": results_table(demo["evals"]) + "\n",
        "sim_paired": sim_paired_table(root / "reports/sim/record"),
        "memory_test": memory_table(root / "reports/memory/record", "test"),
        "memory_fair_test": memory_table(
            root / "reports/memory_fair/record", "test", _fair_plan(root), memory_fair.NAMING
        ),
        "sampling": sampling.readme_table(root / "reports/sampling" / sampling.RECORD_DIR),
        "calibration": calibration_study.readme_table(root / "reports/calibration" / calibration_study.RECORD_DIR),
        "delay": delay_study.readme_table(root / "reports/delay" / delay_study.RECORD_DIR),
    }
    if (root / "reports/delay_fair/record/evals").is_dir():
        blocks["delay_fair"] = delay_study.readme_table(root / "reports/delay_fair/record", delay_fair.FAIR_PLAN)
    if (root / "reports/metaworld/record/plan.json").is_file():
        blocks["metaworld"] = metaworld.readme_table(root / "reports/metaworld/record")
    for block, (script, record) in BENCHMARK_BLOCKS.items():
        blocks[block] = benchmark(root, script).markdown(json.loads((root / record).read_text())) + "\n"
    return blocks


BENCHMARK_BLOCKS = {
    "cpu_targets": ("cpu_targets", "reports/cpu/cpu_targets.json"),
    "dp3_paper": ("dp3_comparison", "reports/cpu/dp3_comparison_paper.json"),
    "dp3_sim": ("dp3_comparison", "reports/cpu/dp3_comparison_sim.json"),
    "gpu_train_paper": ("train_step_time", "reports/gpu/train_step_time_paper_h200.json"),
    "loop_overhead": ("loop_overhead", "reports/cpu/loop_overhead.json"),
}
"""README block -> (the benchmark script whose ``markdown`` renders it, its committed record)."""


def rebuild(root: Path, check: bool) -> list[str]:
    """Rebuild everything under ``root``; returns the files that differ (``check``) or were rewritten."""
    changed = []
    blocks = readme_blocks(root)
    seen: set[str] = set()
    for readme in readmes(root):
        text = readme.read_text()

        def replace(m: re.Match) -> str:
            name = m.group("name")
            if name not in blocks:
                raise DSSPError(
                    f"{readme.relative_to(root)} has a figure block {name!r} that nothing rebuilds; known: "
                    f"{', '.join(blocks)}"
                )
            seen.add(name)
            return m.group(1) + blocks[name] + m.group(4)

        new_text = BLOCK.sub(replace, text)
        if new_text != text:
            changed.append(str(readme.relative_to(root)))
            if not check:
                atomic_write_text(readme, new_text)
    missing = set(blocks) - seen
    if missing:
        raise DSSPError(
            f"no README has the figure block(s) {', '.join(sorted(missing))} (<!-- figures: NAME --> ... "
            "<!-- /figures -->)"
        )
    for folder, build in SOURCES.items():
        if not (root / folder).is_dir():
            continue
        with tempfile.TemporaryDirectory() as tmp:
            out = Path(tmp)
            for name in build(root, out):
                new, old = out / name, root / folder / name
                if not old.is_file() or old.read_text() != new.read_text():
                    changed.append(f"{folder}/{name}")
                    if not check:
                        atomic_write_text(old, new.read_text())
            if not check:
                for png in out.glob("*.png"):
                    shutil.copyfile(png, root / folder / png.name)
    return changed


def readmes(root: Path) -> list[Path]:
    """The project's READMEs: the top one and each package's."""
    return [root / "README.md", *sorted(p for p in root.glob("*/README.md") if p.parent.name not in ("runs", "build"))]


def main(argv: list[str] | None = None) -> int:
    p = ArgumentParser(prog="python -m studies.rebuild", description=__doc__.split("\n\n")[0])
    p.add_argument(
        "--check", action="store_true", help="change nothing: list what differs from its record, exit 1 if anything"
    )
    p.add_argument("--root", type=Path, default=Path(__file__).resolve().parent.parent, help="the project's root")
    args = p.parse_args(argv)

    def _main() -> int:
        changed = rebuild(args.root, args.check)
        if args.check and changed:
            print("differs from its record: " + ", ".join(changed) + "; run python -m studies.rebuild")
            return 1
        print(("rewritten: " + ", ".join(changed)) if changed else "every report and README figure matches its record")
        return 0

    return run_cli(_main)


if __name__ == "__main__":
    sys.exit(main())

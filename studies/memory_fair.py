"""The memory tasks with every model at its best: DSSP against DP3 trained with DP3's own recipe at three sizes, each
at the learning rate its tuning chose on validation seeds, five training seeds on the headline rows, and Table 5's
ablations retrained beside their DSSP control on one machine kind with the same code and graphs.

    python -m studies.memory_fair [--split validation|test] [--tasks T ...] [--models M ...] [--workers 2]
                                  [--work runs/memory_fair] [--report reports/memory_fair] [--freeze]
                                  [--report-only] [--quick]

The memory study's stages, report and statistics (:mod:`studies.memory_tasks`) on :func:`fair_plan`:

- DSSP (``sim`` preset) and DP3 with its recipe (``dp3_recipe``: 128 windows per step drawn across the dataset) at
  0.71, 4.8 and 17 M parameters, all with the same training windows per task, training seeds 0–4 (the seed-level
  test has a smallest p of 0.008 with five against five, 0.1 with three);
- DSSP without history and, on tap, the four ablations of Table 5: DSSP's preset and rate, training seeds 0–2;
- each model's learning rate per task is the one :mod:`studies.baseline_tuning` chose (its report,
  ``reports/baseline_tuning/baseline_tuning.json``); the ablations and DSSP without history take DSSP's. While a
  task's tuning is pending the plan is refused in one line that names the command to run.

The plan is frozen (``--freeze``) before ``--split test`` runs it, as every study's. DP3 at its own size (the
``dp3`` preset, 262 M parameters) with its recipe and its own rate (1e-4) is a GPU row: the report prints its
commands.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from dssp_core.errors import DSSPError
from studies import baseline_tuning, memory_tasks

ROOT = Path(__file__).resolve().parents[1]  # the checkout whose tuning report the plan is built from
TUNING = ROOT / "reports" / "baseline_tuning" / "baseline_tuning.json"
HEADLINE_SEEDS = [0, 1, 2, 3, 4]
OTHER_SEEDS = [0, 1, 2]
DP3_RECIPE = {"preset": "dp3_recipe", "batch": baseline_tuning.PLAN["models"]["dp3_0.7m"]["batch"]}
LABELS = {**baseline_tuning.LABELS, **memory_tasks.LABELS}


def chosen_rates(tuning: dict, tasks: list[str]) -> dict[str, dict[str, float]]:
    """{model: {task: learning rate}} chosen by the tuning report's figures (``baseline_tuning.json``'s "tasks")."""
    out: dict[str, dict[str, float]] = {}
    for task in tasks:
        for name, row in tuning["tasks"].get(task, {}).items():
            if row["chosen_lr"] is None:
                raise DSSPError(
                    f"the learning rate of {name} on {task} is not chosen yet: run python -m studies.baseline_tuning "
                    f"--tasks {task}, then commit its record"
                )
            out.setdefault(name, {})[task] = float(row["chosen_lr"])
    missing = [name for name in baseline_tuning.PLAN["models"] if set(out.get(name, {})) != set(tasks)]
    if missing:
        raise DSSPError(
            f"the tuning report holds no choice for {', '.join(missing)} on every task: run python -m "
            f"studies.baseline_tuning --tasks {' '.join(tasks)}"
        )
    return out


def fair_plan(tuning_path: Path = TUNING) -> dict:
    """The plan of this study, from the tuning's report at ``tuning_path``."""
    try:
        tuning = json.loads(tuning_path.read_text())
    except (OSError, ValueError) as exc:
        raise DSSPError(
            f"cannot read the tuning report {tuning_path} ({exc}): rebuild it with python -m studies.baseline_tuning"
        ) from exc
    tasks = memory_tasks.PLAN["tasks"]
    lrs = chosen_rates(tuning, list(tasks))
    dssp = {"preset": "sim", "flags": [], "lr": lrs["dssp"]}
    return {
        **memory_tasks.PLAN,
        "models": {
            "dssp": dssp,
            **{
                name: {**DP3_RECIPE, "flags": list(baseline_tuning.PLAN["models"][name]["flags"]), "lr": lrs[name]}
                for name in baseline_tuning.DP3_SIZES
            },
            "wo_history": {**dssp, "flags": ["--no-history"], "seeds": OTHER_SEEDS},
        },
        "ablations": {
            task: {name: {**model, "lr": lrs["dssp"], "seeds": OTHER_SEEDS} for name, model in ablations.items()}
            for task, ablations in memory_tasks.PLAN["ablations"].items()
        },
        "gpu_models": {
            "dp3": {
                **DP3_RECIPE,
                "preset": "dp3",
                "flags": ["--set", "train.sampling=windows"],
                "lr": {task: baseline_tuning.PLAN["models"]["dp3_0.7m"]["lrs"][0] for task in tasks},
            }
        },
        "seeds": HEADLINE_SEEDS,
    }


def quick_plan() -> dict:
    """A tiny plan of the same shape (tests): one task, DSSP, one DP3 size with two seeds, and DSSP w/o history with
    one."""
    quick = memory_tasks.QUICK_PLAN
    return {
        **quick,
        "models": {
            "dssp": {"preset": "sim", "flags": [], "lr": {"tap": 1e-3}},
            "dp3_0.7m": {
                "preset": "dp3_recipe",
                "batch": 32,
                "flags": ["--set", "model.unet_down_dims=[16,32]"],
                "lr": {"tap": 1e-3},
            },
            "wo_history": {"preset": "sim", "flags": ["--no-history"], "lr": {"tap": 1e-3}, "seeds": [0]},
        },
    }


def main(argv: list[str] | None = None) -> int:
    return memory_tasks.main(
        argv,
        plan_of=lambda quick: quick_plan() if quick else fair_plan(TUNING),
        command="studies.memory_fair",
        doc=__doc__,
        labels=LABELS,
    )


if __name__ == "__main__":
    sys.exit(main())

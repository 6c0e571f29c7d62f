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
- each model's batch and learning rate per task are the ones :mod:`studies.baseline_tuning` chose (its report,
  ``reports/baseline_tuning/baseline_tuning.json``); the ablations and DSSP without history take DSSP's. While a
  task's tuning is pending the plan is refused in one line that names the command to run.

The plan is frozen (``--freeze``) before ``--split test`` runs it, as every study's. DP3 at its own size (the
``dp3`` preset, 262 M parameters) with its recipe and its own rate (1e-4) is a GPU row: the report prints its
commands.
"""

from __future__ import annotations

import sys
from pathlib import Path

from studies import baseline_tuning, memory_tasks
from studies.study_stages import DP3_SIZES, dp3_recipe

HEADLINE_SEEDS = [0, 1, 2, 3, 4]
OTHER_SEEDS = [0, 1, 2]
LABELS = {**baseline_tuning.LABELS, **memory_tasks.LABELS}
NAMING = memory_tasks.Naming("studies.memory_fair", LABELS)


def fair_plan(choices: Path = baseline_tuning.CHOICES) -> dict:
    """The plan of this study, with the configurations (batch, learning rate) the tuning's report at ``choices``
    chose."""
    tasks = memory_tasks.PLAN["tasks"]
    configs = baseline_tuning.chosen_configurations(baseline_tuning.read_choices(choices), list(tasks))
    chosen = {
        name: {field: {task: c[field] for task, c in by_task.items()} for field in ("batch", "lr")}
        for name, by_task in configs.items()
    }
    dssp = {"preset": "sim", "flags": [], **chosen["dssp"]}
    return {
        **memory_tasks.PLAN,
        "models": {
            "dssp": dssp,
            **{name: {**dp3_recipe(name), **chosen[name]} for name in DP3_SIZES},
            "wo_history": {**dssp, "flags": ["--no-history"], "seeds": OTHER_SEEDS},
        },
        "ablations": {
            task: {name: {**model, **chosen["dssp"], "seeds": OTHER_SEEDS} for name, model in ablations.items()}
            for task, ablations in memory_tasks.PLAN["ablations"].items()
        },
        "gpu_models": {
            "dp3": {
                "preset": "dp3",
                "batch": dp3_recipe("dp3_0.7m")["batch"],
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
        plan_of=lambda quick: quick_plan() if quick else fair_plan(baseline_tuning.CHOICES),
        naming=NAMING,
        doc=__doc__,
    )


if __name__ == "__main__":
    sys.exit(main())

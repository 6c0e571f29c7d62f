"""The fair delay study: each way of taking actions from chunks at its best on the compute a robot has, with
training-time real-time chunking as a fourth mode.

    python -m studies.delay_fair [--tasks tap put2] [--workers 2] [--work runs/delay_fair] [--report reports/delay_fair]
                                 [--report-only] [--quick]

The delay study's stages, report and statistics (:mod:`studies.delay_study`) on :data:`FAIR_PLAN`: ``none``,
``prefetch``, ``ensemble`` with one chunk in flight, ``rtc`` and ``rtc_trained`` at 0, 1, 2 and 4 ticks of delay,
the ticks spent waiting left out of the step limit; validation seeds, nothing tuned.
"""

from __future__ import annotations

import sys
from functools import partial

from studies import delay_study
from studies.evaluations import study_main

# The plan: the delay study's tasks, seeds and budget; its own modes, delays and step limit (its "about").
FAIR_PLAN = {
    **delay_study.PLAN,
    "delays_ms": [0, 100, 200, 400],
    "smoothings": ["none", "prefetch", "ensemble", "rtc", "rtc_trained"],
    "modes": {
        "none": {"flags": ["--smoothing", "none"]},
        "prefetch": {"flags": ["--prefetch"]},
        "ensemble": {"flags": ["--smoothing", "ensemble", "--ensemble-every", "{every}"]},
        "rtc": {"flags": ["--smoothing", "rtc"]},
        "rtc_trained": {"flags": ["--smoothing", "rtc"], "model": "trained_rtc"},
    },
    "models": {"trained_rtc": ["--set", "model.committed_prefix_max=4"]},
    "eval_flags": ["--limit-excludes-holds"],
    "title": "# Inference delay, each mode at its best on a robot's compute: none, prefetch, ensembling, real-time chunking "
    "at inference and at training",
    "about": "Every mode has one chunk in flight at a time, as on a robot's CPU: `none` waits for each chunk, `prefetch` "
    "starts it d ticks early and drops its passed actions (the runtime's latency hiding), `ensemble` starts one every "
    "max(1, d) ticks, `rtc` inpaints the committed actions (inference-time real-time chunking) and `rtc_trained` is "
    "given them by a model trained with committed prefixes of up to 4 actions (training-time real-time chunking, "
    "a second model per training seed, `model.committed_prefix_max=4`). The delays are distinct ticks (0, 1, 2 and 4), "
    "and the ticks spent waiting for a chunk leave the task's step limit (`--limit-excludes-holds`), so success is "
    "scored on the task, not on the wait.",
}
QUICK_FAIR_PLAN = {
    **FAIR_PLAN,
    **{k: delay_study.QUICK_PLAN[k] for k in ("tasks", "episodes", "seeds", "export_flags")},
    "delays_ms": [0, 200],
    "models": {"trained_rtc": ["--set", "model.committed_prefix_max=2"]},
}


def main(argv: list[str] | None = None) -> int:
    return study_main(
        argv,
        "delay_fair",
        __doc__,
        FAIR_PLAN,
        QUICK_FAIR_PLAN,
        delay_study.SPLIT,
        delay_study.stages,
        partial(delay_study.write_report, command="studies.delay_fair"),
    )


if __name__ == "__main__":
    sys.exit(main())

"""The stages the studies share, each a :class:`studies.runner.Stage` calling its package's entry point with the
arguments every study passes it: a collection (``collect_KEY``), a training (``train_KEY``, resumed from its
checkpoint), an export (``export_KEY``) and a closed-loop evaluation (``eval_RESULT``, kept in the record).

    train_stage("tap_dssp_s0", "data/tap.zarr", "runs/tap_dssp_s0", "sim", 3000, 0, after=("collect_tap",))
    eval_stage("tap_dssp_s0", "models/tap_dssp_s0", "tap", 20, 1000, after=("export_tap_dssp_s0",))
"""

from __future__ import annotations

from dssp_sim import sim_cli
from dssp_train.cli import train
from studies.runner import Stage


def collect_stage(key: str, task: str, demos: int, data: str) -> Stage:
    """``collect_KEY``: ``dssp-sim collect`` of ``demos`` expert demonstrations of ``task`` into ``data`` (a
    collection stopped halfway is removed and collected again)."""
    return Stage(
        f"collect_{key}",
        sim_cli.main,
        ("collect", "--task", task, "--episodes", str(demos), "--out", data, "--no-progress"),
        clean=(data,),
    )


def train_argv(
    data: str, run: str, preset: str, steps: int, seed: int, *flags: str, options: tuple[str, ...] = ()
) -> tuple[str, ...]:
    """``dssp-train``'s arguments: ``preset`` trained ``steps`` steps with training ``seed`` on ``data`` into ``run``,
    ``options`` before the output flags (no progress bar, ``--force``) and the model's ``flags`` last."""
    argv = ("--data", data, "--out", run, "--preset", preset, "--steps", str(steps), "--seed", str(seed), *options)
    return (*argv, "--no-progress", "--force", *flags)


def train_stage(
    key: str,
    data: str,
    run: str,
    preset: str,
    steps: int,
    seed: int,
    *flags: str,
    after: tuple[str, ...],
    options: tuple[str, ...] = (),
) -> Stage:
    """``train_KEY``: ``dssp-train`` with :func:`train_argv`'s arguments after the stages ``after``; a training
    stopped halfway resumes from its checkpoint in ``run``."""
    return Stage(
        f"train_{key}",
        train.main,
        train_argv(data, run, preset, steps, seed, *flags, options=options),
        after=after,
        resume=("--data", data, "--out", run, "--resume", "--no-progress"),
        started=f"{run}/checkpoint",
    )


def export_stage(key: str, run: str, model: str, *options: str, after: tuple[str, ...]) -> Stage:
    """``export_KEY``: ``python -m export.to_onnx RUN -o MODEL OPTIONS...`` after the stages ``after``."""
    from export import to_onnx  # deferred: loads torch, which a stage's process imports after setting its threads

    return Stage(f"export_{key}", to_onnx.main, (run, "-o", model, *options), after=after)


def eval_stage(
    result: str,
    model: str,
    task: str,
    episodes: int,
    seed: int,
    *flags: str,
    after: tuple[str, ...],
    threads: int = 1,
) -> Stage:
    """``eval_RESULT``: ``dssp-sim eval`` of ``model`` on ``episodes`` scenes of ``task`` from scene ``seed`` (its
    settings in ``flags``) on ``threads`` threads, after the stages ``after``; its output, the evaluation kept in the
    study's record, is ``evals/RESULT.json``."""
    path = f"evals/{result}.json"
    argv = ("eval", "--model", model, "--task", task, "--episodes", str(episodes), "--seed", str(seed), *flags)
    argv += ("--threads", str(threads), "--json", path, "--force", "--no-progress")
    return Stage(f"eval_{result}", sim_cli.main, argv, after=after, outputs=(path,))

"""The stages the studies share, each a :class:`studies.runner.Stage` calling its package's entry point with the
arguments every study passes it: a collection (``collect_KEY``), a training (``train_KEY``, resumed from its
checkpoint), an export (``export_KEY``) and a closed-loop evaluation (``eval_RESULT``, kept in the record).

    train_stage("tap_dssp_s0", "data/tap.zarr", "runs/tap_dssp_s0", "sim", 3000, 0, after=("collect_tap",))
    eval_stage("tap_dssp_s0", "models/tap_dssp_s0", "tap", 20, 1000, after=("export_tap_dssp_s0",))
"""

from __future__ import annotations

from dssp_sim import sim_cli
from dssp_train.cli import train
from dssp_train.config import load_preset
from studies.runner import Stage

SIM_BATCH = load_preset("sim").train.batch_size  # a plan's steps count its training windows at this batch
# DP3 trained with DP3's recipe (the ``dp3_recipe`` preset: its batch of windows drawn across the dataset) at the
# sizes the studies sweep: the ``sim`` preset's parameter count (0.71 M), and UNet widths x2 and x4 (4.8 M, 17 M)
DP3_SIZES = {"dp3_0.7m": "[32,48,64]", "dp3_4.8m": "[64,128,256]", "dp3_17m": "[128,256,512]"}
DP3_LABELS = {name: f"DP3, DP3's recipe, UNet {dims}" for name, dims in DP3_SIZES.items()}


def dp3_recipe(name: str, *flags: str) -> dict:
    """A plan's model: DP3 at the size ``name`` of :data:`DP3_SIZES` with its recipe, ``flags`` first."""
    return {
        "preset": "dp3_recipe",
        "batch": load_preset("dp3_recipe").train.batch_size,
        "flags": [*flags, "--set", f"model.unet_down_dims={DP3_SIZES[name]}"],
    }


def seeds_of(plan: dict, model: dict) -> list[int]:
    """The training seeds of a plan's ``model``: its own ``seeds`` where it names them, else the plan's."""
    return model.get("seeds", plan["seeds"])


def of_task(value, task: str | None):
    """A plan's per-model setting for ``task``: one value for every task, or a {task: value} dict."""
    return value[task] if isinstance(value, dict) else value


def model_steps(steps: int, model: dict, task: str | None = None) -> int:
    """The steps in which a plan's ``model`` takes the training windows of ``steps`` steps at the ``sim`` preset's
    :data:`SIM_BATCH`, at its own ``batch`` where it has one (one, or one per task): steps × batch windows."""
    return max(1, steps * SIM_BATCH // of_task(model["batch"], task)) if "batch" in model else steps


def training_of(steps: int, model: dict, task: str) -> tuple[int, tuple[str, ...]]:
    """(steps, flags) that train a plan's ``model`` on ``task`` with the training windows of ``steps`` steps
    (:func:`model_steps`) at its ``batch`` and ``lr`` where it has them (each one value, or one per task)."""
    flags = tuple(model["flags"])
    if "batch" in model:
        flags += ("--set", f"train.batch_size={of_task(model['batch'], task)}")
    if "lr" in model:
        flags += ("--set", f"train.lr={of_task(model['lr'], task):g}")
    return model_steps(steps, model, task), flags


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

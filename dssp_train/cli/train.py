"""``dssp-train``: train DSSP (or an ablation) on a DP3/RoboTwin zarr dataset.

    dssp-train --data PATH.zarr --preset robotwin --out runs/x [--steps N] [--seed S] [--device cpu|cuda]
    dssp-train --data PATH.zarr --out runs/x --resume            # continue where the run stopped
    torchrun --nproc_per_node 2 -m dssp_train.cli.train ...       # data-parallel (gloo on CPU, NCCL on GPU)

A new run goes into a new or empty --out. A previous run there is refused (continue it with --resume) or,
with --force, replaced: it is moved aside while the new run trains, deleted when the new run completes,
and put back if the new run fails or is interrupted. A folder holding anything but a run is never touched
(:mod:`dssp_core.output_guard`). A run that stopped before its first checkpoint cannot be continued: it is
started over with --force. One process writes a run directory at a time: a second dssp-train or dssp-distill
with the same --out (a new run, --force or --resume) is refused before it reads or changes anything there
(:func:`dssp_core.staging.writer_lock`).

Every config field has one source: a flag (--steps, --seed, ...), else ``--set model.*/train.*``, else the
preset; the same field from a flag and a --set, or twice from --set, is refused. The dataset gives the
dimensions, the cloud size and the control rate; a --control-rate or a ``--set model.n_points`` that
contradicts it is refused. --resume continues the run on the same --data (its resolved path and, as the
checkpoint records them, its episodes) with the run's own config; only --steps may grow. A config.json that
differs from the config the checkpoint records is refused, naming the fields (one from a version that did not
record it is taken with a warning); the --steps of a resume reach config.json with its next checkpoint. A
--resume of a run that has completed its steps trains nothing and says so.

--log tensorboard|wandb sends what log.jsonl records, and the validation chunks as images, to a dashboard
in the run directory (:mod:`dssp_train.training.dashboards`); like --no-progress it is not part of the run's config,
so --resume may change it.

Ctrl-C and SIGTERM stop the same way (exit code 130): the message says which checkpoint is kept and the
command that continues from it. Before training, a step that clearly cannot fit in memory is refused
(:mod:`dssp_train.training.memory`).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import shlex
import signal
import sys
import threading
import typing
import warnings
from pathlib import Path

from dssp_core.cli_runner import ArgumentParser, run_cli
from dssp_core.errors import CheckpointError, ConfigError, DSSPError, OutputError
from dssp_core.files import read_regular_text
from dssp_core.output_guard import OWN, OutputDir, OutputKind, check_output
from dssp_core.schema import Spec, check_value
from dssp_core.staging import writer_lock
from dssp_train.config import RunConfig, apply_overrides, load_preset, preset_names
from dssp_train.training.dashboards import DASHBOARDS, check_dashboard


def _run_signature(path: Path) -> bool:
    config = json.loads(read_regular_text(path / "config.json") or "null")
    return isinstance(config, dict) and "model" in config and "train" in config


RUN_DIR = OutputKind(
    "a run directory",
    "dssp-train",
    entries=("config.json", "model.safetensors", "checkpoint", "log.jsonl", "loss.png", "tensorboard", "wandb"),
    signature=_run_signature,
    marker=False,
)
"""``dssp-train --out``: config.json (a JSON object with ``model`` and ``train``), model.safetensors,
checkpoint/, log.jsonl, loss.png, and the dashboards' tensorboard/ and wandb/ (``--log``) — recognised by its
config.json, no marker added."""


def build_parser() -> argparse.ArgumentParser:
    p = ArgumentParser(prog="dssp-train", description=__doc__.split("\n\n")[0].strip("`"))
    p.add_argument(
        "--data",
        required=True,
        help="DP3/RoboTwin zarr dataset (data/point_cloud, data/state, data/action, meta/episode_ends)",
    )
    p.add_argument(
        "--preset", default=None, help=f"model and training preset: {', '.join(preset_names())} (default tiny)"
    )
    p.add_argument("--out", required=True, help="run directory to create (or to continue with --resume)")
    p.add_argument(
        "--steps", type=int, help="total optimisation steps (with --resume: the new total, past the checkpoint's step)"
    )
    p.add_argument("--seed", type=int, help="seed for initialisation, episode split and sampling")
    p.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda"], help="default: cuda when available")
    p.add_argument("--batch-size", type=int, help="action windows sampled from each trajectory per step")
    p.add_argument("--lr", type=float, help="peak learning rate")
    p.add_argument(
        "--epochs",
        type=int,
        help="passes over the training trajectories (steps = epochs x training episodes); instead of --steps",
    )
    p.add_argument("--val-ratio", type=float, help="fraction of episodes held out for validation")
    p.add_argument(
        "--no-holdout",
        action="store_true",
        help="train on every episode (train.val_ratio 0), as the paper does with "
        "its 10 MetaWorld/Adroit demonstrations; validation reports on training episodes",
    )
    p.add_argument(
        "--control-rate",
        type=float,
        help="control rate of the data in Hz, when the dataset does not record it "
        "(a recorded rate must not be contradicted)",
    )
    p.add_argument("--resume", action="store_true", help="continue the run in --out from its last checkpoint")
    p.add_argument("--force", action="store_true", help="replace a previous run in --out (once the new one completes)")
    ablations = p.add_argument_group("ablations (paper Tables 3 and 5)")
    ablations.add_argument(
        "--no-history",
        action="store_true",
        help="no history encoder: DSSP without history (the reactive baseline; DP3 itself: --preset dp3_sim or dp3)",
    )
    ablations.add_argument(
        "--no-timestep-decoupling", action="store_true", help="AdaLN modulates the prefix tokens too"
    )
    ablations.add_argument("--no-recent-states", action="store_true", help="prefix is [c_t] only")
    ablations.add_argument("--no-dynamics-loss", action="store_true", help="lambda = 0")
    ablations.add_argument("--history-backbone", choices=["mamba", "transformer"], help="history encoder backbone")
    ablations.add_argument(
        "--history-window", type=int, help="encode only the last T_h observations (0 = full history)"
    )
    ablations.add_argument(
        "--denoiser-backbone",
        choices=["mamba", "transformer"],
        help="denoiser blocks' mixer: Mamba, or causal self-attention (Table 5's w/ Trans.)",
    )
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="SECTION.FIELD=VALUE",
        help="any other config field, e.g. model.d_model=256",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_log_flag(p)
    return p


def add_log_flag(p: argparse.ArgumentParser) -> None:
    """``--log tensorboard|wandb|none`` on ``p``: the dashboard the run logs to besides log.jsonl. Checked by
    ``run_training`` (one line naming the allowed values, or the package to install), not by argparse."""
    p.add_argument(
        "--log",
        default="none",
        metavar="{" + ",".join(DASHBOARDS) + "}",
        help="dashboard besides log.jsonl: tensorboard (RUN_DIR/tensorboard), wandb (RUN_DIR/wandb, offline unless "
        "WANDB_MODE says otherwise) or none (default); needs the viz extra",
    )


# Flags that set one config field: (flag, argparse dest, field).
VALUE_FLAGS = (
    ("--steps", "steps", "train.steps"),
    ("--epochs", "epochs", "train.epochs"),
    ("--seed", "seed", "train.seed"),
    ("--batch-size", "batch_size", "train.batch_size"),
    ("--lr", "lr", "train.lr"),
    ("--val-ratio", "val_ratio", "train.val_ratio"),
    ("--history-backbone", "history_backbone", "model.history_backbone"),
    ("--history-window", "history_window", "model.history_window"),
    ("--denoiser-backbone", "denoiser_backbone", "model.denoiser_backbone"),
)
SWITCH_FLAGS = (
    ("--no-holdout", "no_holdout", "train.val_ratio", 0.0),
    ("--no-history", "no_history", "model.use_history", False),
    ("--no-timestep-decoupling", "no_timestep_decoupling", "model.timestep_decoupled", False),
    ("--no-recent-states", "no_recent_states", "model.use_recent_states", False),
    ("--no-dynamics-loss", "no_dynamics_loss", "model.dynamics_weight", 0.0),
)
SET_SECTIONS = ("model", "train")
NOT_SET_FIELDS = {"preset": "--preset", "dataset": "--data", "control_rate_hz": "--control-rate"}


def _field(key: str):
    """(type annotation, Spec) of a ``section.field`` of RunConfig (sections model, train, model.diffusion)."""
    cls = RunConfig
    *sections, name = key.split(".")
    for section in sections:
        cls = typing.get_type_hints(cls)[section]
    return typing.get_type_hints(cls)[name], {f.name: f for f in dataclasses.fields(cls)}[name].metadata.get(
        "spec", Spec()
    )


def check_flag(flag: str, key: str, value):
    """``value`` of ``flag`` checked against the config field ``key`` it sets; the error names the flag."""
    tp, spec = _field(key)
    return check_value(value, tp, spec, flag)


def set_fields(items: list[str], elsewhere: str | None = None) -> dict[str, str]:
    """``{section.field: item}`` of ``--set`` items; refuses fields that are not the user's to set this way.

    ``elsewhere``: where the refusal says preset, dataset and control_rate_hz come from (default: dssp-train's flags).
    """
    elsewhere = elsewhere or ", ".join(f"{name} comes from {flag}" for name, flag in NOT_SET_FIELDS.items())
    keys = {}
    for item in items:
        if "=" not in item:
            continue  # apply_overrides explains the form
        key = item.split("=", 1)[0]
        head = key.split(".")[0]
        if head in NOT_SET_FIELDS or (head in SET_SECTIONS and "." not in key):
            raise ConfigError(
                f"--set {item}: --set takes model.* and train.* fields, one at a time (e.g. model.d_model=256); {elsewhere}"
            )
        if key in keys:
            raise ConfigError(f"--set {keys[key]} and --set {item} both set {key}; keep one")
        keys[key] = item
    return keys


def given_flags(args) -> list[tuple[str, str, object]]:
    """(flag as typed, field, value) of every config flag on the command line, values checked."""
    flags = []
    for flag, dest, key in VALUE_FLAGS:
        value = getattr(args, dest)
        if value is not None:
            flags.append((f"{flag} {value}", key, check_flag(flag, key, value)))
    for flag, dest, key, value in SWITCH_FLAGS:
        if getattr(args, dest):
            flags.append((flag, key, value))
    return flags


def with_flags(config: RunConfig, flags: list[tuple[str, str, object]]) -> RunConfig:
    """``config`` with each flag's field set (``given_flags``' triples); a value the config refuses is one error
    naming the flag as typed."""
    for typed, key, value in flags:
        data = config.to_dict()
        section, name = key.split(".")
        data[section][name] = value
        try:
            config = RunConfig.from_dict(data)
        except ConfigError as exc:
            raise ConfigError(f"{typed}: {exc}") from None
    return config


def config_from_args(args, run_config: RunConfig | None = None) -> RunConfig:
    """The config of this run: ``run_config`` (the run's own, on --resume) or the preset, with --set and the flags."""
    flags = given_flags(args)
    sets = set_fields(args.set)
    seen: dict[str, str] = {}
    for typed, key, _ in flags:
        if key in sets:
            raise ConfigError(f"{typed.split()[0]} and --set {sets[key]} both set {key}; keep one")
        if key in seen:
            raise ConfigError(f"{seen[key]} and {typed.split()[0]} both set {key}; keep one")
        seen[key] = typed.split()[0]
    budget = {key for _, key, _ in flags} | set(sets)
    if {"train.steps", "train.epochs"} <= budget:
        raise ConfigError("--steps and --epochs (or their --set) both set the training budget; keep one")
    if args.resume:
        if args.preset:
            raise DSSPError("--resume continues the run with its own config; drop --preset")
        changed = [typed for typed, key, _ in flags if key != "train.steps"] + [f"--set {item}" for item in args.set]
        if changed:
            raise DSSPError(f"--resume keeps the run's config; only --steps may change (got {', '.join(changed)})")
        if run_config is None:
            from dssp_train.training.checkpoint import load_config  # deferred: loads safetensors, torch, tqdm

            run_config = load_config(Path(args.out))
        config = run_config
    else:
        config = apply_overrides(load_preset(args.preset or "tiny"), list(args.set))
    config = with_flags(config, flags)
    if "train.steps" in budget and config.train.epochs:  # steps asked for: the preset's (or the run's) epochs give way
        config = apply_overrides(config, ["train.epochs=0"])
    return config


def _first_save(out: Path) -> str:
    """ "step N's save" for the run in ``out`` (its config.json), or "its first save"."""
    from dssp_train.training.checkpoint import first_save_step, load_config  # deferred: loads safetensors, torch, tqdm

    try:
        return f"step {first_save_step(load_config(out))}'s save"
    except DSSPError:
        return "its first save"


def no_checkpoint_message(out: Path) -> str:
    """Why the run in ``out`` cannot be continued when it holds no checkpoint, and what to do."""
    if (out / "model.safetensors").is_file():  # written with every checkpoint: this one was removed since
        return (
            f"{out / 'checkpoint'} is missing, so the run cannot be continued (its model.safetensors stays usable "
            "for export): start it over with --force"
        )
    return f"{out} has no checkpoint yet (stopped before {_first_save(out)}): start it over with --force"


def check_resume(args, out: Path) -> RunConfig:
    """Before the dataset is read: the run in ``out`` can be continued as asked, and its config.json is the config
    its checkpoint was trained with (one without that record, from an older version, is taken with a warning).
    Returns its config."""

    # deferred: loads safetensors, torch, tqdm
    from dssp_train.training.checkpoint import check_recorded_config, checkpoint_dir, load_config, read_trainer_state

    config = load_config(out)
    state = read_trainer_state(out)
    if state is None:
        raise CheckpointError(no_checkpoint_message(out))
    where = checkpoint_dir(out) / "trainer_state.json"
    if not check_recorded_config(out, config, state, where):
        warnings.warn(
            f"{where} does not record the config it was trained with (saved by an older version): "
            f"{out / 'config.json'} is taken as it is"
        )
    if args.steps is not None and args.steps <= state["step"]:
        raise ConfigError(
            f"--steps must be larger than the checkpoint's step {state['step']} to continue (got {args.steps})"
        )
    return config


def interrupted_message(args, out: Path, trainer, replaced: bool) -> str:
    """What a Ctrl-C (or SIGTERM) kept, and how to go on from there."""
    # deferred: loads safetensors, torch, tqdm
    from dssp_train.training.checkpoint import checkpoint_dir, read_trainer_state

    if trainer is None:
        at = "interrupted before training began"
    elif trainer.step > trainer.start_step:
        at = f"interrupted after step {trainer.step}"
    elif trainer.start_step:
        at = f"interrupted before any step past the checkpoint's step {trainer.start_step}"
    else:
        at = "interrupted before the first step"
    if replaced:
        return f"{at}; this run is discarded and the previous run in {out} is back as it was"
    if not out.exists():
        return f"{at}; nothing was kept"
    state = None
    with contextlib.suppress(DSSPError):
        state = read_trainer_state(out)
    if state is not None:
        command = ["dssp-train", "--data", str(args.data), "--out", str(args.out), "--resume"]
        if args.resume and args.steps is not None and args.steps != _run_steps(out):  # not saved yet: asked again
            command += ["--steps", str(args.steps)]
        return f"{at}; the checkpoint of step {state['step']} is in {checkpoint_dir(out)}: continue with {shlex.join(command)}"
    if args.resume:
        return f"{at}; {out} is unchanged"
    if trainer is not None and trainer.step == 0:
        return f"{at}: no checkpoint was kept; start the run over by adding --force"
    return f"{at}, before {_first_save(out)}: no checkpoint was kept; start the run over by adding --force"


def _run_steps(out: Path) -> int | None:
    """train.steps of the run's config.json, or None when it cannot be read."""
    from dssp_train.training.checkpoint import load_config  # deferred: loads safetensors, torch, tqdm

    try:
        return load_config(out).train.steps
    except DSSPError:
        return None


@contextlib.contextmanager
def sigterm_as_interrupt():
    """SIGTERM (a scheduler, kill, systemd) stops the run as Ctrl-C does: a KeyboardInterrupt in the main thread."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum, frame):
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def main(argv: list[str] | None = None) -> int:
    return run_training(build_parser().parse_args(argv), config_from_args)


def run_training(args, make_config) -> int:
    """Train into ``args.out`` with the config ``make_config(args, run_config)`` builds (``run_config``: the
    run's own on --resume, else None): the output guard, --resume, --force and interruptions of dssp-train,
    shared by dssp-distill."""
    args.trainer = None  # set by _train once the Trainer exists (for the interruption message)

    def _main() -> int:
        out = Path(args.out)
        if args.resume and args.force:
            raise DSSPError("--resume continues the run in --out; drop --force")
        check_dashboard(args.log)  # before --out is touched: an unknown value, or its package missing
        is_main = int(os.environ.get("RANK", "0")) == 0
        replaced = False
        try:
            with contextlib.ExitStack() as stack:
                if is_main:  # one writer per run directory, before anything in it is read, moved or written
                    stack.enter_context(writer_lock(out, what="run directory", flag="--out"))
                target = None
                if not args.resume:
                    try:  # before anything else: a run that may not be replaced stops here
                        if is_main:
                            target = stack.enter_context(
                                OutputDir(out, RUN_DIR, force=args.force, staged=False, keep_partial=True)
                            )
                            replaced = target.found == OWN
                        else:  # rank 0 moves a replaced run aside and creates --out
                            check_output(out, force=args.force, kind=RUN_DIR)
                    except OutputError:
                        # deferred: loads safetensors, torch, tqdm
                        from dssp_train.training.checkpoint import checkpoint_dir

                        if RUN_DIR.owns(out):
                            if checkpoint_dir(out) is None:
                                raise OutputError(f"{no_checkpoint_message(out)}, or choose another --out") from None
                            raise OutputError(
                                f"{out} already holds a run; continue it with --resume, pass --force to replace it "
                                "or choose another --out"
                            ) from None
                        raise
                summary = _train(args, out, make_config)
                if target is not None:
                    target.commit()
        except KeyboardInterrupt:
            if is_main:
                print(interrupted_message(args, out, args.trainer, replaced), file=sys.stderr)
            return 130
        if summary is not None:
            print(json.dumps(summary, indent=2))
        return 0

    with sigterm_as_interrupt():
        return run_cli(_main)


def _train(args, out: Path, make_config) -> dict | None:
    """Train into ``out``; the summary on the main process, None on the others."""
    import torch  # deferred: loads torch, tqdm

    from dssp_train.training.checkpoint import read_trainer_state  # deferred: loads safetensors, torch, tqdm
    from dssp_train.training.trainer import Trainer  # deferred: loads msgpack, numcodecs, safetensors, …

    given_flags(args)  # each flag's value first, named as typed
    if args.control_rate is not None:
        check_flag("--control-rate", "control_rate_hz", args.control_rate)
    run_config = check_resume(args, out) if args.resume else None
    config = make_config(args, run_config)
    if args.resume and args.steps is None:
        done = read_trainer_state(out)["step"]
        if done >= config.train.steps:  # nothing to train: nothing is read, written or reported as trained
            if int(os.environ.get("RANK", "0")) == 0:
                print(
                    f"{out} has completed its {config.train.steps} steps: nothing to train; continue it with "
                    f"--resume {getattr(args, 'steps_flag', '--steps')} N (N > {done})",
                    file=sys.stderr,
                )
            return None
    if not Path(args.data).exists():
        raise DSSPError(
            f"dataset {args.data} does not exist; pass a DP3/RoboTwin .zarr directory (dssp-synth makes one)"
        )
    device = args.device if args.device != "auto" else ("cuda" if torch.cuda.is_available() else "cpu")
    trainer = Trainer(
        config,
        args.data,
        out,
        device=device,
        resume=args.resume,
        progress=not args.no_progress,
        control_rate_hz=args.control_rate,
        user_set=set_fields(args.set),
        dashboard=args.log,
    )
    args.trainer = trainer
    if trainer.is_main:
        for note in trainer.notes:
            print(note, file=sys.stderr)
    if trainer.is_main and trainer.config.control_rate_hz is None:
        print(
            f"warning: {args.data} does not record its control rate; pass --control-rate HZ so the runtime can match it",
            file=sys.stderr,
        )
    summary = trainer.run()
    return summary if trainer.is_main else None


if __name__ == "__main__":
    sys.exit(main())

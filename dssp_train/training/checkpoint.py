"""Run directories and checkpoints: safetensors for tensors, JSON for everything else, no pickles.

A run directory::

    RUN_DIR/
      config.json            RunConfig (model, train, control rate, dataset)
      model.safetensors      EMA weights, normalisers included — what export and deployment load
      checkpoint/            the latest full training state, for --resume
        model.safetensors    raw weights
        ema.safetensors      EMA weights
        optimizer.safetensors AdamW moments, one tensor per parameter and moment
        trainer_state.json   step, EMA step, LR-schedule step, param groups, the run's config
        rng.safetensors      torch RNG states
      log.jsonl, loss.png

Every file is written to a temporary name and renamed into place; the checkpoint folder is swapped
in whole, so a crash never leaves a half-written checkpoint behind.

Every weights file records the config it was trained with (safetensors metadata ``config``, its SHA-256
in ``config_sha256``; ``trainer_state.json`` the same as ``config`` and ``config_sha256``): a config.json
edited after training is refused where weights are loaded (:func:`load_policy`, so export and verify) and
by ``--resume`` (:func:`check_recorded_config`), one line naming the fields that differ. Checkpoints saved
before configs were recorded carry no record: they are accepted with config.json as it is (``--resume``
warns; export says so in its "loaded" line), their tensors still checked against it by shape.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import load_file, save_file
from torch import nn

from dssp_core.errors import CheckpointError, ConfigError
from dssp_core.files import _umask, atomic_write, atomic_write_text, replace_dir
from dssp_core.schema import read_json_object
from dssp_train.config import RunConfig
from dssp_train.model.policy import DSSPPolicy

FORMAT_VERSION = "1"


# ------------------------------------------------------------------ file helpers
def save_tensors(path: Path, tensors: dict[str, torch.Tensor], metadata: dict[str, str] | None = None) -> None:
    tensors = {k: v.detach().cpu().contiguous() for k, v in tensors.items()}
    atomic_write(path, lambda tmp: save_file(tensors, tmp, metadata=metadata))


def load_tensors(path: Path) -> dict[str, torch.Tensor]:
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(
            f"{path} is missing: train a model first (dssp-train) or point at a complete run directory"
        )
    try:
        return load_file(str(path))
    except (SafetensorError, OSError, ValueError) as exc:
        raise CheckpointError(f"{path} is not a readable safetensors file ({exc}); re-export or retrain it") from None


def load_state_into(module: nn.Module, tensors: dict[str, torch.Tensor], source: Path) -> None:
    """Load a state dict strictly, explaining any key or shape that does not fit the config."""
    expected = module.state_dict()
    missing = sorted(set(expected) - set(tensors))
    unexpected = sorted(set(tensors) - set(expected))
    mismatched = [
        f"{k} {tuple(tensors[k].shape)} vs {tuple(v.shape)}"
        for k, v in expected.items()
        if k in tensors and tuple(tensors[k].shape) != tuple(v.shape)
    ]
    problems = []
    if missing:
        problems.append(f"{len(missing)} missing (e.g. {', '.join(missing[:3])})")
    if unexpected:
        problems.append(f"{len(unexpected)} unexpected (e.g. {', '.join(unexpected[:3])})")
    if mismatched:
        problems.append(
            f"{len(mismatched)} with another shape (checkpoint vs config, e.g. {'; '.join(mismatched[:3])})"
        )
    if problems:
        raise CheckpointError(
            f"{source} does not fit its config: tensors {'; '.join(problems)}. "
            "Use the config.json saved with these weights, or retrain with this config"
        )
    module.load_state_dict(tensors, strict=True)


# -------------------------------------------------------------------- run files
def save_config(run_dir: Path, config: RunConfig) -> None:
    atomic_write_text(Path(run_dir) / "config.json", config.to_json() + "\n")


RESTORE_HINT = "restore the run's own config.json, or train the run again (dssp-train --force)"


def load_config(run_dir: Path) -> RunConfig:
    """``RUN_DIR/config.json`` as a validated RunConfig; every problem is one CheckpointError naming the file."""
    path = Path(run_dir) / "config.json"
    if not path.is_file():
        raise CheckpointError(
            f"{path} is missing: {run_dir} is not a DSSP run directory (dssp-train --out creates one)"
        )
    values = read_json_object(path, None, error=CheckpointError, hint=RESTORE_HINT)
    try:
        config = RunConfig.from_dict(values)
    except (ConfigError, TypeError) as exc:
        raise CheckpointError(f"{path} is not a valid DSSP config: {exc}") from None
    missing = [key for key in ("model", "train") if not isinstance(values.get(key), dict)]
    if missing:
        raise CheckpointError(
            f"{path} lacks its {' and '.join(missing)} section{'s' if len(missing) > 1 else ''}: "
            f"it is not a complete run config; {RESTORE_HINT}"
        )
    m = config.model
    if m.state_dim < 1 or m.action_dim < 1:
        raise CheckpointError(
            f"{path} has model.state_dim={m.state_dim} and model.action_dim={m.action_dim}, but a run "
            f"records its dataset's (at least 1); {RESTORE_HINT}"
        )
    return config


# ------------------------------------------------------------ the recorded config
CONFIG_KEY, CONFIG_HASH_KEY = "config", "config_sha256"
"""Where a checkpoint records its config: safetensors metadata keys and ``trainer_state.json`` keys."""


def canonical_config(config: RunConfig) -> str:
    """``config`` as the one JSON text that is hashed and recorded (sorted keys, no spaces)."""
    return json.dumps(config.to_dict(), sort_keys=True, separators=(",", ":"))


def config_sha256(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()


def config_record(config: RunConfig) -> dict[str, str]:
    """What a checkpoint records of the config it was trained with: ``{"config": JSON, "config_sha256": hex}``."""
    text = canonical_config(config)
    return {CONFIG_KEY: text, CONFIG_HASH_KEY: config_sha256(text)}


def _flat(values: Any, prefix: str = "") -> dict[str, Any]:
    """``{"model.d_model": 32, ...}``: nested objects flattened to dotted field names (lists kept whole)."""
    if not isinstance(values, Mapping):
        return {prefix: values}
    flat: dict[str, Any] = {}
    for key, value in values.items():
        flat.update(_flat(value, f"{prefix}.{key}" if prefix else str(key)))
    return flat


def config_differences(recorded: Mapping[str, Any], now: Mapping[str, Any]) -> list[tuple[str, Any, Any]]:
    """(field, value now, value recorded) of every field that differs, in field order (absent: None)."""
    a, b = _flat(now), _flat(recorded)
    return [(key, a.get(key), b.get(key)) for key in sorted(set(a) | set(b)) if a.get(key) != b.get(key)]


def _recorded_values(text: Any, digest: Any, where: str) -> dict[str, Any]:
    """The recorded config (a JSON text or object, with its SHA-256) as a dict normalised through RunConfig, so
    that fields added to the config since compare as their defaults."""
    if isinstance(text, Mapping):
        text = json.dumps(text, sort_keys=True, separators=(",", ":"))
    damaged = f"{where} records a damaged config; train the run again (dssp-train --force)"
    if not isinstance(text, str) or not isinstance(digest, str) or config_sha256(text) != digest:
        raise CheckpointError(damaged)
    try:
        values = json.loads(text)
    except json.JSONDecodeError:
        raise CheckpointError(damaged) from None
    if not isinstance(values, dict):
        raise CheckpointError(damaged)
    try:
        return RunConfig.from_dict(values).to_dict()
    except (ConfigError, TypeError):
        return values


def _show(value: Any) -> str:
    return json.dumps(value) if not isinstance(value, str) else value


def check_recorded_config(
    run_dir: Path, config: RunConfig, record: Mapping[str, Any] | None, where: Path | str
) -> bool:
    """Refuse a config.json that differs from the config ``where`` (a weights file, a trainer_state.json) records.

    ``record``: the safetensors metadata or the trainer state holding ``config`` and ``config_sha256``. Returns
    False when there is no record (a checkpoint from before configs were recorded: config.json is taken as it
    is), True when config.json is the recorded config; otherwise one CheckpointError naming the fields that differ.
    """
    record = record or {}
    if CONFIG_KEY not in record and CONFIG_HASH_KEY not in record:
        return False
    digest = record.get(CONFIG_HASH_KEY)
    now_text = canonical_config(config)
    if isinstance(record.get(CONFIG_KEY), str) and config_sha256(now_text) == digest == config_sha256(
        record[CONFIG_KEY]
    ):
        return True
    differences = config_differences(_recorded_values(record.get(CONFIG_KEY), digest, str(where)), json.loads(now_text))
    if not differences:
        return True
    shown = ", ".join(f"{key} {_show(now)} (trained: {_show(then)})" for key, now, then in differences[:4])
    more = f" and {len(differences) - 4} more" if len(differences) > 4 else ""
    raise CheckpointError(
        f"{Path(run_dir) / 'config.json'} differs from the config {where} was trained with: {shown}{more}; "
        "put the trained values back in config.json, or train a new run with the new ones"
    )


def weights_metadata(path: Path) -> dict[str, str]:
    """The safetensors metadata of the weights file ``path`` (its header only; {} when it has none)."""

    try:
        with safe_open(str(path), "pt") as f:
            return dict(f.metadata() or {})
    except (SafetensorError, OSError, ValueError) as exc:
        raise CheckpointError(f"{path} is not a readable safetensors file ({exc}); re-export or retrain it") from None


def config_recorded(path: Path) -> bool:
    """Whether the weights file ``path`` records the config it was trained with."""
    return CONFIG_HASH_KEY in weights_metadata(path)


def first_save_step(config: RunConfig) -> int:
    """The step of a run's first checkpoint."""
    return min(config.train.save_every, config.train.steps)


def load_policy(run_dir: Path, weights: str = "model.safetensors"):
    """Build the policy described by ``RUN_DIR/config.json`` and load its (EMA) weights.

    A config.json that differs from the config the weights record is refused (:func:`check_recorded_config`).
    """

    config = load_config(run_dir)
    path = Path(run_dir) / weights
    tensors = load_tensors(path)
    check_recorded_config(run_dir, config, weights_metadata(path), path)
    policy = DSSPPolicy(config.model)
    load_state_into(policy, tensors, path)
    return policy.eval(), config


# ------------------------------------------------------------ training state
def _optimizer_tensors(optimizer: torch.optim.Optimizer) -> tuple[dict[str, torch.Tensor], list[dict[str, Any]]]:
    state = optimizer.state_dict()
    tensors = {}
    for idx, slots in state["state"].items():
        for name, value in slots.items():
            tensors[f"{idx}.{name}"] = value if torch.is_tensor(value) else torch.tensor(value)
    return tensors, state["param_groups"]


def _optimizer_state(tensors: dict[str, torch.Tensor], param_groups: list[dict[str, Any]]) -> dict[str, Any]:
    state: dict[int, dict[str, torch.Tensor]] = {}
    for key, value in tensors.items():
        idx, name = key.split(".", 1)
        state.setdefault(int(idx), {})[name] = value
    return {"state": state, "param_groups": param_groups}


PARTIAL_PREFIX = ".checkpoint.partial-"


def remove_partial_checkpoints(run_dir: Path) -> None:
    """Delete what a killed save left half-written in RUN_DIR: ``.checkpoint.*`` folders other than
    ``.checkpoint.old`` (which may be the only complete checkpoint) and atomic writes' ``.*.tmp`` files."""
    run_dir = Path(run_dir)
    for leftover in run_dir.glob(".checkpoint.*"):
        if leftover.name != ".checkpoint.old" and leftover.is_dir():
            shutil.rmtree(leftover, ignore_errors=True)
    for leftover in run_dir.glob(".*.tmp"):
        if leftover.is_file():
            leftover.unlink(missing_ok=True)


def save_training_state(
    run_dir: Path,
    model: nn.Module,
    ema_model: nn.Module,
    optimizer: torch.optim.Optimizer,
    trainer_state: dict[str, Any],
    rng: dict[str, torch.Tensor],
    config: RunConfig | None = None,
) -> None:
    """Write RUN_DIR/checkpoint atomically (a new folder swapped in whole). ``config``: the run's config, recorded
    in every file of the checkpoint (:func:`config_record`)."""
    run_dir = Path(run_dir)
    remove_partial_checkpoints(run_dir)
    tmp = Path(tempfile.mkdtemp(dir=run_dir, prefix=PARTIAL_PREFIX))
    record = config_record(config) if config is not None else {}
    if config is not None:
        trainer_state = {
            **trainer_state,
            CONFIG_KEY: json.loads(record[CONFIG_KEY]),
            CONFIG_HASH_KEY: record[CONFIG_HASH_KEY],
        }
    try:
        os.chmod(tmp, 0o777 & ~_umask())
        meta = {"format_version": FORMAT_VERSION, "step": str(trainer_state["step"]), **record}
        save_tensors(tmp / "model.safetensors", model.state_dict(), meta)
        save_tensors(tmp / "ema.safetensors", ema_model.state_dict(), meta)
        opt_tensors, groups = _optimizer_tensors(optimizer)
        save_tensors(tmp / "optimizer.safetensors", opt_tensors, meta)
        save_tensors(tmp / "rng.safetensors", rng, meta)
        atomic_write_text(tmp / "trainer_state.json", json.dumps({**trainer_state, "param_groups": groups}, indent=2))
    except BaseException:  # an error or Ctrl-C mid-save: the partial folder goes, the previous checkpoint stays
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    final, old = run_dir / "checkpoint", run_dir / ".checkpoint.old"
    if final.exists() and old.exists():
        shutil.rmtree(old)  # stale: checkpoint/ is complete
    # Without checkpoint/ (a crash mid-swap), .checkpoint.old is the only complete checkpoint: keep it until now.
    replace_dir(tmp, final, aside=old)
    shutil.rmtree(old, ignore_errors=True)


def checkpoint_dir(run_dir: Path) -> Path | None:
    """The folder :func:`load_training_state` reads (``checkpoint/``, or ``.checkpoint.old`` after a crash
    mid-swap), or None when the run has no checkpoint yet. Changes nothing on disk."""
    for name in ("checkpoint", ".checkpoint.old"):
        path = Path(run_dir) / name
        if path.is_dir() and not path.is_symlink():
            return path
    return None


def read_trainer_state(run_dir: Path) -> dict[str, Any] | None:
    """The checkpoint's ``trainer_state.json`` (step, EMA step, the dataset it was trained on, ...) without
    the tensors, or None when the run has no checkpoint yet. Changes nothing on disk."""
    ckpt = checkpoint_dir(run_dir)
    if ckpt is None:
        return None
    path = ckpt / "trainer_state.json"
    state = read_json_object(path, None, error=CheckpointError, hint="start a new run")
    if not isinstance(state, dict) or isinstance(state.get("step"), bool) or not isinstance(state.get("step"), int):
        raise CheckpointError(f"{path} does not record the checkpoint's step; start a new run")
    return state


def load_training_state(run_dir: Path) -> dict[str, Any]:
    """Everything :func:`save_training_state` wrote, as tensors and JSON."""
    if Path(run_dir).is_dir():
        remove_partial_checkpoints(run_dir)
    ckpt = checkpoint_dir(run_dir)
    if ckpt is None:
        raise CheckpointError(
            f"{run_dir} has no checkpoint yet (it stopped before its first save): nothing to resume; "
            "start it over with --force (without --resume)"
        )
    trainer_state = read_json_object(ckpt / "trainer_state.json", None, error=CheckpointError, hint="start a new run")
    try:
        groups = trainer_state.pop("param_groups")
    except KeyError as exc:
        raise CheckpointError(f"{ckpt / 'trainer_state.json'} is unreadable ({exc!r}); start a new run") from None
    return {
        "model": load_tensors(ckpt / "model.safetensors"),
        "ema": load_tensors(ckpt / "ema.safetensors"),
        "optimizer": _optimizer_state(load_tensors(ckpt / "optimizer.safetensors"), groups),
        "rng": load_tensors(ckpt / "rng.safetensors"),
        "trainer_state": trainer_state,
        "path": ckpt,
    }

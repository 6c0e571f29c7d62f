"""The evaluation protocol: three disjoint seed ranges, the test range locked behind a frozen plan, and the
provenance every record carries.

- **demonstrations** (:data:`DEMO_SEEDS`): the scenes the experts are recorded in (``dssp-sim collect``
  starts at seed 0).
- **validation** (:data:`VALIDATION_SEEDS`): every choice — task settings, crops, budgets, checkpoints,
  sampler settings — is made on these. Every simulation figure reported before this protocol was measured on
  seeds 1000 and up while those choices were made: they are validation figures and are reported as such.
- **test** (:data:`TEST_SEEDS`): touched only to produce a reported table. A study evaluates on it only
  after its plan is frozen (:func:`freeze_plan`: the plan's hash written beside the record, from a
  validation run of the same plan), and refuses when the plan has changed since (:func:`check_frozen`), so
  a configuration cannot be tuned on test seeds and then reported.

Each record states its provenance (:func:`provenance`): the task definition's hash (the source of the
simulation's tasks, scenes and experts), the code's commit, the seeds, the budget (in the plan) and the
machine.
"""

from __future__ import annotations

import hashlib
import json
import subprocess
from collections.abc import Callable, Iterable
from datetime import datetime, timezone
from pathlib import Path

import dssp_sim
from dssp_core import machine
from dssp_core.errors import DSSPError
from dssp_core.files import atomic_write_text

DEMO_SEEDS = range(0, 1000)
VALIDATION_SEEDS = range(1000, 10_000)
TEST_SEEDS = range(10_000, 20_000)
SPLITS = {"validation": VALIDATION_SEEDS, "test": TEST_SEEDS}
FROZEN_NAME = "frozen_plan.json"
"""Beside a study's record: the plan's hash when it was frozen for the test split."""
TASK_SOURCES = ("tasks.py", "experts.py", "env.py", "mjcf.py", "settings.py", "ik.py")
"""The files of ``dssp_sim`` that define a task: its scene, randomisation, scoring and expert."""


def split_seeds(split: str, n: int) -> list[int]:
    """The first ``n`` scene seeds of a split ("validation" or "test"): the same scenes for every model (paired)."""
    if split not in SPLITS:
        raise DSSPError(f"unknown split {split!r}; choose one of {', '.join(SPLITS)}")
    seeds = SPLITS[split]
    if not 1 <= n <= len(seeds):
        raise DSSPError(f"{split}: {n} episodes asked for, the split holds {len(seeds)} seeds")
    return list(seeds[:n])


def check_disjoint() -> None:
    """The three ranges do not overlap (a change to one is checked here)."""
    ranges = [DEMO_SEEDS, VALIDATION_SEEDS, TEST_SEEDS]
    for a, b in zip(ranges, ranges[1:]):
        if a.stop > b.start:
            raise DSSPError(f"seed ranges overlap: {a} and {b}")


def task_definition_hash() -> str:
    """sha256 over the source of the simulation's task definitions (:data:`TASK_SOURCES`), first 16 hex digits."""
    root = Path(dssp_sim.__file__).parent
    h = hashlib.sha256()
    for name in TASK_SOURCES:
        h.update(name.encode() + b"\0" + (root / name).read_bytes() + b"\0")
    return h.hexdigest()[:16]


def plan_hash(plan: dict) -> str:
    """sha256 of the plan's canonical JSON (sorted keys), first 16 hex digits."""
    return hashlib.sha256(json.dumps(plan, sort_keys=True).encode()).hexdigest()[:16]


def code_commit() -> str:
    """The git commit of the code (with ``+changes`` when the work tree's code differs from it), or "unknown".

    The committed records under ``reports/`` are left out of the comparison: a study rewrites its own record as it
    goes, and that is no change to the code that produced it."""
    root = Path(__file__).resolve().parent.parent
    try:
        head = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=10)
        dirty = subprocess.run(
            ["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no", "--", ".", ":(exclude)reports"],
            capture_output=True,
            text=True,
            timeout=10,
        )
    except (OSError, subprocess.TimeoutExpired):
        return "unknown"
    if head.returncode != 0:
        return "unknown"
    return head.stdout.strip() + ("+changes" if dirty.stdout.strip() else "")


def provenance(plan: dict, tasks: Iterable[str] | None = None, definition: str | None = None) -> dict:
    """What a record states about how it was made (module docstring); ``tasks``: the tasks the run was started for;
    ``definition``: the hash of a benchmark defined elsewhere (MetaWorld's), instead of :func:`task_definition_hash`."""
    return {
        "task_definition": definition or task_definition_hash(),
        "plan": plan_hash(plan),
        "commit": code_commit(),
        "machine": machine.describe(),
        **({"tasks": sorted(tasks)} if tasks is not None else {}),
    }


def note_provenance(
    record_dir: Path,
    plan: dict,
    split: str,
    tasks: Iterable[str] | None = None,
    definition: str | None = None,
    allow_changes: bool = False,
) -> None:
    """Add this run's provenance to the record's list for ``split`` (a resumed study on other code or another
    machine adds an entry; the same one again adds none). Code with uncommitted changes is refused: a record names
    the commit that made it (``allow_changes``: a quick plan's record, which reports nothing)."""
    path = Path(record_dir) / f"provenance_{split}.json"
    runs = json.loads(path.read_text()) if path.is_file() else []
    now = provenance(plan, tasks, definition)
    if now["commit"].endswith("+changes") and not allow_changes:
        raise DSSPError(
            f"the code has uncommitted changes ({now['commit']}): commit them first, so that {path.parent} names the "
            "code that made it"
        )
    if not runs or runs[-1] != now:
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(path, json.dumps(runs + [now], indent=1) + "\n")


def freeze_plan(
    record_dir: Path,
    plan: dict,
    tested: Iterable[str] = (),
    definition: str | None = None,
    reason: str | None = None,
    now: Callable[[], datetime] = lambda: datetime.now(timezone.utc),
) -> str:
    """Freeze ``plan`` for the test split: write its hash and the task definition's beside the record, with when
    (``now``, UTC) and at which commit (once; a different frozen plan there is refused: a new plan is a new study).

    Freezing the same plan again after the task definition changed (a scorer fixed on validation evidence, say)
    needs a ``reason``: it moves the freeze to the new definition, recording the reason, the time and the commit,
    and keeps the earlier freeze in ``earlier`` with the tasks whose test evaluations were already in the record
    (``tested``): those stay as they were run (each run's provenance names its definition), and only tasks tested
    from now on run on the new one."""
    path = Path(record_dir) / FROZEN_NAME
    digest = plan_hash(plan)
    current = definition or task_definition_hash()
    stamp = {"at": now().isoformat(timespec="seconds"), "commit": code_commit()}
    if path.is_file():
        frozen = json.loads(path.read_text())
        if frozen.get("plan") != digest:
            raise DSSPError(
                f"{path} froze plan {frozen.get('plan')}, this plan is {digest}: a plan changed after its test run "
                "is a new study (another --report folder)"
            )
        if frozen.get("task_definition") == current:
            return digest
        if not (reason or "").strip():
            raise DSSPError(
                f"the task definition changed since {path} froze the plan ({frozen.get('task_definition')} -> "
                f"{current}): freezing it again needs --reason TEXT, which the record keeps"
            )
        previous = {k: v for k, v in frozen.items() if k != "earlier"}
        earlier = [*frozen.get("earlier", []), {**previous, "tested": sorted(tested)}]
        entry = {"plan": digest, "task_definition": current, **stamp, "reason": reason.strip(), "earlier": earlier}
        atomic_write_text(path, json.dumps(entry, indent=2) + "\n")
        return digest
    path.parent.mkdir(parents=True, exist_ok=True)  # a plan may be frozen before its first run
    atomic_write_text(path, json.dumps({"plan": digest, "task_definition": current, **stamp}, indent=2) + "\n")
    return digest


def check_frozen(record_dir: Path, plan: dict, definition: str | None = None) -> None:
    """Refuse the test split unless ``plan`` is the one frozen beside the record, on the same task definition
    (``definition``: a benchmark's own hash, as given to :func:`freeze_plan`)."""
    current = definition or task_definition_hash()
    path = Path(record_dir) / FROZEN_NAME
    if not path.is_file():
        raise DSSPError(
            f"the test split needs a frozen plan and {path} does not exist: run the validation split, choose "
            "on it, then --freeze (the plan's hash is kept; the test seeds stay untouched until then)"
        )
    frozen = json.loads(path.read_text())
    if frozen.get("plan") != plan_hash(plan):
        raise DSSPError(
            f"the plan changed since it was frozen ({frozen.get('plan')} -> {plan_hash(plan)}): the test split "
            "evaluates only the frozen plan; a changed plan is a new study"
        )
    if frozen.get("task_definition") != current:
        raise DSSPError(
            f"the task definition changed since the plan was frozen ({frozen.get('task_definition')} -> "
            f"{current}): a changed task is a new study"
        )


TRAINED_ELSEWHERE = "trained_elsewhere.json"
"""Beside a record: trainings run on another machine than its evaluations (a GPU)."""


def trained_elsewhere(record_dir: Path) -> list[dict]:
    """``record/trained_elsewhere.json``: each entry's models, tasks, seeds, machine, how and code; absent: every
    training ran where the record's provenance says."""
    path = Path(record_dir) / TRAINED_ELSEWHERE
    if not path.is_file():
        return []
    entries = json.loads(path.read_text())
    keys = ("models", "tasks", "seeds", "machine", "how", "code")
    if not isinstance(entries, list) or not all(isinstance(e, dict) and all(k in e for k in keys) for e in entries):
        raise DSSPError(f"{path} must hold a list of objects with {', '.join(keys)}; write it again")
    return entries


def describe_run(prov: dict, split: str | None = None, definition: str = "task definition") -> str:
    """The report's line for one run's provenance (:func:`record_provenance`): its split and tasks, the
    definition, plan and code it ran with, and the machine."""
    m = prov.get("machine", {})
    said = [part for part in (split, ", ".join(prov.get("tasks") or ())) if part]
    label = f" ({': '.join(said)})" if said else ""
    return (
        f"Run{label} on: {definition} {prov.get('task_definition')}, plan {prov.get('plan')}, code {prov.get('commit')}; "
        f"{m.get('cpu')} ({m.get('cores')} cores), onnxruntime {m.get('onnxruntime')}, torch {m.get('torch')}."
    )


def describe_trained_elsewhere(entry: dict, labels: dict[str, str]) -> str:
    """The report's line for one :func:`trained_elsewhere` entry."""
    return (
        f"Trained elsewhere ({', '.join(labels.get(m, m) for m in entry['models'])}; {', '.join(entry['tasks'])}; "
        f"training seeds {entry['seeds']}): {entry['machine']}; {entry['how']} (code {entry['code']})."
    )

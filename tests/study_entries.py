"""Entry points for the stage runner's tests (tests/test_studies.py, tests/test_sim_study.py): a spawned stage
imports this module, so it imports nothing heavy."""

from __future__ import annotations

import json
import os
import threading
from pathlib import Path


def write_marker(argv: list[str]) -> int:
    """Writes argv[0] with its own threads and working folder in it."""
    path = Path(argv[0])
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"argv": argv, "omp": os.environ.get("OMP_NUM_THREADS"), "cwd": os.getcwd()}))
    print(f"wrote {path}")
    return 0


def fail(argv: list[str]) -> int:
    print("first line")
    print(f"something broke: {argv[0]}")
    return 3


def needs(argv: list[str]) -> int:
    """Succeeds only when argv[0] exists (the stage it comes after ran)."""
    return 0 if Path(argv[0]).is_file() else 4


def record_call(argv: list[str]) -> int:
    """Appends its argv to calls.jsonl in the working folder: the call a study's stage makes, without making it."""
    with open("calls.jsonl", "a") as f:
        f.write(json.dumps(argv) + "\n")
    return 0


def sleep_long(argv: list[str]) -> int:
    """A stage that runs until it is stopped; writes its pid first. It waits on an event nothing sets, so only
    its end (the runner's SIGTERM, or a kill) ends it, however long the test takes to get there."""
    Path(argv[0]).write_text(str(os.getpid()))
    threading.Event().wait()
    return 0


def chatter(argv: list[str]) -> int:
    """Lines, a progress bar on stderr and an unended last line."""
    import sys

    print("one")
    sys.stderr.write("\rbar 1\rbar 2\n")
    sys.stderr.flush()
    print(os.environ.get("OMP_NUM_THREADS"))
    sys.stdout.write("no newline")
    return 0

"""What every benchmark script ends with: the Markdown table on stdout and, with ``--json``, every figure."""

from __future__ import annotations

import json
from pathlib import Path

from dssp_core.output_guard import check_output_file, write_output_text


def check_json(path: Path | None, force: bool) -> None:
    """Refuse an existing ``--json`` file without ``--force`` before any measuring (one-line error)."""
    if path is not None:
        check_output_file(path, force=force, flag="--json")


def emit(report: dict, markdown: str, path: Path | None, force: bool) -> int:
    """Print ``markdown``; write ``report`` to ``path`` as JSON (atomically) when given. Returns exit code 0."""
    print(markdown)
    if path is not None:
        write_output_text(path, json.dumps(report, indent=2) + "\n", force=force, flag="--json")
    return 0

"""What every command shares: one-line errors instead of tracebacks for bad input."""

from __future__ import annotations

import sys
from collections.abc import Callable

from dssp_train.errors import DSSPError


def run_cli(main: Callable[[], int | None]) -> int:
    """Run a command; a :class:`DSSPError` becomes ``error: <message>`` and exit code 2."""
    try:
        return int(main() or 0)
    except DSSPError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130

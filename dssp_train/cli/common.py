"""What every command shares: one-line errors instead of tracebacks for bad input."""

from __future__ import annotations

import sys
import warnings
from collections.abc import Callable

from dssp_train.errors import DSSPError


def _one_line_warning(message, category, filename, lineno, file=None, line=None) -> None:
    print(f"warning: {message}", file=file or sys.stderr)


def run_cli(main: Callable[[], int | None]) -> int:
    """Run a command; a :class:`DSSPError` becomes ``error: <message>`` and exit code 2.

    Warnings print as one ``warning: <message>`` line, without the source line.
    """
    warnings.showwarning = _one_line_warning
    try:
        return int(main() or 0)
    except DSSPError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130

"""What every command shares: one-line errors instead of tracebacks for bad input."""

from __future__ import annotations

import json
import sys
import warnings
from collections.abc import Callable

from dssp_train.errors import ConfigError, DSSPError


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


def read_json_object(path, what: str) -> dict:
    """A JSON object from a settings file, or a one-line ``ConfigError`` naming ``what`` and the problem."""
    from pathlib import Path

    try:
        values = json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise ConfigError(f"{what} file {path} does not exist") from None
    except json.JSONDecodeError as exc:
        raise ConfigError(f"{what} file {path} is not valid JSON ({exc.msg} at line {exc.lineno})") from None
    if not isinstance(values, dict):
        raise ConfigError(f"{what} file {path} must hold a JSON object")
    return values

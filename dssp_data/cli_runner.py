"""What every command shares: one-line errors instead of tracebacks for bad input."""

from __future__ import annotations

import argparse
import os
import sys
import warnings
from collections.abc import Callable

from dssp_data.errors import DSSPError


def _one_line_warning(message, category, filename, lineno, file=None, line=None) -> None:
    print(f"warning: {message}", file=file or sys.stderr)


class ArgumentParser(argparse.ArgumentParser):
    """argparse with the commands' one-line errors: ``error: PROG: MESSAGE (see PROG --help)``, exit code 2
    (argparse's own prints the whole usage block first)."""

    def error(self, message: str):
        self.exit(2, f"error: {self.prog}: {message} (see {self.prog} --help)\n")


def run_cli(main: Callable[[], int | None]) -> int:
    """Run a command; a :class:`DSSPError` becomes ``error: <message>`` and exit code 2.

    Warnings print as one ``warning: <message>`` line, without the source line.
    """
    warnings.showwarning = _one_line_warning
    try:
        code = int(main() or 0)
        sys.stdout.flush()
        return code
    except DSSPError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        _settle_after_interrupt()
        print("interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # the reader of stdout went away (| head): stop quietly, as command-line tools do
        try:
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
        except (OSError, ValueError, AttributeError):  # stdout is not a file (tests capture it)
            pass
        return 141


def _settle_after_interrupt() -> None:
    """zarr 3 reads and writes on its own thread: let them end before the process does (a Ctrl-C reaches only
    the main thread), and do not warn about the calls the interruption stopped before they started."""
    if "zarr" not in sys.modules:
        return
    from dssp_data.output_guard import settle_background_writes

    warnings.filterwarnings("ignore", message="coroutine .* was never awaited", category=RuntimeWarning)
    settle_background_writes()

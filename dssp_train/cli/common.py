"""What every command shares: one-line errors instead of tracebacks for bad input."""

from __future__ import annotations

import argparse
import os
import sys
import warnings
from collections.abc import Callable

from dssp_train.errors import DSSPError


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
        return int(main() or 0)
    except DSSPError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # the reader of stdout went away (| head): stop quietly, as command-line tools do
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 141

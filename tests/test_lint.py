"""The code's form: ruff's formatter and linter, as configured in pyproject.toml ([tool.ruff]: line length 120)."""

import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import ROOT


def ruff(*args: str) -> subprocess.CompletedProcess:
    exe = shutil.which("ruff", path=str(Path(sys.executable).parent)) or shutil.which("ruff")
    assert exe, "ruff is not installed: pip install -e '.[dev]' (make setup) installs it"
    return subprocess.run([exe, *args], cwd=ROOT, capture_output=True, text=True, timeout=300)


@pytest.mark.parametrize("args", [("format", "--check", "."), ("check", ".")], ids=["format", "lint"])
def test_the_code_is_as_ruff_formats_and_lints_it(args):
    done = ruff(*args)
    assert done.returncode == 0, (
        f"ruff {' '.join(args)} (run `ruff format . && ruff check --fix .`):\n{done.stdout}{done.stderr}"
    )

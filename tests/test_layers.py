"""The house's layout: imports run down the data flow (import-linter's contracts in pyproject.toml), the
robot side imports without torch, and every module name is unique across the packages."""

import json
import os
import shutil
import subprocess
import sys
from collections import Counter

from conftest import ROOT

PACKAGES = ("dssp_core", "dssp_data", "dssp_train", "export", "dssp_deploy", "hardware", "dssp_sim", "studies")
ROBOT_SIDE = ("dssp_core", "dssp_data", "dssp_deploy", "hardware", "dssp_sim")


def modules(package: str) -> list[str]:
    out = []
    for path in sorted((ROOT / package).rglob("*.py")):
        parts = path.relative_to(ROOT).with_suffix("").parts
        out.append(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
    return out


def test_import_contracts_hold():
    exe = shutil.which("lint-imports")
    assert exe is not None, "lint-imports is not installed (pip install -e '.[dev]')"
    proc = subprocess.run([exe, str(ROOT / "pyproject.toml")], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-2000:]
    assert "broken" not in proc.stdout.lower().replace("0 broken", "")


BLOCKED = """
import importlib, json, sys

class Block:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in ("torch", "onnx", "dssp_train", "export"):
            raise ImportError(f"{name} is blocked: the robot side may not import it")
        return None

sys.meta_path.insert(0, Block())
failed = {}
for name in json.loads(sys.argv[1]):
    try:
        importlib.import_module(name)
    except BaseException as exc:  # noqa: BLE001 - report every module that cannot import
        failed[name] = f"{type(exc).__name__}: {exc}"
print(json.dumps({"failed": failed, "loaded": sorted(m for m in sys.modules if m.split(".")[0] in ("torch", "onnx"))}))
"""


def test_every_robot_side_module_imports_where_torch_cannot():
    names = [m for p in ROBOT_SIDE for m in modules(p)]
    assert len(names) > 60
    proc = subprocess.run(
        [sys.executable, "-c", BLOCKED, json.dumps(names)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")},
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert result == {"failed": {}, "loaded": []}


def test_module_names_are_unique_across_packages():
    leaves = Counter(m.rsplit(".", 1)[-1] for p in PACKAGES for m in modules(p) if "." in m and not m.endswith(".cli"))
    assert [name for name, n in leaves.items() if n > 1 and name != "cli"] == []


def test_the_core_and_dssp_run_load_without_numpy():
    """dssp-run installs its stop handling before numpy and the runtime load (a Ctrl-C during those imports is a
    clean stop), so what it imports at module level — the core included — must not pull numpy in."""
    code = (
        "import sys; import dssp_core.output_guard, dssp_core.staging, dssp_core.cli_runner, dssp_core.schema, "
        "hardware.cli.run; print(sorted(m for m in sys.modules if m.split('.')[0] in ('numpy', 'zarr', 'torch')))"
    )
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0 and proc.stdout.strip() == "[]", proc.stdout + proc.stderr[-2000:]

"""Every import is declared: each third-party module that the packages, the plugin, the benchmarks or the tests
import comes from a distribution that pyproject.toml's dependencies or extras declare (or that `make setup` installs
by name), and each requirement of a package `make setup` installs without its dependencies is installed here too, or
named below as left out on purpose. CI runs the suite in a fresh virtualenv, so nothing comes from the machine."""

from __future__ import annotations

import ast
import importlib.metadata as metadata
import os
import re
import sys
import tomllib
from pathlib import Path

import pytest
from conftest import ROOT
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

SOURCES = (
    "dssp_core",
    "dssp_data",
    "dssp_train",
    "export",
    "dssp_deploy",
    "hardware",
    "dssp_sim",
    "studies",
    "plugins",
    "benchmarks",
    "tests",
)

# Standard-library modules of newer Pythons, imported where they exist (a backport stands in before).
NEWER_STDLIB = {"compression": "zstd in the standard library from Python 3.14 (backports.zstd before)"}
# Requirements of the packages installed with --no-deps (Makefile: METAWORLD, LEROBOT) that are not installed, and why.
LEFT_OUT = {
    "metaworld": {"mujoco": "metaworld pins mujoco==3.3.0; it runs on the MuJoCo the sim extra installs"},
    "lerobot": {
        "torch": "lerobot declares torch<2.11; its dataset and training code runs on the torch installed here",
        "torchvision": "PyPI's torchvision does not import beside the local torch wheel; tests/test_lerobot.py "
        "stands in for the one function LeRobot's dataset code uses",
        "torchcodec": "video decoding: DSSP's LeRobot datasets hold no video",
        "pynput": "keyboard teleoperation",
        "cmake": "building LeRobot's optional native extras",
    },
}


def declared() -> set[str]:
    """Distribution names pyproject.toml declares (dependencies and every extra) and `make setup` installs by name."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    requirements = list(project["dependencies"])
    for extra in project["optional-dependencies"].values():
        requirements += extra
    makefile = (ROOT / "Makefile").read_text()
    for var in ("TORCH", "METAWORLD", "LEROBOT"):
        requirements.append(re.search(rf"^{var} \?= (\S+)$", makefile, re.M).group(1))
    names = {canonicalize_name(Requirement(r).name) for r in requirements}
    return names | {"lerobot-policy-dssp", canonicalize_name(project["name"])}


def first_party() -> set[str]:
    """Modules of this repository: its packages, the plugin, and the modules beside the tests and benchmarks."""
    names = {p for p in SOURCES if (ROOT / p / "__init__.py").exists()} | {"lerobot_policy_dssp"}
    for folder in ("tests", "benchmarks"):
        names |= {p.stem for p in (ROOT / folder).glob("*.py")}
    return names


def imports() -> dict[str, set[str]]:
    """Top-level module → the files that import it (function-local and guarded imports included)."""
    found: dict[str, set[str]] = {}
    for source in SOURCES:
        for path in sorted((ROOT / source).rglob("*.py")):
            if any(part.endswith(".egg-info") or part == "__pycache__" for part in path.parts):
                continue
            tree = ast.parse(path.read_text(), str(path))
            for node in ast.walk(tree):
                if isinstance(node, ast.Import):
                    names = [alias.name for alias in node.names]
                elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    names = [node.module]
                else:
                    continue
                for name in names:
                    found.setdefault(name.split(".")[0], set()).add(str(path.relative_to(ROOT)))
    return found


def test_every_third_party_import_comes_from_a_declared_distribution():
    provided = metadata.packages_distributions()
    ours, known = first_party(), declared()
    found = imports()
    assert {"numpy", "torch", "onnxruntime", "can", "zarr"} <= set(found)  # the walk sees the packages' imports
    problems = []
    for module, files in sorted(found.items()):
        if module in ours or module in sys.stdlib_module_names or module in NEWER_STDLIB or module == "__future__":
            continue
        dists = {canonicalize_name(d) for d in provided.get(module, [])}
        where = ", ".join(sorted(files)[:3])
        if not dists:
            problems.append(f"{module} (imported by {where}) is installed by no distribution: declare it in an extra")
        elif not dists & known:
            problems.append(
                f"{module} (imported by {where}) comes from {', '.join(sorted(dists))}, which no extra "
                f"of pyproject.toml declares"
            )
    assert not problems, "\n".join(problems)


@pytest.mark.parametrize("package", sorted(LEFT_OUT))
def test_each_requirement_of_a_package_installed_without_its_dependencies_is_here(package):
    """metaworld and lerobot go in with --no-deps (their pins contradict ours); what they need must come from
    our extras, or be named in LEFT_OUT with the reason."""
    requirements = [Requirement(r) for r in metadata.requires(package) or []]
    base = [r for r in requirements if r.marker is None or r.marker.evaluate({"extra": ""})]
    assert base, f"{package} lists no requirements: is it installed?"
    left_out = LEFT_OUT[package]
    missing = []
    for requirement in base:
        name = canonicalize_name(requirement.name)
        if name in left_out:
            continue
        try:
            metadata.version(name)
        except metadata.PackageNotFoundError:
            missing.append(
                f"{package} needs {requirement}, which is not installed: declare it in an extra, or name "
                f"it in LEFT_OUT with the reason"
            )
    assert not missing, "\n".join(missing)
    stale = set(left_out) - {canonicalize_name(r.name) for r in base}
    assert not stale, f"LEFT_OUT names requirements {package} no longer has: {sorted(stale)}"


def test_ci_runs_in_a_fresh_virtualenv():
    """CI's suite runs in a virtualenv that does not see the machine's own packages (.ci/run makes it)."""
    ci_script = (ROOT / ".ci" / "run").read_text()
    assert re.search(r"python3 -m venv --clear \.venv", ci_script) and "--system-site-packages" not in ci_script
    if os.environ.get("CI") != "true":
        return
    assert sys.prefix != sys.base_prefix, "CI's tests run outside a virtualenv"
    config = (Path(sys.prefix) / "pyvenv.cfg").read_text()
    assert re.search(r"include-system-site-packages\s*=\s*false", config), config

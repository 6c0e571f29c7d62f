"""The int8 products for a few rows (dssp_deploy/kernel/qgemm.h), through their harness (qgemm_check.cc): built
natively, every path this CPU has must run and match the plain C++ reference bit for bit and every path it lacks
must be reported unavailable; cross-built for aarch64, it runs under qemu on a CPU with the dot-product
instructions (neon_dot and neon) and on one without (neon alone)."""

import json
import os
import platform
import shutil
import subprocess
from pathlib import Path

import pytest
from conftest import CROSS_HINT, CROSS_TOOLS, QGEMM_X86_PATHS, ROOT, build_harness, cpu_flags

BUILD = ROOT / "build" / "qgemm"
HARNESS = "qgemm_check.cc"

X86_PATHS = QGEMM_X86_PATHS
ARM_PATHS = ("neon", "neon_dot")


def build(compiler: str, output: Path, *flags: str) -> Path:
    return build_harness(HARNESS, compiler, output, *flags)


def run(command: list[str], **env: str) -> tuple[int, dict]:
    """The harness's exit status and its JSON line."""
    result = subprocess.run(command, capture_output=True, text=True, timeout=300, env={**os.environ, **env})
    lines = result.stdout.strip().splitlines()
    assert lines, f"{command[0]} printed nothing (exit {result.returncode}): {result.stderr}"
    return result.returncode, json.loads(lines[-1])


@pytest.fixture(scope="module")
def native() -> Path:
    return build("g++", BUILD / "qgemm_check")


@pytest.fixture(scope="module")
def cross() -> Path:
    missing = [tool for tool in CROSS_TOOLS if shutil.which(tool) is None]
    if missing:
        pytest.fail(f"{', '.join(missing)} missing: the aarch64 build runs under qemu; {CROSS_HINT}")
    # one static armv8-a build: neon_dot is compiled for armv8.2-a+dotprod by a function attribute and chosen at run time
    return build("aarch64-linux-gnu-g++", BUILD / "qgemm_check_aarch64", "-static")


def test_every_path_this_cpu_has_matches_the_reference(native, monkeypatch):
    monkeypatch.delenv("DSSP_QGEMM_PATH", raising=False)
    code, report = run([str(native)])
    assert code == 0 and report["ok"], report
    flags = cpu_flags()
    machine = platform.machine()
    if machine in ("x86_64", "AMD64"):
        expected = [path for path, needs in X86_PATHS.items() if needs <= flags]  # fastest first
        lacking = [path for path in X86_PATHS if path not in expected] + list(ARM_PATHS)
        fastest = expected[0] if expected else "portable"
    else:
        assert machine == "aarch64", f"no paths are expected for {machine}"
        expected = ["neon"] + (["neon_dot"] if "asimddp" in flags else [])
        lacking = [path for path in ARM_PATHS if path not in expected] + list(X86_PATHS)
        fastest = expected[-1]
    assert set(report["run"]) == set(report["matched"]) == set(expected) | {"portable"}, report
    assert set(report["unavailable"]) == set(lacking), report  # reported, with why, never silently left out
    assert report["best"] == fastest, report
    assert report["cases"] >= 40
    if "avx512_vnni" in expected and "avx512vl" in flags:  # avx_vnni's kernel, run through the EVEX encoding here
        assert report["avx_vnni_kernel_evex"] == "matched", report


def test_dssp_qgemm_path_forces_a_path_and_refuses_one_this_cpu_lacks(native):
    code, report = run([str(native)], DSSP_QGEMM_PATH="portable")
    assert code == 0 and report["best"] == "portable"
    lacking = "neon" if platform.machine() != "aarch64" else "avx2"
    code, report = run([str(native)], DSSP_QGEMM_PATH=lacking)
    assert code == 2 and report["path_error"].startswith(f"DSSP_QGEMM_PATH={lacking}, but "), report
    assert "unset it or name an available path" in report["path_error"]
    code, report = run([str(native)], DSSP_QGEMM_PATH="avx1024")
    assert code == 2 and "is not one of auto, portable" in report["path_error"], report


@pytest.mark.parametrize("cpu, dot", [("max", True), ("cortex-a53", False)])
def test_aarch64_paths_match_under_qemu(cross, cpu, dot, monkeypatch):
    monkeypatch.delenv("DSSP_QGEMM_PATH", raising=False)
    code, report = run(["qemu-aarch64", "-cpu", cpu, str(cross)])
    assert code == 0 and report["ok"] and report["arch"] == "aarch64", report
    expected = ["portable", "neon"] + (["neon_dot"] if dot else [])
    assert report["run"] == report["matched"] == expected, report
    assert report["best"] == expected[-1]
    assert set(report["unavailable"]) == set(X86_PATHS) | ({"neon_dot"} if not dot else set()), report
    if not dot:
        assert "lacks the dot-product instructions" in report["unavailable"]["neon_dot"]


def test_on_a_cpu_without_avx512_the_avx2_path_is_chosen_and_matches(monkeypatch):
    """The x86-64 build on an emulated Haswell (AVX2 + FMA, no AVX-512, no VNNI: what many robot computers and
    older workstations have), whatever CPU runs the suite: it picks avx2, which matches the reference, and names the
    VNNI paths unavailable."""
    monkeypatch.delenv("DSSP_QGEMM_PATH", raising=False)
    assert platform.machine() == "x86_64", "the suite's machines are x86-64"
    if shutil.which("qemu-x86_64") is None:
        pytest.fail(f"qemu-x86_64 is missing; {CROSS_HINT}")
    binary = build("g++", BUILD / "qgemm_check_static", "-static")
    code, report = run(["qemu-x86_64", "-cpu", "Haswell", str(binary)])
    assert code == 0 and report["ok"] and report["best"] == "avx2", report
    assert report["run"] == report["matched"] == ["portable", "avx2"], report
    assert {"avx512_vnni", "avx_vnni"} <= set(report["unavailable"]), report

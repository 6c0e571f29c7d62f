"""The fused int8 Mamba block without ONNX Runtime (dssp_deploy/kernel/block_check.cc over mamba_block.h, the code
the ai.dssp::MambaBlockQ8 operator runs): built natively and for aarch64, where it runs under qemu on a CPU with
the dot-product instructions and on one without (the neon scan, and the portable one when asked for), each against
``export.fused_ops.block_reference``."""

import json
import os
import shutil
import struct
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import CROSS_HINT, CROSS_TOOLS, ROOT, block_case, build_harness

BUILD = ROOT / "build" / "block"
MAGIC = b"DSSPTENS"
CASES = [
    ("gated", 1, "actions"),
    ("none", 2, "actions"),
    ("gated", 2, "prefix"),
    ("gated", 1, "joint"),
    ("gated", 2, "step"),
]


def write_tensors(path: Path, tensors: dict[str, np.ndarray]) -> None:
    """block_check.cc's tensor file: per tensor its name, 'f' (float32) or 'b' (int8), its shape and its values."""
    with path.open("wb") as out:
        out.write(MAGIC)
        for name, value in tensors.items():
            value = np.array(value, order="C")  # (ascontiguousarray would make a scalar (1,))
            kind = {np.dtype(np.float32): b"f", np.dtype(np.int8): b"b"}[value.dtype]
            out.write(struct.pack("<I", len(name)) + name.encode() + kind + struct.pack("<I", value.ndim))
            out.write(struct.pack(f"<{value.ndim}q", *value.shape) + value.tobytes())


def read_tensors(path: Path) -> dict[str, np.ndarray]:
    data, at, out = path.read_bytes(), len(MAGIC), {}
    assert data[:at] == MAGIC
    while at < len(data):
        (length,) = struct.unpack_from("<I", data, at)
        name = data[at + 4 : at + 4 + length].decode()
        at += 4 + length
        kind, (ndim,) = data[at : at + 1], struct.unpack_from("<I", data, at + 1)
        shape = struct.unpack_from(f"<{ndim}q", data, at + 5)
        at += 5 + 8 * ndim
        dtype = np.float32 if kind == b"f" else np.int8
        count = int(np.prod(shape))
        out[name] = np.frombuffer(data, dtype, count, at).reshape(shape)
        at += count * np.dtype(dtype).itemsize
    return out


def case(tmp_path: Path, mlp: str, batch: int, part: str) -> tuple[Path, list[np.ndarray]]:
    """A block's inputs written for the harness, and what block_reference gives for them: (a, conv, ssm), the
    states after the tokens on the prefix alone, after the prefix's tokens on [prefix, actions] ("joint"), else
    (batch, 0, .) (not written). "step" is one prefix token from the given states, its states written: the scan's
    one-token path."""
    from export.fused_ops import block_reference

    fused, values = block_case(mlp, batch)
    plain = 3 if part == "joint" else 0  # the prefix's tokens before the actions', in one pass
    if part == "prefix":  # from zeros given, and from zeros as the exported graphs say it (empty states)
        values.update(
            conv_state=torch.zeros_like(values["conv_state"]), ssm_state=torch.zeros_like(values["ssm_state"])
        )
    if part == "joint":
        values.update(conv_state=values["conv_state"][:, :0], ssm_state=values["ssm_state"][:, :0])
    if part == "step":
        values.update(a=values["a"][:, :1])
    if part in ("prefix", "step"):
        values.update(mod=torch.zeros(0, values["a"].shape[-1]))
    with torch.no_grad():
        want = [t.numpy() for t in block_reference(*values.values(), fused.eps, plain)]
    if part not in ("prefix", "step", "joint"):
        want = [want[0], want[1][:, :0], want[2][:, :0]]
    path = tmp_path / f"{mlp}-{batch}-{part}.case"
    write_tensors(
        path,
        {
            **{name: value.numpy() for name, value in values.items()},
            "eps": np.array(fused.eps, np.float32),
            "plain": np.array(plain, np.float32),
        },
    )
    return path, want


def run(command: list[str], out: Path, **env: str) -> tuple[dict, dict[str, np.ndarray]]:
    result = subprocess.run(command, capture_output=True, text=True, timeout=300, env={**os.environ, **env})
    lines = result.stdout.strip().splitlines()
    assert lines, f"{command[0]} printed nothing (exit {result.returncode}): {result.stderr}"
    report = json.loads(lines[-1])
    assert result.returncode == 0 and report["ok"], report
    return report, read_tensors(out)


def assert_close(got: dict[str, np.ndarray], want: list[np.ndarray], where) -> None:
    for name, w in zip(("a", "conv", "ssm"), want):
        g = got[name]
        assert g.shape == w.shape, (where, name)
        assert np.abs(g - w).max(initial=0) <= 1e-3 * np.abs(w).max(initial=1), (where, name)


@pytest.fixture(scope="module")
def native() -> Path:
    return build_harness("block_check.cc", "g++", BUILD / "block_check")


@pytest.fixture(scope="module")
def cross() -> Path:
    missing = [tool for tool in CROSS_TOOLS if shutil.which(tool) is None]
    if missing:
        pytest.fail(f"{', '.join(missing)} missing: the aarch64 build runs under qemu; {CROSS_HINT}")
    return build_harness("block_check.cc", "aarch64-linux-gnu-g++", BUILD / "block_check_aarch64", "-static")


@pytest.mark.parametrize("mlp, batch, part", CASES)
def test_the_block_matches_its_reference_natively(native, tmp_path, mlp, batch, part, monkeypatch):
    """The default paths, one thread and three (the columns and channels split across them give the same bits)."""
    monkeypatch.delenv("DSSP_QGEMM_PATH", raising=False)
    monkeypatch.delenv("DSSP_SCAN_PATH", raising=False)
    path, want = case(tmp_path, mlp, batch, part)
    out = tmp_path / "out"
    _, one = run([str(native), str(path), str(out), "1"], out)
    assert_close(one, want, "native")
    report, three = run([str(native), str(path), str(out), "3"], out)
    assert report["threads"] == 3
    for name in one:
        assert np.array_equal(one[name], three[name]), name


@pytest.mark.parametrize("cpu, product", [("max", "neon_dot"), ("cortex-a53", "neon")])
@pytest.mark.parametrize("mlp, batch, part", CASES)
def test_the_block_matches_its_reference_on_aarch64_under_qemu(
    cross, tmp_path, cpu, product, mlp, batch, part, monkeypatch
):
    """On a CPU with sdot (neon_dot) and one without (neon), the scan on its neon path: the products' paths give the
    same bits as the portable one (their integer sums are exact), and the block matches the reference."""
    monkeypatch.delenv("DSSP_QGEMM_PATH", raising=False)
    monkeypatch.delenv("DSSP_SCAN_PATH", raising=False)
    path, want = case(tmp_path, mlp, batch, part)
    out = tmp_path / "out"
    report, got = run(["qemu-aarch64", "-cpu", cpu, str(cross), str(path), str(out), "2"], out)
    assert report["arch"] == "aarch64" and report["qgemm_path"] == product and report["scan_path"] == "neon", report
    assert_close(got, want, (cpu, product))
    _, portable = run(["qemu-aarch64", "-cpu", cpu, str(cross), str(path), str(out)], out, DSSP_QGEMM_PATH="portable")
    for name in got:
        assert np.array_equal(got[name], portable[name]), name


@pytest.mark.parametrize("mlp, batch, part", [("gated", 2, "prefix"), ("gated", 2, "step")])
def test_the_portable_scan_still_runs_on_aarch64_and_agrees_with_neon(cross, tmp_path, mlp, batch, part, monkeypatch):
    """DSSP_SCAN_PATH=portable on aarch64 (the loops GCC vectorises): the block matches the reference, and the neon
    scan to the same tolerance (another exp and summation order: close, not the same bits). The cases write the
    scan's state: over several tokens (scan_block) and over one (scan_step)."""
    monkeypatch.delenv("DSSP_QGEMM_PATH", raising=False)
    path, want = case(tmp_path, mlp, batch, part)
    out = tmp_path / "out"
    binary = ["qemu-aarch64", "-cpu", "cortex-a53", str(cross), str(path), str(out), "2"]
    report, portable = run(binary, out, DSSP_SCAN_PATH="portable")
    assert (report["arch"], report["scan_path"]) == ("aarch64", "portable"), report
    assert_close(portable, want, "portable")
    report, neon = run(binary, out, DSSP_SCAN_PATH="neon")
    assert report["scan_path"] == "neon", report
    assert_close(neon, want, "neon")
    assert_close(neon, [portable[name] for name in ("a", "conv", "ssm")], "neon against portable")


def test_a_path_the_cpu_lacks_is_one_line_not_a_crash(cross, native, tmp_path, monkeypatch):
    """x86-64 paths asked of the aarch64 build, and the neon scan of the native (x86-64) one."""
    monkeypatch.delenv("DSSP_QGEMM_PATH", raising=False)
    monkeypatch.delenv("DSSP_SCAN_PATH", raising=False)
    path, _ = case(tmp_path, "gated", 1, "actions")
    aarch64 = ["qemu-aarch64", "-cpu", "max", str(cross)]
    for binary, env, word in (
        (aarch64, dict(DSSP_SCAN_PATH="avx512"), "DSSP_SCAN_PATH=avx512"),
        (aarch64, dict(DSSP_QGEMM_PATH="avx2"), "DSSP_QGEMM_PATH=avx2"),
        ([str(native)], dict(DSSP_SCAN_PATH="neon"), "DSSP_SCAN_PATH=neon"),
    ):
        result = subprocess.run(
            [*binary, str(path), str(tmp_path / "out")],
            capture_output=True,
            text=True,
            timeout=300,
            env={**os.environ, **env},
        )
        report = json.loads(result.stdout.strip().splitlines()[-1])
        assert result.returncode == 2 and report["path_error"].startswith(word), report
        assert not (tmp_path / "out").exists()


@pytest.fixture(scope="module")
def static_x86() -> Path:
    """The x86-64 build, static, for qemu-x86_64's emulated CPUs."""
    if shutil.which("qemu-x86_64") is None:
        pytest.fail(f"qemu-x86_64 is missing; {CROSS_HINT}")
    return build_harness("block_check.cc", "g++", BUILD / "block_check_static", "-static")


# emulated x86-64 CPUs: Haswell (AVX2 + FMA, no AVX-512, no VNNI) and Nehalem (SSE4.2, no AVX): the paths each picks
EMULATED = [("Haswell", "avx2", "x86-64-v3"), ("Nehalem", "portable", "default")]


@pytest.mark.parametrize("cpu, path, clone", EMULATED)
def test_on_a_cpu_without_avx512_the_block_takes_its_paths_by_itself_and_matches(
    static_x86, tmp_path, monkeypatch, cpu, path, clone
):
    """The x86-64 build on an emulated CPU, whatever CPU runs the suite: the block picks the scan and products that
    CPU can run (the avx2 ones on Haswell, the portable ones and the baseline copies of the plain C++ loops on
    Nehalem) by itself and matches the reference."""
    monkeypatch.delenv("DSSP_QGEMM_PATH", raising=False)
    monkeypatch.delenv("DSSP_SCAN_PATH", raising=False)
    for mlp, batch, part in CASES:
        case_path, want = case(tmp_path, mlp, batch, part)
        out = tmp_path / "out"
        report, got = run(["qemu-x86_64", "-cpu", cpu, str(static_x86), str(case_path), str(out), "2"], out)
        assert (report["arch"], report["scan_path"], report["qgemm_path"]) == ("x86_64", path, path), report
        assert_close(got, want, (cpu, part))


def ddim_case(tmp_path: Path, sample: bool, clip: bool, tokens: bool) -> tuple[Path, list[np.ndarray]]:
    """ai.dssp::DdimStep's inputs and attributes written for the harness (d and A not multiples of a vector, so every
    loop runs its tail), and what ``export.fused_ops.ddim_step_reference`` gives for them: (x_next, a_next)."""
    from export.fused_ops import ddim_step_reference

    g = torch.Generator().manual_seed(7 + 4 * sample + 2 * clip + tokens)
    batch, H, d, A = 2, 3, 37, 7
    values = {
        "h": torch.randn(batch, H, d, generator=g),
        "x": 1.5 * torch.randn(batch, H, A, generator=g),  # some of x0 beyond [-1, 1], for the clip
        "norm_w": 1 + 0.1 * torch.randn(d, generator=g),
        "mod": 0.1 * torch.randn(2, d, generator=g),
        "out_w": torch.randn(A, d, generator=g) / d**0.5,
        "out_b": 0.1 * torch.randn(A, generator=g),
        "in_w": torch.randn(A, d, generator=g) / A**0.5,
        "in_b": 0.1 * torch.randn(d, generator=g),
        "pos": 0.1 * torch.randn(H, d, generator=g),
    }
    eps, a_t, a_prev = 1e-5, 0.3, 0.6
    with torch.no_grad():
        want = [t.numpy() for t in ddim_step_reference(*values.values(), eps, a_t, a_prev, sample, clip, tokens)]
    scalars = {
        "eps": eps,
        "c_t": a_t**0.5,
        "s_t": (1 - a_t) ** 0.5,
        "c_prev": a_prev**0.5,
        "s_prev": (1 - a_prev) ** 0.5,
        "sample": sample,
        "clip": clip,
        "tokens": tokens,
    }
    path = tmp_path / f"ddim-{sample:d}{clip:d}{tokens:d}.case"
    write_tensors(
        path,
        {**{k: v.numpy() for k, v in values.items()}, **{k: np.array(v, np.float32) for k, v in scalars.items()}},
    )
    return path, want


DDIM_CASES = [(True, True, True), (True, False, False), (False, True, True), (False, False, True)]


def assert_ddim_close(got: dict[str, np.ndarray], want: list[np.ndarray], where) -> None:
    for name, w in zip(("x_next", "a_next"), want):
        assert got[name].shape == w.shape, (where, name)
        assert np.abs(got[name] - w).max(initial=0) <= 1e-5 * max(1.0, np.abs(w).max(initial=1)), (where, name)


@pytest.mark.parametrize("sample, clip, tokens", DDIM_CASES)
def test_the_ddim_step_matches_its_reference_natively_and_on_emulated_cpus(
    native, static_x86, tmp_path, sample, clip, tokens
):
    """DdimStep's arithmetic (the readout, the DDIM update, the next tokens) in the copy each CPU takes: this CPU's,
    the AVX2 + FMA copy on Haswell and the baseline copy on Nehalem, which no CPU here would run otherwise."""
    case_path, want = ddim_case(tmp_path, sample, clip, tokens)
    out = tmp_path / "out"
    _, got = run([str(native), str(case_path), str(out)], out)
    assert_ddim_close(got, want, "native")
    for cpu, _, clone in EMULATED:
        report, got = run(["qemu-x86_64", "-cpu", cpu, str(static_x86), str(case_path), str(out)], out)
        assert report["ddim_clone"] == clone, report
        assert_ddim_close(got, want, cpu)

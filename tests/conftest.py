"""Test-wide settings: one intra-op thread, so results do not depend on the machine's core count
and small tensor ops do not stall when another process shares the cores; Ctrl-C as Python's default."""

import os
import shutil
import signal
import subprocess
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
# MuJoCo picks its OpenGL platform when it is first imported; every test module is imported at collection, in
# every worker, so the headless one is set here, before any of them (a window platform would hang a render thread).
os.environ.setdefault("MUJOCO_GL", "egl")

# A suite started in the background by a non-interactive shell (`make test &`) inherits SIGINT ignored, and
# every process it starts would too; the Ctrl-C tests send SIGINT, so the suite restores Python's default
# (its processes then start with the default as well).
if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

try:
    import torch
except ImportError:  # a deploy-only environment
    torch = None

if torch is not None:
    torch.set_num_threads(1)


import pytest  # noqa: E402

TEST_SEED = 0
"""The seed every test starts from (torch, numpy's global generator, ``random``): a test's result does not
depend on which tests ran before it in the same worker."""


@pytest.fixture(autouse=True)
def process_state():
    """Each test starts from the same process-wide state and leaves it as it found it: one torch intra-op
    thread, seeded global generators, and the environment, the working directory and the signal handlers
    restored afterwards (what a test, or code it calls, changes in the process stays with that test)."""
    import random

    import numpy as np

    environ, cwd = dict(os.environ), os.getcwd()
    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    random_state, numpy_state = random.getstate(), np.random.get_state()
    random.seed(TEST_SEED)
    np.random.seed(TEST_SEED)
    if torch is not None:
        threads, interop_rng = torch.get_num_threads(), torch.get_rng_state()
        torch.set_num_threads(1)
        torch.manual_seed(TEST_SEED)
    try:
        yield
    finally:
        if torch is not None:
            torch.set_num_threads(threads)
            torch.set_rng_state(interop_rng)
        random.setstate(random_state)
        np.random.set_state(numpy_state)
        for sig, handler in handlers.items():
            if handler is not None and signal.getsignal(sig) is not handler:
                signal.signal(sig, handler)
        os.chdir(cwd)
        if dict(os.environ) != environ:
            os.environ.clear()
            os.environ.update(environ)


def built_once(tmp_path_factory, request, name: str, build) -> tuple:
    """``build(root)`` (a tuple of paths) made once per test run, however many pytest-xdist workers need it:
    the first worker builds it under a file lock in the run's shared temporary folder, the others wait and
    reuse it. Tests treat such a fixture as read-only (they copy what they change)."""
    import json

    from filelock import FileLock

    base = tmp_path_factory.getbasetemp()
    worker = getattr(request.config, "workerinput", None)  # set in a pytest-xdist worker
    shared = base if worker is None else base.parent  # .../pytest-N, common to this run's workers only
    root, record = shared / f"built_{name}", shared / f"built_{name}.json"
    with FileLock(str(shared / f"built_{name}.lock")):
        if record.is_file():
            return tuple(Path(p) for p in json.loads(record.read_text()))
        shutil.rmtree(root, ignore_errors=True)  # what a failed build in another worker left
        root.mkdir()
        built = build(root)
        record.write_text(json.dumps([str(p) for p in built]))
    return built


def _build_tiny_export(root):
    from dssp_train.cli.train import main as train_main
    from dssp_train.data.synthetic import write_tap_count_dataset
    from export.to_onnx import main as export_main

    data = write_tap_count_dataset(root / "tap.zarr", 6, seed=0, n_points=32)
    run_dir, model_dir = root / "run", root / "model"
    assert (
        train_main(
            [
                "--data",
                str(data),
                "--out",
                str(run_dir),
                "--preset",
                "tiny",
                "--steps",
                "30",
                "--set",
                "train.val_every=30",
                "--no-progress",
            ]
        )
        == 0
    )
    assert export_main([str(run_dir), "-o", str(model_dir), "--skip-verify"]) == 0
    return run_dir, model_dir, data


@pytest.fixture(scope="session")
def tiny_export(tmp_path_factory, request):
    """A briefly trained tiny DSSP run and its exported model directory: (run_dir, model_dir, data_path)."""
    return built_once(tmp_path_factory, request, "tiny_export", _build_tiny_export)


# A small, quick training configuration (``--set`` overrides of the tiny preset) for CLI tests.
SMALL = [
    "model.d_model=32",
    "model.d_state=8",
    "model.n_denoiser_layers=2",
    "model.n_history_layers=1",
    "train.batch_size=4",
    "train.val_windows=4",
    "train.warmup_steps=1",
    "train.log_every=1",
    "train.val_every=2",
    "train.save_every=2",
]
SET_SMALL = [a for item in SMALL for a in ("--set", item)]


def one_error_line(stderr: str) -> str:
    """The one ``error: ...`` line a command printed (no traceback, nothing else)."""
    assert "Traceback" not in stderr, stderr
    lines = stderr.strip().splitlines()
    assert len(lines) == 1, stderr
    assert lines[0].startswith("error: "), stderr
    return lines[0]


from dssp_train.data.rig_reach import write_rig_reach as write_arm_dataset  # noqa: E402


def _arm_export(tmp_path_factory, request, n_arms: int):
    from dssp_train.cli.train import main as train_main
    from export.to_onnx import main as export_main

    def build(root):
        data = write_arm_dataset(root / "arm.zarr", n_arms=n_arms)
        run_dir, model_dir = root / "run", root / "model"
        assert (
            train_main(
                [
                    "--data",
                    str(data),
                    "--out",
                    str(run_dir),
                    "--preset",
                    "tiny",
                    "--steps",
                    "20",
                    "--set",
                    "train.val_every=20",
                    "--no-progress",
                ]
            )
            == 0
        )
        assert export_main([str(run_dir), "-o", str(model_dir), "--skip-verify"]) == 0
        return (model_dir,)

    return built_once(tmp_path_factory, request, f"arm_export_{n_arms}", build)[0]


@pytest.fixture(scope="session")
def arm_export(tmp_path_factory, request):
    """A briefly trained tiny model for one simulated Piper (state = action = 7): its model directory."""
    return _arm_export(tmp_path_factory, request, 1)


@pytest.fixture(scope="session")
def dual_arm_export(tmp_path_factory, request):
    """The same for the two-arm platform (state = action = 14, RoboTwin order)."""
    return _arm_export(tmp_path_factory, request, 2)


def snapshot(root):
    """Every path under ``root`` with what it is: a folder, a link and its target, a file's sha256, or "special" (a
    FIFO, socket or device: never opened)."""
    import hashlib

    found = {}
    for folder, dirs, files in os.walk(root, followlinks=False):
        for name in dirs + files:
            path = Path(folder, name)
            rel = str(path.relative_to(root))
            if path.is_symlink():
                found[rel] = "link:" + os.readlink(path)
            elif path.is_dir():
                found[rel] = "dir"
            elif path.is_file():
                found[rel] = hashlib.sha256(path.read_bytes()).hexdigest()
            else:
                found[rel] = "special"
    return found


def pytest_terminal_summary(terminalreporter, config):
    """The test order's seed on the last lines (``-q`` hides the header that names it): ``--randomly-seed=N``
    runs the same order again, ``-p no:randomly`` the files' own order."""
    seed = getattr(config.option, "randomly_seed", None)
    if seed is not None and getattr(config.option, "randomly_reorganize", True):
        terminalreporter.write_line(f"test order: random, --randomly-seed={seed}")


def cpu_flags() -> set[str]:
    """This CPU's feature words as Linux lists them (x86 ``flags``, aarch64 ``Features``): what a test of a CPU
    feature asks."""
    words = set()
    for line in Path("/proc/cpuinfo").read_text().splitlines():
        if line.startswith(("flags", "Features")):
            words |= set(line.split(":", 1)[1].split())
    return words


QGEMM_X86_PATHS = {
    "avx512_vnni": {"avx512f", "avx512bw", "avx512_vnni", "avx2", "fma"},
    "avx_vnni": {"avx_vnni", "avx2", "fma"},
    "avx2": {"avx2", "fma"},
}
"""dssp_deploy/kernel/qgemm.h's x86-64 paths, fastest first, and the CPU flags each needs."""


BLOCK_INPUTS = [
    "a",
    "conv_state",
    "ssm_state",
    "mod",
    "norm_w",
    "in_q",
    "in_s",
    "conv_w",
    "conv_b",
    "xp_q",
    "xp_s",
    "dt_q",
    "dt_s",
    "dt_b",
    "A",
    "D",
    "out_q",
    "out_s",
    "norm2_w",
    "fc1_q",
    "fc1_s",
    "fc2_q",
    "fc2_s",
]
"""``ai.dssp::MambaBlockQ8``'s inputs in order (dssp_deploy/kernel/mamba_ops.cc)."""


def block_case(mlp: str, batch: int, seed: int = 0):
    """A denoiser block of the sim preset's size with random weights (the AdaLN projection too), as
    ``export.fused_ops.QuantizedMambaBlock`` holds it, and inputs: (the block module, the inputs by name)."""
    import dataclasses

    from dssp_train.config import load_preset
    from dssp_train.model.denoiser import DenoiserBlock
    from export.fused_ops import QuantizedMambaBlock

    torch.manual_seed(seed)
    m = dataclasses.replace(load_preset("sim").model, state_dim=7, action_dim=7)
    block = DenoiserBlock(m.d_model, m.d_state, m.d_conv, m.expand, 0, mlp).eval()
    with torch.no_grad():
        for p in block.parameters():
            p.add_(torch.randn_like(p) * 0.05)
    fused = QuantizedMambaBlock(block)
    E, W, n, d = block.mixer.d_inner, block.mixer.d_conv, block.mixer.d_state, m.d_model  # noqa: N806
    values = {
        "a": torch.randn(batch, m.horizon, d),
        "conv_state": torch.randn(batch, E, W),
        "ssm_state": torch.randn(batch, E, n) * 0.3,
        "mod": torch.randn(3, d) * 0.2,
    }
    values.update({name: getattr(fused, name) for name in BLOCK_INPUTS[4:]})
    return fused, values


KERNEL_DIR = Path(__file__).resolve().parents[1] / "dssp_deploy" / "kernel"
CROSS_TOOLS = ("aarch64-linux-gnu-g++", "qemu-aarch64")
CROSS_HINT = "`make setup` installs them (its `system` target: apt-get install g++-aarch64-linux-gnu qemu-user)"


def build_harness(source: str, compiler: str, output: Path, *flags: str) -> Path:
    """A C++ harness of dssp_deploy/kernel (``source``, a file name there) compiled with -O2 into ``output``, again
    only when the binary is older than a source or header of that folder; a missing compiler fails the test with
    what installs it."""
    if shutil.which(compiler) is None:
        hint = CROSS_HINT if compiler in CROSS_TOOLS else "install a C++17 compiler (Debian: apt-get install g++)"
        pytest.fail(f"{compiler} is missing; {hint}")
    sources = [p for p in KERNEL_DIR.iterdir() if p.suffix in (".h", ".inc", ".cc")]
    if output.exists() and output.stat().st_mtime >= max(p.stat().st_mtime for p in sources):
        return output
    output.parent.mkdir(parents=True, exist_ok=True)
    partial = output.with_name(f"{output.name}.{os.getpid()}.tmp")  # a build beside another one never clashes
    command = [
        compiler,
        "-O2",
        "-std=c++17",
        "-Wall",
        "-Wextra",
        "-fopenmp-simd",
        "-fno-trapping-math",
        "-pthread",
        *flags,
        "-o",
        str(partial),
        str(KERNEL_DIR / source),
    ]
    result = subprocess.run(command, capture_output=True, text=True)
    assert result.returncode == 0, f"{compiler} failed:\n{result.stderr}"
    os.replace(partial, output)
    return output

"""Test-wide settings: one intra-op thread, so results do not depend on the machine's core count
and small tensor ops do not stall when another process shares the cores; Ctrl-C as Python's default.

And what the test modules share, defined here once: fixtures (pytest finds them), helpers and constants (a test module
imports them: ``from conftest import ...``)."""

import contextlib
import json
import math
import os
import shutil
import signal
import subprocess
import uuid
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


import numpy as np  # noqa: E402
import pytest  # noqa: E402

from dssp_data.dataset_layout import Episode  # noqa: E402
from dssp_data.observation import PointCloudConfig  # noqa: E402
from dssp_data.pointcloud import save_extrinsics  # noqa: E402
from dssp_data.recording import can_log_dir  # noqa: E402
from dssp_data.replay_buffer_writer import write_replay_buffer  # noqa: E402
from dssp_train.data.rig_reach import write_rig_reach as write_arm_dataset  # noqa: E402
from hardware.camera.tabletop import Box, SimCamera, intrinsics_for  # noqa: E402
from hardware.piper.limits import GRIPPER_STROKE_MAX, JointLimits  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
"""The repository's root folder."""
FIXTURES = ROOT / "tests" / "fixtures"
"""The files the tests read: small datasets and their expected contents."""
DP3_DATASET = FIXTURES / "dp3_zarr2_tiny.zarr"
"""A tiny dataset in DP3's zarr v2 layout."""
ONE_THREAD_ENV = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
"""The environment for a command run as a process of its own: this one's, one thread per BLAS and OpenMP pool."""

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


def one_error_line(err: str, *fragments: str) -> str:
    """The one ``error: ...`` line a command printed on stderr (``err``): no traceback, nothing else there; the line
    holds each of ``fragments``."""
    assert "Traceback" not in err, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("error: "), err
    for fragment in fragments:
        assert fragment in lines[0], (fragment, err)
    return lines[0]


def refusal(result: tuple[int, str, str], *fragments: str) -> str:
    """The line of a refused command, from its ``result`` (exit code, stdout, stderr): exit code 2, nothing on
    stdout, and :func:`one_error_line` on stderr, holding each of ``fragments``."""
    code, out, err = result
    assert code == 2, (code, out, err)
    assert out == "", (code, out, err)
    return one_error_line(err, *fragments)


def one_line_message(error, *fragments: str) -> str:
    """The message of a raised error (the exception, or pytest's ``ExceptionInfo`` of it): one line, holding each of
    ``fragments``."""
    message = str(error.value if isinstance(error, pytest.ExceptionInfo) else error)
    assert "\n" not in message, message
    for fragment in fragments:
        assert fragment in message, (fragment, message)
    return message


def _arm_export(tmp_path_factory, request, n_arms: int, export_flags: tuple[str, ...] = ("--skip-verify",)):
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
        assert export_main([str(run_dir), "-o", str(model_dir), *export_flags]) == 0
        return (model_dir,)

    return built_once(tmp_path_factory, request, f"arm_export_{n_arms}", build)[0]


@pytest.fixture(scope="session")
def arm_export(tmp_path_factory, request):
    """A briefly trained tiny model for one simulated Piper (state = action = 7): its model directory."""
    return _arm_export(tmp_path_factory, request, 1)


@pytest.fixture(scope="session")
def dual_arm_export(tmp_path_factory, request):
    """The same for the two-arm platform (state = action = 14, RoboTwin order): its fp32 standard graphs only."""
    return _arm_export(tmp_path_factory, request, 2, tuple(FAST_EXPORT))


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


KERNEL_DIR = ROOT / "dssp_deploy" / "kernel"
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


# ------------------------------------------------------------------------------------------------ datasets
def episodes(n: int, seed: int = 0, steps: int = 3, points: int = 4) -> list[Episode]:
    """``n`` random episodes of ``steps`` steps each: clouds of ``points`` points, 7 joint states and 7 actions."""
    rng = np.random.default_rng(seed)
    return [
        Episode(
            rng.normal(size=(steps, points, 3)).astype(np.float32),
            rng.normal(size=(steps, 7)).astype(np.float32),
            rng.normal(size=(steps, 7)).astype(np.float32),
        )
        for _ in range(n)
    ]


def recorded(path: Path, n: int = 3, seed: int = 0, **attrs) -> Path:
    """A dataset as dssp-record leaves it (:func:`episodes`, generator dssp-record, ``attrs`` added), one CAN log
    per episode in ``path.can``."""
    infos = [{"index": i, "can_logs": {"can0": f"episode_{i:06d}.can0.blf"}, "problems": []} for i in range(n)]
    write_replay_buffer(
        path,
        episodes(n, seed),
        attrs={"generator": "dssp-record", "control_rate_hz": 10.0, "episode_info": infos, **attrs},
    )
    can_log_dir(path).mkdir()
    for i in range(n):
        (can_log_dir(path) / f"episode_{i:06d}.can0.blf").write_bytes(b"log %d" % i)
    return path


def copy_dataset(src: Path, dst: Path) -> Path:
    """A copy of dataset ``src`` at ``dst``, with its CAN logs folder where it has one."""
    shutil.copytree(src, dst)
    if can_log_dir(src).is_dir():
        shutil.copytree(can_log_dir(src), can_log_dir(dst))
    return dst


def run_data_cli(capsys, *argv) -> tuple[int, str, str]:
    """dssp-data in-process: (exit code, stdout, stderr)."""
    from dssp_data.data_cli import main as data_main

    code = data_main([str(a) for a in argv])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


# A noiseless camera, so a frame is a function of its time, and a box sliding along the table, so each frame is its
# own: the camera of the converted ROS 2 bags and LeRobot datasets.
CAMERA = SimCamera(
    seed=0,
    intrinsics=intrinsics_for(160, 120, 70.0),
    noise_std=0.0,
    invalid_fraction=0.0,
    moving_box=lambda t: Box((0.1 + 0.2 * t, 0.0, 0.05), (0.08, 0.08, 0.1)),
)
CLOUD = PointCloudConfig(n_points=128)
"""The point-cloud settings those datasets are converted with."""
DEPTH_UNIT = 0.00025
"""A depth camera's unit: metres per depth value (0.25 mm)."""


def calibration_flags(folder: Path) -> list[str]:
    """--extrinsics and --pointcloud for a dataset seen by :data:`CAMERA` (converted with :data:`CLOUD`), their files
    written into ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    save_extrinsics(folder / "calib.json", CAMERA.camera_to_base)
    (folder / "cloud.json").write_text(json.dumps(CLOUD.to_dict()))
    return ["--extrinsics", str(folder / "calib.json"), "--pointcloud", str(folder / "cloud.json")]


# ------------------------------------------------------------------------------------------------ training
@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    """A module's training set: 4 tap-count episodes recorded at 10 Hz, 24 points per cloud (one episode held out
    for validation)."""
    from dssp_train.data.synthetic import write_tap_count_dataset

    return write_tap_count_dataset(tmp_path_factory.mktemp("data") / "tap.zarr", 4, seed=0, n_points=24)


@pytest.fixture(scope="module")
def trained(tmp_path_factory, data) -> Path:
    """A finished 2-step run on ``data`` (checkpoint at step 2)."""
    from dssp_train.cli.train import main as train_main

    out = tmp_path_factory.mktemp("trained") / "run"
    assert train_main(["--data", str(data), "--out", str(out), "--steps", "2", "--no-progress", *SET_SMALL]) == 0
    return out


FAST_EXPORT = ["--format", "onnx", "--skip-verify", "--quantize", "none", "--no-fused"]
"""The quickest export's flags: ONNX graphs, neither verified nor quantised nor fused."""
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
"""The first bytes of every PNG file."""
STUDY_ENTRIES = "study_entries"
"""The module of the stage runner's test entry points (tests/ is on sys.path: pytest puts it there, spawned stages
inherit it)."""


# ------------------------------------------------------------------------------------------------ the arm
LIMITS = JointLimits.piper()
"""The Piper's joint limits."""
GRIPPER = np.arange(7) == 6
"""Which of the Piper's 7 action values is the gripper's."""
WIRE = 2e-5
"""One wire unit in policy units, with room: 0.001 degree in rad, 1 µm of stroke in opening units (x 1/0.07)."""
MDEG = math.radians(0.001)
"""One wire unit of a joint angle (0.001 degree), in radians."""
UM = 1e-6
"""One wire unit of a gripper stroke (1 µm), in metres."""
CALIBRATION_START = np.array([0.0, 1.2, -1.0, 0.0, 0.6, 0.0])
"""A pose to plan a calibration from: inside the limits, the wrist away from its singularity."""


def channel(tag: str) -> str:
    """A virtual CAN channel's name of its own (``tag`` and a random suffix): no other test's bus shares it."""
    return f"test-{tag}-{uuid.uuid4().hex[:10]}"


def sent_commands(blf_path) -> np.ndarray:
    """The joint+gripper commands on the bus, (n, 7) in policy units, from the 0x155-0x157 + 0x159 frames."""
    from hardware.can_log import read_log
    from hardware.piper import codec

    decoder = codec.Decoder()
    commands, joints = [], {}
    gripper = None
    for frame in read_log(blf_path):
        msg = decoder.decode(frame)
        if isinstance(msg, codec.JointCtrl):
            joints[msg.pair] = (msg.first, msg.second)
            if msg.pair == 2:
                assert set(joints) == {0, 1, 2}, "joint frames out of order"
                commands.append([*joints[0], *joints[1], *joints[2], np.nan])
                joints = {}
        elif isinstance(msg, codec.GripperCtrl) and msg.code == codec.GRIPPER_ENABLE:
            gripper = msg.stroke / GRIPPER_STROKE_MAX
            if commands and np.isnan(commands[-1][6]):
                commands[-1][6] = gripper
    return np.array(commands).reshape(-1, 7)


def assert_within_limits(commands: np.ndarray, max_step) -> None:
    """Every command (:func:`sent_commands`) lies within the Piper's joint limits and the gripper's [0, 1], and no
    step between two commands is larger than ``max_step`` (per value), to a wire unit."""
    assert np.all(commands[:, :6] >= LIMITS.lower[:6] - WIRE) and np.all(commands[:, :6] <= LIMITS.upper[:6] + WIRE)
    grip = commands[:, 6][~np.isnan(commands[:, 6])]
    assert np.all(grip >= -WIRE) and np.all(grip <= 1 + WIRE)
    steps = np.abs(np.diff(commands, axis=0))
    steps = np.where(np.isnan(steps), 0, steps)
    assert np.all(steps <= max_step + 2 * WIRE), steps.max(axis=0)


def run_dssp(capsys, *argv) -> tuple[int, str, str]:
    """dssp-run in-process: (exit code, stdout, stderr); a flag argparse refuses exits 2 with its one line."""
    from hardware.cli.run import main as run_main

    try:
        code = run_main([str(a) for a in argv])
    except SystemExit as exc:
        code = exc.code
    out, err = capsys.readouterr()
    return code, out, err


def catches(pid: int, signum: int) -> bool:
    """Whether process ``pid`` has a handler for ``signum`` (its SigCgt mask under /proc)."""
    status = Path(f"/proc/{pid}/status").read_text()
    caught = int(next(line.split()[1] for line in status.splitlines() if line.startswith("SigCgt:")), 16)
    return bool(caught >> (signum - 1) & 1)


def ticks_logged(log_dir: Path) -> int:
    """How many ticks the run log in ``log_dir`` holds so far (0 before it has any)."""
    from hardware.run_log import read_ticks

    try:
        return len(read_ticks(log_dir))
    except FileNotFoundError:
        return 0


# The moments of dssp-run's start-up seen from outside, in the order they come, and what shows each: its stop
# handlers caught (main()'s first step; the imports follow), the log directory's lock file (the model loads
# next), the "graphs:" line on stderr (the model loaded and checked; the last start-up check follows), the log
# directory made (claimed: from here a stop is the runner's), a CAN log (the devices open; the runner waits for
# the first frame and feedback, then enables the arm), the first logged tick (running).
START_UP = ("handler", "log locked", "model loaded", "log claimed", "devices open", "first tick")


def wait_for_start_up(proc: subprocess.Popen, output, log_dir: Path, moment: str, timeout: float = 120.0) -> None:
    """Wait until ``proc`` (a dssp-run on ``log_dir``, its pipes read by ``output``, a ``waiting.Output``) has
    reached ``moment`` of :data:`START_UP`, or has ended."""
    from waiting import wait_for

    from dssp_core.staging import writer_lock_path

    what = f"dssp-run's start-up: {moment}"
    if moment == "model loaded":  # a line it prints: waited for as it comes
        output.wait_for_line("stderr", "graphs: ", timeout=timeout, what=what)
        return
    shown = {
        "handler": lambda: catches(proc.pid, signal.SIGTERM),
        "log locked": writer_lock_path(log_dir).exists,
        "log claimed": log_dir.is_dir,
        "devices open": lambda: any(log_dir.glob("can_*.blf")),
        "first tick": lambda: ticks_logged(log_dir) >= 1,
    }[moment]
    wait_for(lambda: proc.poll() is not None or shown(), timeout=timeout, what=what, poll=0.005)


def widened_copy(model_dir: Path, dst: Path) -> Path:
    """A copy of ``model_dir`` whose manifest accepts the simulated rig's observations (joints near zero, the
    sim camera's tabletop): the loop tests hold for the reason they inject, not for the fixture's narrow data."""
    from dssp_deploy.manifest import MANIFEST_NAME

    shutil.copytree(model_dir, dst)
    manifest = json.loads((dst / MANIFEST_NAME).read_text())
    for name, low, high in (("agent_pos", -1.0, 1.0), ("point_cloud", -1.0, 1.0)):
        stats = manifest["normalizers"][name]
        stats["input_min"], stats["input_max"] = [low] * len(stats["input_min"]), [high] * len(stats["input_max"])
    (dst / MANIFEST_NAME).write_text(json.dumps(manifest))
    return dst


@contextlib.contextmanager
def rig_loop(arm_export, tmp_path, monkeypatch, edit_cloud):
    """The robot's loop (``hardware.run_loop.Runner``) on the simulated camera and arm, with every cloud passed
    through ``edit_cloud(cloud) -> cloud`` first: yields (policy, runner, ticks), ``ticks(n)`` the records of n
    ticks, each on a fresh frame, one right after the other: nothing here waits on the loop's period. Generous
    timeouts and no deadline hold: the only reason to hold is what the test injects."""
    from dssp_deploy.onnx_policy import OnnxPolicy
    from hardware import run_loop
    from hardware.piper.piper_robot import open_robot
    from hardware.policies.exported_model import ModelPolicy
    from hardware.rig import Rig
    from hardware.safety import SafetyConfig

    real_cloud = run_loop.frame_to_cloud

    def edited(frame, config, camera_to_base=None):
        cloud, info = real_cloud(frame, config, camera_to_base)
        return edit_cloud(cloud), info

    monkeypatch.setattr(run_loop, "frame_to_cloud", edited)
    policy = OnnxPolicy(widened_copy(arm_export, tmp_path / "model"), threads=1)  # accepts the rig's observations
    camera, robot = SimCamera(seed=0), open_robot("sim")
    safety = SafetyConfig(camera_timeout=2.0, feedback_timeout=2.0, deadline_hold=False)
    camera.start(thread=False)
    camera.capture()
    try:
        with robot:
            rig = Rig(camera, robot, camera.camera_to_base, safety, limits=(LIMITS.lower, LIMITS.upper, GRIPPER))
            runner = run_loop.Runner(
                ModelPolicy(policy, 50.0, seed=0),
                rig,
                PointCloudConfig(n_points=64),
                run_loop.LoopSettings(control_rate_hz=50.0),
            )
            runner.start()

            def ticks(n):
                out = []
                for _ in range(n):
                    camera.capture()
                    out.append(runner.tick())
                return out

            yield policy, runner, ticks
            runner.finish("test over")
    finally:
        camera.stop()


def policy_state(p) -> tuple:
    """A copy of what an ``OnnxPolicy`` holds of its history: (steps, recent, context, state)."""
    return p.steps, p.recent.copy(), p.context.copy(), {k: v.copy() for k, v in p.state.items()}


def assert_policy_state_kept(p, kept: tuple) -> None:
    """``p`` still holds the history ``kept`` (a :func:`policy_state`): the same steps, recent states, context and
    recurrent states."""
    steps, recent, context, state = policy_state(p)
    assert steps == kept[0] and np.array_equal(recent, kept[1]) and np.array_equal(context, kept[2])
    assert state.keys() == kept[3].keys() and all(np.array_equal(state[k], kept[3][k]) for k in kept[3])

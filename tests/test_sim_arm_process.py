"""``dssp-sim-arm`` as a separate process on udp_multicast (hop limit 0: frames stay on this host),
driven by our driver from the test process; signals end it cleanly; bad arguments give one error line.

Each test uses its own multicast group and UDP port derived from the pid, so parallel runs do not meet.
"""

import json
import os
import re
import select
import signal
import socket
import subprocess
import sys

import numpy as np
import pytest
import waiting
from conftest import MDEG, ROOT

from hardware.cli.can_sim import main as sim_arm_main
from hardware.piper.arm import PiperArm
from hardware.piper.piper_robot import open_robot


def endpoint(k: int) -> tuple[str, int]:
    """A multicast group and UDP port for this process and slot k."""
    pid = os.getpid()
    group = f"239.{200 + k}.{(pid >> 8) & 0xFF}.{pid & 0xFF}"
    port = 20000 + (pid * 7 + k) % 30000
    return group, port


def start_sim(channels: str, port: int, *extra: str) -> tuple[subprocess.Popen, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), env.get("PYTHONPATH", "")) if p)
    env["CAN_CONFIG"] = json.dumps({"hop_limit": 0, "port": port})
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "hardware.cli.can_sim",
            "--channel",
            channels,
            "--interface",
            "udp_multicast",
            "--port",
            str(port),
            *extra,
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
        env=env,
    )
    ready, _, _ = select.select([proc.stdout], [], [], 30.0)
    if not ready:
        proc.kill()
        raise AssertionError(f"dssp-sim-arm printed nothing in 30 s: {proc.communicate()}")
    line = proc.stdout.readline()
    if not line:
        raise AssertionError(f"dssp-sim-arm exited early: rc={proc.wait()} {proc.stderr.read()}")
    return proc, line


def stop_sim(proc: subprocess.Popen, sig=signal.SIGTERM) -> tuple[str, str]:
    proc.send_signal(sig)
    out, err = proc.communicate(timeout=15)
    assert proc.returncode == 0, err
    assert "Traceback" not in err
    return out, err


def wait_for(predicate, timeout: float = 10.0, what: str = "condition"):
    """Across processes: a longer default timeout, a slower poll."""
    return waiting.wait_for(predicate, timeout, what, poll=0.01)


def test_driver_enables_and_moves_a_sim_arm_process():
    group, port = endpoint(0)
    proc, line = start_sim(group, port)
    try:
        assert "1 simulated Piper arm(s) on udp_multicast " + group in line and f"port {port}" in line
        arm = PiperArm(group, "udp_multicast", bus_options={"port": port})
        arm.connect()
        try:
            wait_for(lambda: arm.feedback().joints is not None, what="feedback from the process")
            arm.enable(5.0)
            # A stray datagram on the group is counted and skipped by both ends, not fatal.
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as stray:
                stray.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 0)
                stray.sendto(b"not a CAN frame", (group, port))
            wait_for(lambda: arm.decoder.counts["receive_error"] == 1, what="stray datagram counted")
            target = np.array([0.4, 0.3, -0.35, 0.2, -0.1, 0.5])
            arm.set_joint_mode(100)
            arm.command_joints(target)
            arm.command_gripper(0.04)
            wait_for(lambda: np.allclose(arm.feedback().joints, target, atol=MDEG), what="joint target reached")
            wait_for(lambda: abs(arm.feedback().gripper.stroke - 0.04) < 2e-6, what="gripper target reached")
            st = arm.status()
            assert st.enabled and not st.error, st.detail
            assert arm.decoder.counts["decoded"] > 0 and arm.decoder.counts["unknown_id"] == 0
        finally:
            arm.close()
    finally:
        if proc.poll() is None:
            out, _ = stop_sim(proc)
        else:
            out = proc.stdout.read()
    summary = re.search(r"stopped after [\d.]+ s; (\S+): (\d+) ticks, (\d+) frames sent, (\d+) commands received", out)
    assert summary, out
    assert summary.group(1) == group and int(summary.group(2)) > 0 and int(summary.group(4)) >= 6


def test_two_arms_in_one_process_stay_apart():
    (left, port), (right, _) = endpoint(1), endpoint(2)
    proc, line = start_sim(f"{left},{right}", port)
    try:
        assert "2 simulated Piper arm(s)" in line
        with open_robot(f"{left},{right}", interface="udp_multicast", bus_options={"port": port}) as robot:
            wait_for(robot.state, what="state of both arms")
            robot.enable(5.0)
            target = np.array([0.3, 0.2, -0.2, 0.1, 0.0, 0.1, 0.25, -0.3, 0.5, -0.6, -0.1, 0.2, -0.2, 0.75])

            def commanded_and_reached() -> bool:  # the simulator process moves the arms on wall time
                robot.command(target)
                return np.allclose(robot.state().position, target, atol=2 * MDEG)

            waiting.wait_for(commanded_and_reached, 10.0, "both arms at the target", poll=0.02)
    finally:
        if proc.poll() is None:
            stop_sim(proc)


def test_sigint_ends_the_process_cleanly():
    group, port = endpoint(3)
    proc, _ = start_sim(group, port, "--feedback-rate", "50")
    out, _ = stop_sim(proc, signal.SIGINT)
    assert "stopped after" in out


def test_bad_arguments_exit_2_with_one_error_line():
    proc = subprocess.run(
        [sys.executable, "-m", "hardware.cli.can_sim", "--channel", "10.0.0.1"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=60,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    assert proc.returncode == 2 and proc.stdout == ""
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "multicast group" in lines[0]


@pytest.mark.parametrize(
    "argv, needle",
    [
        ([], "--channel"),
        (["--channel", "239.1.2.3", "--feedback-rate", "0"], "--feedback-rate"),
        (["--channel", "239.1.2.3", "--feedback-rate", "nan"], "--feedback-rate"),
        (["--channel", "239.1.2.3", "--duration", "-1"], "--duration"),
        (["--channel", "239.1.2.3", "--port", "70000"], "--port"),
        (["--channel", "239.1.2.3,,239.1.2.4"], "empty"),
        (["--channel", "239.1.2.3,239.1.2.3"], "twice"),
        (["--channel", "can0"], "multicast group"),
        (["--channel", "x", "--interface", "socketcan"], "--interface"),
    ],
)
def test_bad_arguments_in_process(argv, needle, capsys):
    assert sim_arm_main(argv) == 2
    out, err = capsys.readouterr()
    assert out == "" and len(err.strip().splitlines()) == 1 and err.startswith("error: ") and needle in err


def test_duration_on_a_virtual_channel(capsys):
    assert (
        sim_arm_main(
            [
                "--channel",
                f"sim-arm-cli-{os.getpid()}",
                "--interface",
                "virtual",
                "--duration",
                "0.2",
                "--feedback-rate",
                "100",
            ]
        )
        == 0
    )
    out, err = capsys.readouterr()
    lines = out.strip().splitlines()
    assert len(lines) == 2 and "on virtual" in lines[0] and "stopped after" in lines[1] and err == ""

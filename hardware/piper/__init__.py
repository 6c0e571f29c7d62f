"""AgileX Piper arms on CAN: frame codec, one-arm driver, the two-arm ``Robot``, limits, and a simulator.

``open_robot("can0,can1")`` gives the dual-arm robot in policy units (14 values, RoboTwin order);
``open_robot("sim:2")`` the same on in-process simulated arms. ``hardware.piper.limits`` is the single
source of joint limits and gripper range and needs only numpy; the rest needs python-can, imported on
first use of a name below.
"""

from importlib import import_module

_EXPORTS = {
    "JointLimits": "hardware.piper.limits",
    "PiperArm": "hardware.piper.arm",
    "PiperFeedback": "hardware.piper.arm",
    "PiperRobot": "hardware.piper.piper_robot",
    "open_robot": "hardware.piper.piper_robot",
    "SimulatedPiper": "hardware.piper.can_simulator",
}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'hardware.piper' has no attribute {name!r}")

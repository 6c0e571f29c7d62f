"""The task's scripted expert as the control loop's policy source (``dssp-sim eval --expert``).

    source = ScriptedExpert(env)      # the expert of env's task, made afresh at each loop start (after env.reset)

The expert that records the demonstrations (:mod:`dssp_sim.experts`) drives the arm here through the robot's own
chain instead of setting the simulator's targets: the control loop of ``dssp-run``, the safety layer (limits,
per-tick step), Piper CAN frames to the simulated arm. It reads the scene from the simulator (it is privileged:
it knows where the objects are), so it needs no point cloud. Its success is what the chain leaves of the task's
ceiling: a task a model fails through the loop and the expert does not fails on the model's side. Shapes: state
and action (7,) [J1..J6 rad, gripper opening 0..1].
"""

from __future__ import annotations

import numpy as np

from hardware.policies import Act, PolicySource


class ScriptedExpert(PolicySource):
    name = "expert"
    needs_cloud = False

    def __init__(self, env):
        self.env = env
        self.control_rate_hz = env.control_rate_hz
        self.expert = None

    def reset(self, state: np.ndarray) -> None:
        from dssp_sim.experts import make_expert  # deferred: loads mujoco

        self.expert = make_expert(self.env)  # the scene as reset: an expert belongs to one episode

    def act(self, cloud, state) -> Act:
        return Act(np.asarray(self.expert.act(self.env), dtype=np.float64), events=[f"phase {self.expert.phase}"])

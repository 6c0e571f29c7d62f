"""dssp_sim: a MuJoCo simulation of the AgileX Piper workcell with memory tasks and scripted experts.

- ``dssp_sim.mjcf``: the MJCF of the arm, table and depth camera, generated from the Piper's DH table;
- ``dssp_sim.tasks``: the tasks ``tap``, ``swap`` and ``put2`` (objects, randomisation, scoring);
- ``dssp_sim.env``: ``PiperEnv``, the simulation at the policy's control rate, with depth rendering;
- ``dssp_sim.experts``: scripted experts (``make_expert``) for collecting demonstrations;
- ``dssp_sim.ik``: damped-least-squares inverse kinematics on MuJoCo's Jacobian;
- ``dssp_sim.teleop``: the teleoperation rig ``dssp-sim record`` (``--camera mujoco --can mujoco``) records from (the
  expert as a leader arm on a virtual CAN bus, the MuJoCo follower, the simulated camera, in lockstep).

Rendering is headless: importing ``dssp_sim`` sets ``MUJOCO_GL=egl`` unless it is set already. MuJoCo
chooses its GL backend when it is first imported, so import ``dssp_sim`` before ``mujoco`` (or export
``MUJOCO_GL=egl``); otherwise rendering looks for a display.
"""

import os

os.environ.setdefault("MUJOCO_GL", "egl")

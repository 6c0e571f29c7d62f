"""Small demonstrations for the simulated rig (``dssp-run --camera tabletop --can sim``): a reach in the Piper's
joint space whose observations lie inside what the rig produces, so that a model trained on them runs there
without the runtime refusing its observations (tests, benchmarks).

Per episode of ``steps`` steps, 7 values per arm [J1..J6 rad, gripper opening 0..1]: from rest (all zeros, the
simulated arm's power-on pose) a slow reach to :data:`ARM_HOME` and past it by a random offset; point clouds
(steps, P, 3) drawn uniformly in the default crop box; ``action[t] = state[t + 1]``; recorded at 50 Hz.
"""

from __future__ import annotations

import numpy as np

from dssp_data.dataset_layout import Episode
from dssp_data.observation import PointCloudConfig
from dssp_data.replay_buffer_writer import write_replay_buffer

ARM_HOME = (0.0, 0.6, -0.6, 0.0, 0.4, 0.0, 0.8)  # one Piper: J1..J6 rad, gripper opening 0..1
CONTROL_RATE_HZ = 50.0


def write_rig_reach(path, n_episodes: int = 4, n_arms: int = 1, steps: int = 30, n_points: int = 64, seed: int = 0):
    """Write the dataset (DP3 zarr) to ``path``; returns ``path``."""
    rng = np.random.default_rng(seed)
    home = np.tile(np.array(ARM_HOME), n_arms)
    crop = PointCloudConfig()
    episodes = []
    for _ in range(n_episodes):
        offset = rng.uniform(-0.15, 0.15, home.shape)
        s = np.linspace(0, 1, steps + 1)[:, None]
        joints = (np.minimum(1.0, 2 * s) * home + np.sin(np.pi * s) * offset).astype(np.float32)
        cloud = rng.uniform(crop.crop_min, crop.crop_max, (steps, n_points, 3)).astype(np.float32)
        episodes.append(Episode(point_cloud=cloud, state=joints[:-1], action=joints[1:]))
    write_replay_buffer(path, episodes, attrs={"control_rate_hz": CONTROL_RATE_HZ, "task": "reach"})
    return path

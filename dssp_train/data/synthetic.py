"""A small synthetic task that only a policy with memory can solve: "tap count".

Each episode taps the table once or twice, as told by a cue that is visible
only at the start, then parks the arm. All times are in steps (10 Hz):

====================  =====  =====================================================
phase                 steps  arm state (x, y), starting at home (0, 0)
====================  =====  =====================================================
cue                   3      at home; the cue cluster is in the point cloud
tap (n_taps times)    14     y 0.2, 0.4 ... 1.0 (5 steps), 0.8 ... 0.0 (5 steps),
                             then 4 pause steps at home
park                  5      x 0.2, 0.4 ... 1.0 with y = 0
hold                  rest   at (1, 0) until step 40
====================  =====  =====================================================

Every episode has :data:`EPISODE_LENGTH` = 40 steps (3 + 2 * 14 + 5 = 36 for
two taps, so at least 4 hold steps). ``action[t] = state[t + 1]`` (an absolute
target, as RoboTwin records it) and the last action repeats the last state.

Observation aliasing: during the pause after the first tap (steps
:data:`FIRST_PAUSE_STEPS` = 13..16) the state is exactly (0, 0) and the point
cloud differs only by noise in one-tap and two-tap episodes; indeed all
observations from step 3 to 16 are alike. At step 16 the expert's next
targets diverge: one-tap episodes park (x rises), two-tap episodes tap again
(y rises). Only the cue seen 14 steps earlier tells which.

Point cloud, (P, 3) per step: a table plane of ``P - 8`` points at z = 0 (laid
out once per seed, the same in every episode and step), 8 arm points around
(x, y, 0.1), and during the cue steps 8 marker points that replace the last 8
table points: around (-0.8, 1.0, 0.05) for one tap, (1.8, 1.0, 0.05) for two,
outside the table and out of the arm's reach. Gaussian noise of std
:data:`NOISE_STD` is added to every point; the state carries no noise.
"""

from __future__ import annotations

import numbers
import os
from pathlib import Path

import numpy as np

from dssp_core.errors import ConfigError
from dssp_core.schema import DEFAULT_CONTROL_RATE_HZ
from dssp_data.dataset_layout import Episode
from dssp_data.replay_buffer_writer import write_replay_buffer

__all__ = [
    "CUE_STEPS",
    "DECISION_STEP",
    "EPISODE_LENGTH",
    "FIRST_PAUSE_STEPS",
    "NOISE_STD",
    "chunk_decision",
    "count_taps",
    "expert_decision",
    "make_tap_count_episodes",
    "tap_count_states",
    "write_tap_count_dataset",
]

CUE_STEPS = 3
RAMP_STEPS = 5
PAUSE_STEPS = 4
TAP_STEPS = 2 * RAMP_STEPS + PAUSE_STEPS  # 14
PARK_STEPS = 5
EPISODE_LENGTH = 40
FIRST_PAUSE_STEPS = range(CUE_STEPS + 2 * RAMP_STEPS, CUE_STEPS + TAP_STEPS)  # steps 13..16
N_ARM_POINTS = 8
N_CUE_POINTS = 8
MIN_POINTS = N_ARM_POINTS + N_CUE_POINTS + 8
NOISE_STD = 0.002
CUE_CENTERS = {1: (-0.8, 1.0, 0.05), 2: (1.8, 1.0, 0.05)}
MAX_EPISODES = 10_000
MAX_POINTS = 100_000
MAX_SEED = 2**63 - 1
MAX_CLOUD_BYTES = 2 * 10**9  # all point clouds together, float32: they are built in memory before writing
ARM_HEIGHT = 0.1
TABLE_LOW, TABLE_HIGH = -0.5, 1.5


def tap_count_states(n_taps: int) -> np.ndarray:
    """The expert's arm positions for ``n_taps`` taps: (EPISODE_LENGTH, 2) float32 (x, y)."""
    if n_taps not in (1, 2):
        raise ValueError(f"n_taps must be 1 or 2, got {n_taps}")
    ramp = np.arange(1, RAMP_STEPS + 1) / RAMP_STEPS  # 0.2, 0.4, ..., 1.0
    zeros = np.zeros(RAMP_STEPS)
    tap = np.concatenate(
        [
            np.stack([zeros, ramp], axis=1),  # y up
            np.stack([zeros, 1.0 - ramp], axis=1),  # y down, ends at home
            np.zeros((PAUSE_STEPS, 2)),  # pause at home
        ]
    )
    park = np.stack([ramp, zeros], axis=1)
    states = np.concatenate([np.zeros((CUE_STEPS, 2))] + [tap] * n_taps + [park])
    hold = np.repeat(states[-1:], EPISODE_LENGTH - len(states), axis=0)
    return np.concatenate([states, hold]).astype(np.float32)


def count_taps(states: np.ndarray, height: float = 0.9) -> int:
    """Number of times y rises to ``height`` or above in ``states`` (T, 2); e.g. to score a rollout."""
    high = np.asarray(states)[:, 1] >= height
    return int(np.count_nonzero(high[1:] & ~high[:-1]) + bool(high[:1].any()))


DECISION_STEP = FIRST_PAUSE_STEPS[-1]  # 16: the last aliased step, where the expert's next move splits


def expert_decision(episode: Episode) -> str:
    """What the expert does after the first pause: "park" (one-tap episode) or "tap" (two-tap)."""
    return "park" if count_taps(episode.state) == 1 else "tap"


def chunk_decision(chunk: np.ndarray, state: np.ndarray) -> str:
    """Read a predicted action chunk (H, 2) from ``state`` (2,): "park" if it moves more in x than in y."""
    move = np.asarray(chunk)[-1] - np.asarray(state)
    return "park" if move[0] > move[1] else "tap"


def _scene(seed: int, n_points: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fixed layout for a seed: table (P - 8, 3), arm offsets (8, 3), cue offsets (8, 3)."""
    rng = np.random.default_rng((seed, 0))
    n_table = n_points - N_ARM_POINTS
    table = np.zeros((n_table, 3))
    table[:, :2] = rng.uniform(TABLE_LOW, TABLE_HIGH, size=(n_table, 2))
    arm = rng.uniform(-0.05, 0.05, size=(N_ARM_POINTS, 3))
    cue = rng.uniform(-0.03, 0.03, size=(N_CUE_POINTS, 3))
    return table, arm, cue


def _n_taps(seed: int, i: int) -> int:
    """1 or 2: each pair of episodes (2k, 2k + 1) holds one of each, in a seeded order."""
    flip = int(np.random.default_rng((seed, 1, i // 2)).integers(2))
    return 1 + ((i % 2) ^ flip)


def _episode(seed: int, i: int, scene: tuple[np.ndarray, np.ndarray, np.ndarray]) -> Episode:
    table, arm, cue = scene
    n_taps = _n_taps(seed, i)
    states = tap_count_states(n_taps)
    actions = np.concatenate([states[1:], states[-1:]])

    n_table = len(table)
    cloud = np.empty((EPISODE_LENGTH, n_table + N_ARM_POINTS, 3))
    cloud[:, :n_table] = table
    arm_center = np.concatenate([states, np.full((EPISODE_LENGTH, 1), ARM_HEIGHT)], axis=1)
    cloud[:, n_table:] = arm_center[:, None, :] + arm[None]
    cloud[:CUE_STEPS, n_table - N_CUE_POINTS : n_table] = np.asarray(CUE_CENTERS[n_taps]) + cue
    cloud += np.random.default_rng((seed, 2, i)).normal(0.0, NOISE_STD, size=cloud.shape)
    return Episode(point_cloud=cloud.astype(np.float32), state=states, action=actions)


def check_tap_count_size(
    n_episodes: int, seed: int, n_points: int, names: tuple[str, str, str] = ("n_episodes", "seed", "n_points")
) -> None:
    """Refuse (ConfigError, one line naming ``names``) a request outside the task's bounds: 1..MAX_EPISODES
    episodes, a seed >= 0, MIN_POINTS..MAX_POINTS points, at most MAX_CLOUD_BYTES of point clouds in all."""
    episodes_name, seed_name, points_name = names
    for name, value, low, high in (
        (episodes_name, n_episodes, 1, MAX_EPISODES),
        (seed_name, seed, 0, MAX_SEED),
        (points_name, n_points, MIN_POINTS, MAX_POINTS),
    ):
        if isinstance(value, bool) or not isinstance(value, numbers.Integral) or not low <= value <= high:
            raise ConfigError(f"{name} must be an integer in [{low}, {high}], got {value!r}")
    size = n_episodes * EPISODE_LENGTH * n_points * 3 * 4
    if size > MAX_CLOUD_BYTES:
        raise ConfigError(
            f"{episodes_name} {n_episodes} x {points_name} {n_points} make {size / 1e9:.1f} GB of point clouds, "
            f"more than the {MAX_CLOUD_BYTES / 1e9:g} GB the generator holds in memory; lower {episodes_name} or {points_name}"
        )


def make_tap_count_episodes(n_episodes: int, seed: int = 0, n_points: int = 64) -> list[Episode]:
    """Generate ``n_episodes`` tap-count demonstrations, deterministic from ``seed``.

    Each episode has point_cloud (40, n_points, 3), state (40, 2) and
    action (40, 2), all float32. Bounds: :func:`check_tap_count_size`. Episodes 2k and 2k + 1 are one one-tap and one
    two-tap episode, so the first ``n`` episodes do not depend on how many
    more are generated.
    """
    check_tap_count_size(n_episodes, seed, n_points)
    scene = _scene(seed, n_points)
    return [_episode(seed, i, scene) for i in range(n_episodes)]


def write_tap_count_dataset(path: str | os.PathLike, n_episodes: int, seed: int = 0, n_points: int = 64) -> Path:
    """Write :func:`make_tap_count_episodes` as a DP3 zarr dataset at ``path``; return the path."""
    episodes = make_tap_count_episodes(n_episodes, seed=seed, n_points=n_points)
    attrs = {"control_rate_hz": DEFAULT_CONTROL_RATE_HZ, "task": "tap_count", "generator": "dssp_train.data.synthetic"}
    write_replay_buffer(path, episodes, attrs=attrs)
    return Path(path)

"""A recorded episode's actions as the loop's policy source (``dssp-replay``, ``dssp-run --policy episode:PATH@K``).

    source = RecordedEpisode.load("data/pick.zarr", 3)     # actions (T, dof), one per tick, then done

Tick k gives the episode's action k (policy units); after the last one the source is done and the loop ends
(``ended by: done``). It needs no point cloud: the camera does not gate its ticks. ``first_state`` is the episode's
first recorded state (dof,), where a replay without an arm starts.
"""

from __future__ import annotations

import numpy as np

from dssp_core.errors import ConfigError, DSSPError
from hardware.policies import Act, PolicySource
from hardware.robot import ARM_DOF


class RecordedEpisode(PolicySource):
    """``actions`` (T, dof) in policy units, given one per tick; ``first_state`` (dof,); ``control_rate_hz``: the
    dataset's rate (None: it records none); ``where``: the episode's name in messages."""

    name = "episode"
    needs_cloud = False

    def __init__(self, actions: np.ndarray, first_state: np.ndarray, control_rate_hz: float | None, where: str):
        self.actions = np.asarray(actions, dtype=np.float64)
        if self.actions.ndim != 2 or len(self.actions) == 0:
            raise DSSPError(f"{where}: no actions to replay")
        self.first_state = np.asarray(first_state, dtype=np.float64)
        self.control_rate_hz, self.where = control_rate_hz, where
        self.next = 0

    @classmethod
    def load(cls, path, episode: int) -> RecordedEpisode:
        """Episode ``episode`` of the dataset at ``path`` (a bad path, index or dataset: one-line errors)."""
        from dssp_data.replay_buffer import ReplayBufferReader  # deferred: loads zarr

        reader = ReplayBufferReader(path)
        ep = reader.episode(episode, extras=False)
        actions = ep.action.astype(np.float64)
        dof = actions.shape[1]
        if dof % ARM_DOF:
            raise DSSPError(
                f"{path}: actions have {dof} values; a Piper replay needs 7 per arm [J1..J6 rad, gripper 0..1]"
            )
        first = ep.state[0].astype(np.float64) if ep.state.shape[1] == dof else actions[0]
        return cls(actions, first, reader.control_rate_hz, f"{path} episode {episode}")

    @classmethod
    def from_spec(cls, arg: str | None) -> RecordedEpisode:
        """``PATH.zarr@K`` (``--policy episode:PATH.zarr@K``)."""
        path, at, index = (arg or "").rpartition("@")
        if not at or not path or not index.strip().isdecimal():
            raise ConfigError(f"--policy episode:{arg or ''}: give the dataset and the episode as episode:PATH.zarr@K")
        return cls.load(path, int(index))

    def check(self, description, cloud_config) -> None:
        if description.dof != self.actions.shape[1]:
            raise ConfigError(
                f"{self.where} has {self.actions.shape[1]} action values but the robot has {description.dof} "
                "(7 per arm): pass one bus per recorded arm (--can can0[,can1])"
            )

    def reset(self, state: np.ndarray) -> None:
        self.next = 0

    def act(self, cloud, state) -> Act:
        action = self.actions[self.next].copy()
        self.next += 1
        return Act(action)

    @property
    def done(self) -> bool:
        return self.next >= len(self.actions)

    def describe(self) -> dict:
        return {"policy": self.name, "episode": self.where, "steps": len(self.actions)}

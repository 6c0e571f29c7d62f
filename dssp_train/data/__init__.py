"""Datasets: DP3 zarr replay buffers and the synthetic tap-count task."""

from dssp_train.data.replay_buffer import (
    Episode,
    ReplayBuffer,
    ReplayBufferReader,
    ReplayBufferWriter,
    write_replay_buffer,
)

__all__ = ["Episode", "ReplayBuffer", "ReplayBufferReader", "ReplayBufferWriter", "write_replay_buffer"]

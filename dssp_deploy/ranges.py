"""The ranges a model was trained on: an observation or an action chunk far outside them is refused.

A value far outside the training data is no input to act on, whatever the precision: the graphs would
extrapolate, and the int8 graphs (activations quantised on the fly) turn an overflow inside the model
(a state of 1e30 becomes inf in the history graph) into finite, plausible-looking actions where the fp32
and int4 graphs give NaN. So :class:`~dssp_deploy.onnx_policy.OnnxPolicy` checks both ends on every
precision:

- ``observe``: every coordinate of ``point_cloud`` (the model's channels) and every value of
  ``agent_pos`` inside its range, else :class:`ObservationOutOfRange` before any graph runs (the history
  is unchanged, as for NaN/inf: :class:`dssp_core.errors.NonFiniteObservation`);
- ``denoise`` (``act``): every action of the chunk finite and inside the action range, else
  :class:`ChunkOutOfRange`.
The control loops hold on either, as for a stale camera frame (``ChunkedControl.tick``, ``hardware.run_loop``).

The ranges: each channel's training range — what its normaliser maps to [-1, 1], from the statistics in
the manifest (``normalizers.<name>``: ``scale`` and ``offset``, ``y = x * scale + offset``): the channel's
``input_min`` to ``input_max`` over the training data, or ``input_min`` ± 1 for a channel that was constant
in training, as the normaliser treats it (a chunk may reach that far: the sampler clips to [-1, 1]) —
widened on both sides by :data:`MARGIN` (0.5) times the tensor's widest channel span over the training data
(a tensor whose every channel was constant: the normaliser's span of such a channel, 2). Half the widest span: a state the
policy's own actions lead to (they stay inside the action range) and points anywhere near the trained
workspace pass; 1e30, a unit mistake (millimetres for metres, degrees for radians) or an overflowed
reading do not. The widest span rather than each channel's own: a channel that barely moved in training
(a gripper always open, its reading jittering by 1e-3) would otherwise refuse the first tick it jitters a
little more; and point coordinates are lengths in one frame, so their margin is one distance in every
direction (a tabletop cloud's height span is a fraction of its width).

Shapes: ``values`` (..., C) with C the tensor's channels; bounds (C,).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from dssp_core.errors import DSSPError

MARGIN = 0.5  # of the tensor's widest channel span, on both sides of each channel's training range
FLAT_BELOW = 1e-4  # a span below it is a constant channel to the normaliser (dssp_train's RangeNormalizer.range_eps)
FLAT_SPAN = 2.0  # the span the normaliser gives such a channel: used when every channel of a tensor was constant
MAX_LISTED = 3  # values named in a refusal


class ObservationOutOfRange(DSSPError):
    """An observation holds a value outside the model's training range plus the margin; it was refused
    before any graph ran (the history is unchanged). Hold the tick, as for a stale camera frame."""


class ChunkOutOfRange(DSSPError):
    """The denoiser returned a chunk with NaN/inf or an action outside the action range plus the margin;
    it was not used. Hold the tick."""


class Range:
    """The accepted values of one tensor's channels: ``lower`` (C,) to ``upper`` (C,), float64."""

    def __init__(self, name: str, stats: Mapping[str, Any], margin: float = MARGIN):
        self.name = name
        scale, offset = (np.asarray(stats[k], np.float64) for k in ("scale", "offset"))
        self.trained_min, self.trained_max = (-1.0 - offset) / scale, (1.0 - offset) / scale  # x * scale + offset = ±1
        widest = float(np.max(np.asarray(stats["input_max"], np.float64) - np.asarray(stats["input_min"], np.float64)))
        self.slack = margin * (widest if widest >= FLAT_BELOW else FLAT_SPAN)
        self.lower, self.upper = self.trained_min - self.slack, self.trained_max + self.slack

    def outside(self, values: np.ndarray) -> str | None:
        """None when every value of ``values`` (..., C) is finite and inside the range, else what is wrong (one line)."""
        bad = ~(np.isfinite(values) & (values >= self.lower) & (values <= self.upper))
        if not bad.any():
            return None
        where = np.argwhere(bad)
        listed = ", ".join(self._describe(values, tuple(int(i) for i in idx)) for idx in where[:MAX_LISTED])
        more = f" and {len(where) - MAX_LISTED} more" if len(where) > MAX_LISTED else ""
        return (
            f"{self.name} {list(values.shape)} has {len(where)} value(s) outside the model's range: {listed}{more}; "
            f"a channel's range is its training range widened by {self.slack:.4g} ({MARGIN:g} x the widest channel span)"
        )

    def _describe(self, values: np.ndarray, index: tuple[int, ...]) -> str:
        value, c = values[index], index[-1]
        if not np.isfinite(value):
            return f"{index}={value} (not finite)"
        side, bound = (">", self.upper[c]) if value > self.upper[c] else ("<", self.lower[c])
        trained = f"[{self.trained_min[c]:.6g}, {self.trained_max[c]:.6g}]"
        return f"{index}={value:.6g} {side} {bound:.6g} (channel {c}: training range {trained})"

    def sample(self, rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
        """Values (*shape, C) float32 drawn uniformly from the training range (an observation that is accepted)."""
        return rng.uniform(self.trained_min, self.trained_max, (*shape, len(self.trained_min))).astype(np.float32)


def model_ranges(normalizers: Mapping[str, Any], point_dim: int) -> dict[str, Range]:
    """{"point_cloud", "agent_pos", "action": Range} from a manifest's normalisers, as
    ``dssp_deploy.manifest.read_manifest`` checked them (finite, one per channel, scale > 0, min <= max); the cloud's
    first ``point_dim`` channels."""
    cloud = {k: v[:point_dim] for k, v in normalizers["point_cloud"].items()}
    return {
        "point_cloud": Range("point_cloud", cloud),
        "agent_pos": Range("agent_pos", normalizers["agent_pos"]),
        "action": Range("action chunk", normalizers["action"]),
    }

"""Per-channel min/max normalisation to [-1, 1] (DP3's ``LinearNormalizer``, mode "limits").

The normaliser belongs to the model: its statistics are buffers of :class:`~dssp_train.model.policy.DSSPPolicy`,
saved in the same safetensors file and used by the exported graphs. Channels whose range is below
``range_eps`` are mapped to 0 (their mid value), as DP3 does.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn


class RangeNormalizer(nn.Module):
    """``y = x * scale + offset`` per channel (last dim); fitted so that [min, max] → [-1, 1]."""

    def __init__(self, dim: int, range_eps: float = 1e-4):
        super().__init__()
        self.range_eps = range_eps
        self.register_buffer("scale", torch.ones(dim))
        self.register_buffer("offset", torch.zeros(dim))
        self.register_buffer("input_min", -torch.ones(dim))
        self.register_buffer("input_max", torch.ones(dim))

    @torch.no_grad()
    def fit(self, data: np.ndarray | torch.Tensor) -> "RangeNormalizer":
        """Fit on data of shape (..., dim): every leading axis is reduced."""
        x = torch.as_tensor(np.asarray(data), dtype=torch.float64).reshape(-1, self.scale.shape[0])
        lo, hi = x.min(0).values, x.max(0).values
        span = hi - lo
        flat = span < self.range_eps
        span = torch.where(flat, torch.full_like(span, 2.0), span)
        scale = 2.0 / span
        offset = torch.where(flat, -lo, -1.0 - scale * lo)
        self.scale.copy_(scale.float())
        self.offset.copy_(offset.float())
        self.input_min.copy_(lo.float())
        self.input_max.copy_(hi.float())
        return self

    def normalize(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.scale + self.offset

    def unnormalize(self, y: torch.Tensor) -> torch.Tensor:
        return (y - self.offset) / self.scale

    def stats(self) -> dict[str, list[float]]:
        """JSON-friendly statistics (for manifests and reports)."""
        return {k: getattr(self, k).tolist() for k in ("scale", "offset", "input_min", "input_max")}

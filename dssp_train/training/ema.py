"""Exponential moving average of the weights, used for validation, export and deployment.

Decay schedule as in diffusion_policy / DP3: ``1 - (1 + step) ** -power`` capped at ``max_decay``,
0 at the first update. Buffers (the normalisers) and frozen parameters are copied, not averaged.
"""

from __future__ import annotations

import copy

import torch
from torch import nn


class EMA:
    def __init__(self, model: nn.Module, power: float = 0.75, max_decay: float = 0.9999):
        self.model = copy.deepcopy(model).eval().requires_grad_(False)
        self.power = power
        self.max_decay = max_decay
        self.step = 0

    def decay(self) -> float:
        step = max(0, self.step - 1)
        if step <= 0:
            return 0.0
        return min(1 - (1 + step) ** -self.power, self.max_decay)

    @torch.no_grad()
    def update(self, model: nn.Module) -> None:
        decay = self.decay()
        for ema_p, p in zip(self.model.parameters(), model.parameters()):
            if p.requires_grad:
                ema_p.mul_(decay).add_(p.detach(), alpha=1 - decay)
            else:  # frozen (a distilled student's encoders): copied, so they stay bit-identical
                ema_p.copy_(p)
        for ema_b, b in zip(self.model.buffers(), model.buffers()):
            ema_b.copy_(b)
        self.step += 1

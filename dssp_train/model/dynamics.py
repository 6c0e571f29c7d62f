"""Dynamics predictor g_phi(c_t, a_t) → z_hat_{t+1} and the dynamics-aware loss.

L_dyn = mean_t [1 - cos(g_phi(c_t, a_t), stopgrad(z_{t+1}))]   (paper Eq. 6, weight lambda = 0.05)

Shapes: c (B, T, d), a (B, T, A) normalised → z_hat (B, T, d).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


class DynamicsPredictor(nn.Module):
    def __init__(self, d_model: int, action_dim: int):
        super().__init__()
        self.mlp = nn.Sequential(nn.Linear(d_model + action_dim, d_model), nn.SiLU(), nn.Linear(d_model, d_model))

    def forward(self, c: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return self.mlp(torch.cat([c, action], dim=-1))


def dynamics_loss(z_hat_next: torch.Tensor, z_next: torch.Tensor) -> torch.Tensor:
    """1 - cosine similarity, averaged; the target is detached (stop-gradient)."""
    return (1 - F.cosine_similarity(z_hat_next, z_next.detach(), dim=-1)).mean()


@torch.no_grad()
def dynamics_diagnostics(z_hat_next: torch.Tensor, z: torch.Tensor) -> dict[str, torch.Tensor]:
    """How much the predictor knows beyond trivial guesses, on one trajectory z (T, d) and its predictions
    z_hat_next (T - 1, d) of z[1:]: mean cosines to z_{t+1} of the prediction (``dyn_cos`` = 1 - L_dyn), of the
    episode's mean z direction (``dyn_cos_mean``) and of z_t itself (``dyn_cos_prev``). A predictor no better
    than these, or all three near 1 (every z alike), is what a collapsed z looks like."""
    target = z[1:]
    mean = z.mean(dim=0, keepdim=True).expand_as(target)
    return {
        "dyn_cos": F.cosine_similarity(z_hat_next, target, dim=-1).mean(),
        "dyn_cos_mean": F.cosine_similarity(mean, target, dim=-1).mean(),
        "dyn_cos_prev": F.cosine_similarity(z[:-1], target, dim=-1).mean(),
    }

"""Observation encoder E_obs: DP3's point encoder and a proprioception MLP, fused into z_t.

Point branch (DP3): a per-point MLP, Linear → LayerNorm → ReLU for each width, max-pooled over the
points, then Linear → LayerNorm to ``point_feature_dim``. The last ReLU runs after the pooling (ReLU is
monotonic, so max(ReLU(x)) = ReLU(max(x)): one pass over (P, width) values fewer). No T-Net, no BatchNorm. State branch (DP3):
Linear → ReLU → Linear. The two features are concatenated and projected to the model width; DP3's UNet
(``denoiser_backbone = "unet"``) takes the concatenated features as they are, as DP3 does (d_model is then their width).

Shapes: point cloud (B, P, C) with C = ``point_dim`` (normalised), agent_pos (B, S) → z (B, d_model).
Leading dims may be any (e.g. (B, T, P, C) → (B, T, d_model)).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from dssp_train.config import ModelConfig


def max_over_points(x: torch.Tensor) -> torch.Tensor:
    """(..., P, F) → (..., F). In an ONNX export of (B, P, F) it becomes Transpose + GlobalMaxPool: ONNX
    Runtime's ReduceMax over a non-last axis takes 2.4x as long (0.32 vs 0.13 ms for (1, 1024, 256))."""
    if torch.onnx.is_in_onnx_export() and x.dim() == 3:
        return F.adaptive_max_pool1d(x.transpose(1, 2), 1).squeeze(-1)
    return x.amax(dim=-2)


class PointEncoder(nn.Module):
    """(..., P, C) → (..., point_feature_dim)."""

    def __init__(self, in_dim: int, widths: list[int], out_dim: int):
        super().__init__()
        layers: list[nn.Module] = []
        prev = in_dim
        for w in widths:
            layers += [nn.Linear(prev, w), nn.LayerNorm(w), nn.ReLU()]
            prev = w
        self.mlp = nn.Sequential(*layers)
        self.final_projection = nn.Sequential(nn.Linear(prev, out_dim), nn.LayerNorm(out_dim))

    fused_ops = None  # export's fused operators (export.fused_ops.FusedOps): the last LayerNorm and the max as one node

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        if self.fused_ops is not None and points.dim() == 3:
            features = self.mlp[:-2](points)  # up to the last Linear: (B, P, widths[-1])
            pooled = self.fused_ops.layer_norm_max_over_points(features, self.mlp[-2])
        else:
            pooled = max_over_points(self.mlp[:-1](points))  # all but the last ReLU, then the max over the points
        return self.final_projection(self.mlp[-1](pooled))


class StateEncoder(nn.Module):
    """(..., S) → (..., widths[-1]): Linear → ReLU → ... → Linear."""

    def __init__(self, in_dim: int, widths: list[int]):
        super().__init__()
        layers: list[nn.Module] = []
        prev = in_dim
        for i, w in enumerate(widths):
            layers.append(nn.Linear(prev, w))
            if i < len(widths) - 1:
                layers.append(nn.ReLU())
            prev = w
        self.mlp = nn.Sequential(*layers)

    def forward(self, state: torch.Tensor) -> torch.Tensor:
        return self.mlp(state)


class ObservationEncoder(nn.Module):
    """E_obs: (point cloud (..., P, C), agent_pos (..., S)) → z (..., d_model)."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        widths = list(cfg.point_widths)
        if cfg.point_dim == 6 and len(widths) == 3:
            widths = widths + [512]  # DP3 widens the point MLP when colour is used
        self.point_encoder = PointEncoder(cfg.point_dim, widths, cfg.point_feature_dim)
        self.state_encoder = StateEncoder(cfg.state_dim, cfg.state_widths)
        features = cfg.point_feature_dim + cfg.state_widths[-1]
        self.projection = nn.Identity() if cfg.denoiser_backbone == "unet" else nn.Linear(features, cfg.d_model)

    def forward(self, point_cloud: torch.Tensor, agent_pos: torch.Tensor) -> torch.Tensor:
        feats = torch.cat([self.point_encoder(point_cloud), self.state_encoder(agent_pos)], dim=-1)
        return self.projection(feats)

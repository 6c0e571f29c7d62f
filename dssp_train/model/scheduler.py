"""DDPM noising for training and DDIM sampling for inference.

Numerically the same as diffusers' ``DDPMScheduler.add_noise`` and ``DDIMScheduler.step`` with
eta = 0 and "leading" or "trailing" timestep spacing (a test checks it against diffusers). Written out here so that
the exporter can unroll the K sampling steps into a graph with every coefficient a constant.

Shapes: samples (B, H, A); timesteps (B,) int64.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from dssp_train.config import DiffusionConfig


def make_betas(cfg: DiffusionConfig) -> torch.Tensor:
    """(num_train_timesteps,) float32 betas, as diffusers computes them."""
    n = cfg.num_train_timesteps
    if cfg.beta_schedule == "linear":
        return torch.linspace(cfg.beta_start, cfg.beta_end, n, dtype=torch.float32)
    if cfg.beta_schedule == "scaled_linear":
        return torch.linspace(cfg.beta_start**0.5, cfg.beta_end**0.5, n, dtype=torch.float32) ** 2

    def alpha_bar(t: float) -> float:
        return math.cos((t + 0.008) / 1.008 * math.pi / 2) ** 2

    betas = [min(1 - alpha_bar((i + 1) / n) / alpha_bar(i / n), 0.999) for i in range(n)]
    return torch.tensor(betas, dtype=torch.float32)


class DiffusionSchedule:
    """The noise schedule and the DDIM update, independent of any model."""

    def __init__(self, cfg: DiffusionConfig):
        self.cfg = cfg
        self.betas = make_betas(cfg)
        self.alphas_cumprod = torch.cumprod(1.0 - self.betas, dim=0)
        self.final_alpha_cumprod = torch.tensor(1.0) if cfg.set_alpha_to_one else self.alphas_cumprod[0]

    # ---------------------------------------------------------------- training
    def add_noise(self, x0: torch.Tensor, noise: torch.Tensor, timesteps: torch.Tensor) -> torch.Tensor:
        """x_tau = sqrt(abar_tau) x0 + sqrt(1 - abar_tau) noise; x0, noise (B, ...), timesteps (B,)."""
        abar = self.alphas_cumprod.to(x0.device)[timesteps].to(x0.dtype)
        abar = abar.reshape(-1, *([1] * (x0.dim() - 1)))
        return abar.sqrt() * x0 + (1 - abar).sqrt() * noise

    # --------------------------------------------------------------- inference
    def inference_timesteps(self, num_steps: int | None = None) -> list[int]:
        """DDIM timesteps: "leading" spacing [90, 80, ..., 0] for 10 of 100, "trailing" [99, 89, ..., 9]
        (``cfg.timestep_spacing``, as diffusers' DDIMScheduler places them)."""
        k = num_steps or self.cfg.num_inference_steps
        n = self.cfg.num_train_timesteps
        if self.cfg.timestep_spacing == "trailing":
            return [int(round(t)) - 1 for t in np.arange(n, 0, -n / k)]
        ratio = n // k
        return [int(t) + self.cfg.steps_offset for t in reversed(range(0, k * ratio, ratio))]

    def ddim_coefficients(self, t: int, num_steps: int | None = None) -> tuple[float, float]:
        """(alpha_prod_t, alpha_prod_prev) for the DDIM step from timestep t."""
        k = num_steps or self.cfg.num_inference_steps
        prev = t - self.cfg.num_train_timesteps // k
        a_t = self.alphas_cumprod[t]
        a_prev = self.alphas_cumprod[prev] if prev >= 0 else self.final_alpha_cumprod
        return float(a_t), float(a_prev)

    def ddim_step(
        self,
        model_output: torch.Tensor,
        t: int,
        sample: torch.Tensor,
        num_steps: int | None = None,
        inpaint: tuple[torch.Tensor, torch.Tensor] | None = None,
    ) -> torch.Tensor:
        """One deterministic DDIM step (eta = 0) from x_t to x_prev.

        ``inpaint`` (target (B, H, A) normalised, weight (B, H, 1) in [0, 1]): the step's clean prediction is pulled to
        the target, x0 <- weight * target + (1 - weight) * x0, before the step (real-time chunking's inpainting of the
        actions already committed); weight 1 keeps the target exactly at the chain's end, weight 0 changes nothing."""
        a_t, a_prev = self.ddim_coefficients(t, num_steps)
        return ddim_update(
            model_output, sample, a_t, a_prev, self.cfg.prediction_type == "sample", self.cfg.clip_sample, inpaint
        )

    # ------------------------------------------------- per-sample steps (distillation)
    def alpha_prod(self, t: torch.Tensor) -> torch.Tensor:
        """abar_t (B,) of timesteps t (B,) int64; t = -1 is the clean end (the final alpha, as DDIM's last step)."""
        table = torch.cat([self.final_alpha_cumprod.reshape(1), self.alphas_cumprod]).to(t.device)
        return table[t + 1]

    def predicted_x0_eps(
        self, model_output: torch.Tensor, sample: torch.Tensor, t: torch.Tensor, clip: bool = True
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(x0, eps) the model's output implies at x_t = ``sample`` (B, H, A), timesteps t (B,), as :meth:`ddim_step`
        takes them (eps from the unclipped x0, x0 clipped with ``clip_sample`` unless ``clip`` is false)."""
        a_t = self.alpha_prod(t).to(sample.dtype).reshape(-1, *([1] * (sample.dim() - 1)))
        if self.cfg.prediction_type == "sample":
            x0 = model_output
            eps = (sample - a_t.sqrt() * x0) / (1 - a_t).sqrt()
        else:
            eps = model_output
            x0 = (sample - (1 - a_t).sqrt() * eps) / a_t.sqrt()
        return (x0.clamp(-1.0, 1.0) if self.cfg.clip_sample and clip else x0), eps

    def ddim_jump(self, x0: torch.Tensor, eps: torch.Tensor, t_to: torch.Tensor) -> torch.Tensor:
        """Deterministic DDIM to timesteps t_to (B,) (-1: the clean end) from a prediction (x0, eps), each (B, H, A)."""
        a_to = self.alpha_prod(t_to).to(x0.dtype).reshape(-1, *([1] * (x0.dim() - 1)))
        return a_to.sqrt() * x0 + (1 - a_to).sqrt() * eps


def ddim_update(
    model_output: torch.Tensor,
    sample: torch.Tensor,
    a_t: float,
    a_prev: float,
    predicts_sample: bool,
    clip: bool,
    inpaint: tuple[torch.Tensor, torch.Tensor] | None = None,
) -> torch.Tensor:
    """The deterministic DDIM update (eta = 0) from x_t = ``sample`` (B, H, A) with abar_t = ``a_t`` to abar_prev =
    ``a_prev``, given the model's output (B, H, A): the clean sample (``predicts_sample``) or the noise; ``clip``
    clamps the clean prediction to [-1, 1]; ``inpaint`` as in :meth:`DiffusionSchedule.ddim_step`."""
    if predicts_sample:
        x0 = model_output
        eps = (sample - a_t**0.5 * x0) / (1 - a_t) ** 0.5
    else:
        eps = model_output
        x0 = (sample - (1 - a_t) ** 0.5 * eps) / a_t**0.5
    if clip:
        x0 = x0.clamp(-1.0, 1.0)
    if inpaint is not None:
        target, weight = inpaint
        x0 = weight * target + (1 - weight) * x0
    return a_prev**0.5 * x0 + (1 - a_prev) ** 0.5 * eps

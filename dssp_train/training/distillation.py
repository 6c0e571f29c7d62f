"""Few-step students of a trained DSSP run: the objective ``dssp-distill`` trains (dssp_train/README.md,
"dssp-distill").

The student is the teacher's model — same architecture, same weights to start with, same normalisers — whose
config samples in K = ``model.diffusion.num_inference_steps`` steps at "trailing" timesteps ([99] for K = 1,
[99, 49] for K = 2 of 100), so its first step starts from pure noise. Only the denoiser trains when
``distill.freeze_encoders`` (the prefix [c_t, z...] is then the teacher's, exactly); otherwise the encoders
fine-tune through the student's prefix while the teacher keeps its own. Everything else is an ordinary run:
the trainer's windows, EMA, checkpoints, log and plot; export and the runtime take the student unchanged.

Two objectives (``distill.method``), both on the training trajectories' windows, with prefix (B, L_p, d) and
normalised action chunks x0 (B, H, A):

- ``consistency`` (consistency distillation, as Consistency Policy does, on the DDPM timesteps): on the
  teacher's DDIM grid of ``teacher_steps`` trailing timesteps t_1 > ... > t_M, noise a chunk to a grid point
  t_m, take one teacher DDIM step to t_{m+1} (the clean end after t_M), and train the student's x0 at t_m
  to equal the target's x0 at the teacher's point (the target: an EMA of the student, no gradient) — or, past
  the last step, the teacher's x0. Each
  point of a teacher trajectory is pulled to one answer, so one student step from pure noise lands where
  the teacher's ``teacher_steps`` steps do.
- ``trajectory``: the student's K-step DDIM chain from noise eps (B, H, A) is regressed onto the teacher's
  ``teacher_steps``-step DDIM output from the same eps (the teacher's deterministic noise-to-chunk map), with
  gradients through the K steps. It trains exactly what the runtime runs.

Losses are mean squared errors in normalised action units; the logged ``distill`` is that loss, ``teacher_mse``
the student's K-step chunk against the teacher's on the same noise (both methods log it, a common yardstick;
consistency distillation on its first ``GAP_WINDOWS`` windows only).
"""

from __future__ import annotations

import copy
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from dssp_core.errors import ConfigError
from dssp_train.config import RunConfig
from dssp_train.model.policy import DSSPPolicy

ENCODER_PARTS = ("obs_encoder", "history_encoder", "dynamics")
TARGET_DECAY = 0.95  # the consistency target's EMA decay (Consistency Models' distillation setting)
GAP_WINDOWS = 4  # windows on which consistency distillation logs teacher_mse


def load_teacher(config: RunConfig, device: torch.device) -> DSSPPolicy:
    """The teacher named by ``config.distill.teacher`` (its EMA weights), frozen, in eval mode; its architecture
    must be the student's (only the sampling settings may differ)."""
    from dssp_train.training.checkpoint import load_config, load_policy  # deferred: loads safetensors

    run_dir = Path(config.distill.teacher)
    teacher_config = load_config(run_dir)
    mine, theirs = config.model.to_dict(), teacher_config.model.to_dict()
    mine.pop("diffusion"), theirs.pop("diffusion")
    if mine != theirs:
        differ = sorted(k for k in mine if mine[k] != theirs.get(k))
        raise ConfigError(
            f"the student's model differs from its teacher {run_dir} in {', '.join(differ)}; a student "
            "keeps the teacher's architecture (dssp-distill builds its config from the teacher)"
        )
    teacher, _ = load_policy(run_dir)
    teacher.to(device).eval()
    teacher.requires_grad_(False)
    return teacher


def init_student(student: DSSPPolicy, teacher: DSSPPolicy, freeze_encoders: bool) -> None:
    """Copy the teacher's weights and normalisers into the student; freeze its encoders if asked."""
    student.load_state_dict(teacher.state_dict(), strict=True)
    if freeze_encoders:
        for name in ENCODER_PARTS:
            part = getattr(student, name)
            if part is not None:
                part.requires_grad_(False)


class DistillObjective(nn.Module):
    """The student's loss against the frozen teacher on windows of one trajectory; called as the trainer calls
    a policy: ``(point_cloud (T, P, C), agent_pos (T, S), action (T, A), starts (B,), generator)`` → losses."""

    def __init__(self, student: DSSPPolicy, teacher: DSSPPolicy, config: RunConfig):
        super().__init__()
        self.student = student
        self.teacher = teacher
        self.method = config.distill.method
        self.freeze_encoders = config.distill.freeze_encoders
        self.teacher_steps = config.distill.teacher_steps
        n = student.cfg.diffusion.num_train_timesteps
        if n % self.teacher_steps:
            raise ConfigError(f"distill.teacher_steps={self.teacher_steps} must divide the {n} training timesteps")
        # The teacher's grid for consistency distillation: trailing timesteps, e.g. [99, 89, ..., 9] for 10 of 100.
        self.grid = torch.tensor(student.schedule.inference_timesteps(self.teacher_steps) + [-1])
        # The consistency target's denoiser: an EMA of the student's (decay TARGET_DECAY), kept in step lazily
        # (each call folds in the weights of the step before). Not checkpointed: a resumed run restarts it from
        # the student.
        self.target = copy.deepcopy(student.denoiser).requires_grad_(False) if self.method == "consistency" else None

    def train(self, mode: bool = True):
        super().train(mode)
        self.teacher.eval()
        return self

    def _prefixes(self, point_cloud, agent_pos, starts):
        with torch.no_grad():
            teacher_prefix, act_idx = self.teacher.window_prefix(
                *self.teacher.encode_trajectory(point_cloud, agent_pos), starts
            )
        if self.freeze_encoders:
            return teacher_prefix, teacher_prefix, act_idx
        student_prefix, _ = self.student.window_prefix(*self.student.encode_trajectory(point_cloud, agent_pos), starts)
        return student_prefix, teacher_prefix, act_idx

    def forward(self, point_cloud, agent_pos, action, starts, generator=None) -> dict[str, torch.Tensor]:
        prefix, teacher_prefix, act_idx = self._prefixes(point_cloud, agent_pos, starts)
        x0 = self.student.normalizers["action"].normalize(action)[act_idx]  # (B, H, A)
        noise = torch.randn(x0.shape, generator=generator).to(x0.device)
        if self.method == "trajectory":
            with torch.no_grad():
                teacher_chunk = self.teacher.sample_normalized(teacher_prefix, noise, self.teacher_steps)
            loss = F.mse_loss(self.student.ddim_chain(prefix, noise), teacher_chunk)
            return {"loss": loss, "distill": loss, "teacher_mse": loss.detach()}
        loss = self._consistency(prefix, teacher_prefix, x0, generator)
        with torch.no_grad():  # the yardstick on a few windows: the teacher's full chain is not the objective's cost
            few = slice(0, GAP_WINDOWS)
            gap = F.mse_loss(
                self.student.ddim_chain(prefix[few].detach(), noise[few]),
                self.teacher.sample_normalized(teacher_prefix[few], noise[few], self.teacher_steps),
            )
        return {"loss": loss, "distill": loss, "teacher_mse": gap}

    @torch.no_grad()
    def _update_target(self) -> None:
        for mine, theirs in zip(self.target.parameters(), self.student.denoiser.parameters()):
            mine.lerp_(theirs, 1.0 - TARGET_DECAY)

    def _consistency(self, prefix, teacher_prefix, x0, generator) -> torch.Tensor:
        if self.training:
            self._update_target()
        schedule = self.student.schedule
        m = torch.randint(0, len(self.grid) - 1, (x0.shape[0],), generator=generator)
        t_hi, t_lo = self.grid[m].to(x0.device), self.grid[m + 1].to(x0.device)
        x_hi = schedule.add_noise(x0, torch.randn(x0.shape, generator=generator).to(x0.device), t_hi)
        with torch.no_grad():
            x0_t, eps_t = schedule.predicted_x0_eps(self.teacher.denoiser(teacher_prefix, x_hi, t_hi), x_hi, t_hi)
            x_lo = schedule.ddim_jump(x0_t, eps_t, t_lo)
            clean = (t_lo < 0).reshape(-1, 1, 1)
            own, _ = schedule.predicted_x0_eps(
                self.target(prefix.detach(), x_lo, t_lo.clamp(min=0)), x_lo, t_lo.clamp(min=0)
            )
            target = torch.where(clean, x_lo, own)
        # unclipped, so the gradient reaches every output
        pred, _ = schedule.predicted_x0_eps(self.student.denoiser(prefix, x_hi, t_hi), x_hi, t_hi, clip=False)
        return F.mse_loss(pred, target)

"""Before training: does one optimisation step fit in memory?

A step on a configuration far too large for the machine does not fail cleanly: the operating system kills
the process (exit 137, no message). :func:`check_memory` estimates what one step needs and refuses, with
one line, when the estimate exceeds the memory available — on the CPU the machine's available RAM (and
the cgroup limit, in a container), on CUDA the device's free memory.

The estimate counts only the dominant terms, so it stays below the real peak (it refuses only what clearly
cannot fit), all float32:

- the training state: weights, gradients, AdamW's two moments and the EMA copy — 5 x 4 bytes per parameter
  (the parameters counted on the ``meta`` device, nothing allocated);
- the activations autograd keeps for the backward pass of one step on the longest training episode (T steps):
  the point encoder's per-point features, two (T, P, width) tensors per layer (the Linear and ReLU outputs);
  in every Mamba layer the selective scan's decay factors and states, two (tokens, d_inner, d_state)
  tensors, plus two more of them while a layer runs its backward pass; the history encoder sees T
  tokens (``history_window`` 0) or T windows of T_h tokens, the denoiser B x (prefix + H) tokens; a
  Transformer history encoder keeps its attention weights (sequences x heads x length^2) per layer.

Measured on a CPU (one step's peak resident memory above what the process held before the model was
built), the estimate came to 0.56-0.94 of the real need over the tiny and robotwin presets, episodes of
100-1000 steps, history windows, a Transformer history encoder and wider Mamba layers.

Under ``torchrun`` on CPU the processes on one machine share its memory, so the need is multiplied by
``LOCAL_WORLD_SIZE``.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import torch

from dssp_core.errors import ConfigError
from dssp_train.config import ModelConfig, RunConfig
from dssp_train.model.policy import DSSPPolicy

FLOAT_BYTES = 4
STATE_COPIES = 5  # weights, gradients, AdamW exp_avg and exp_avg_sq, EMA weights


@dataclass(frozen=True)
class StepMemory:
    """Estimated bytes of one training step."""

    parameters: int
    state_bytes: int
    activation_bytes: int
    longest_episode: int

    @property
    def total(self) -> int:
        return self.state_bytes + self.activation_bytes


def parameter_count(model: ModelConfig) -> int:
    """Number of parameters of the policy ``model`` describes, built on the meta device (nothing allocated).

    ``state_dim`` and ``action_dim`` must be set."""

    with torch.device("meta"):
        policy = DSSPPolicy(model)
    return sum(p.numel() for p in policy.parameters())


def point_widths(model: ModelConfig) -> list[int]:
    """The point MLP's widths as :class:`~dssp_train.model.obs_encoder.ObservationEncoder` builds them."""
    widths = list(model.point_widths)
    if model.point_dim == 6 and len(widths) == 3:
        widths.append(512)
    return widths


def _mamba_bytes(tokens: int, n_layers: int, m: ModelConfig) -> int:
    scan = tokens * m.expand * m.d_model * m.d_state * FLOAT_BYTES  # one (tokens, d_inner, d_state) tensor
    return (2 * n_layers + 2) * scan if n_layers else 0


def estimate_step_memory(model: ModelConfig, batch_size: int, longest_episode: int) -> StepMemory:
    """The estimate described in the module docstring, for B = ``batch_size`` windows of one episode of
    ``longest_episode`` steps."""
    m, T = model, longest_episode
    params = parameter_count(m)
    point = T * m.n_points * sum(point_widths(m)) * 2 * FLOAT_BYTES
    history = 0
    if m.use_history:
        sequences, length = (1, T) if m.history_window == 0 else (T, m.history_window)
        tokens = sequences * length
        windows = tokens * m.d_model * FLOAT_BYTES if m.history_window else 0  # the (T, T_h, d) window copy
        if m.history_backbone == "mamba":
            history = _mamba_bytes(tokens, m.n_history_layers, m) + windows
        else:
            attention = sequences * m.transformer_heads * length * length * FLOAT_BYTES * 2  # scores and weights
            feed_forward = tokens * 4 * m.d_model * FLOAT_BYTES * 2
            history = m.n_history_layers * (attention + feed_forward) + windows
    denoiser = _mamba_bytes(batch_size * (m.prefix_length + m.horizon), m.n_denoiser_layers, m)
    return StepMemory(params, STATE_COPIES * FLOAT_BYTES * params, point + history + denoiser, T)


def _read_int(path: Path) -> int | None:
    try:
        text = path.read_text().strip()
    except OSError:
        return None
    return int(text) if text.isdecimal() else None


def available_bytes(device: torch.device) -> int | None:
    """Free memory for training on ``device``, or None when it cannot be told.

    CPU (Linux): ``MemAvailable`` of /proc/meminfo, lowered to the room left under the cgroup's limit
    (cgroup v2 ``memory.max`` - ``memory.current``, or v1 ``memory.limit_in_bytes`` - ``memory.usage_in_bytes``).
    CUDA: the device's free memory (``torch.cuda.mem_get_info``)."""
    if device.type == "cuda":
        try:
            return int(torch.cuda.mem_get_info(device)[0])
        except (RuntimeError, AssertionError):
            return None
    if device.type != "cpu":
        return None
    found: list[int] = []
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                found.append(int(line.split()[1]) * 1024)
                break
    except (OSError, ValueError, IndexError):
        pass
    cgroup = Path("/sys/fs/cgroup")
    for limit_name, usage_name in (
        ("memory.max", "memory.current"),
        ("memory/memory.limit_in_bytes", "memory/memory.usage_in_bytes"),
    ):
        limit, usage = _read_int(cgroup / limit_name), _read_int(cgroup / usage_name)
        if limit is not None and usage is not None and limit < 2**60:  # "max" or a huge v1 value: no limit
            found.append(max(0, limit - usage))
            break
    return min(found) if found else None


def format_bytes(n: float) -> str:
    for unit in ("B", "KB", "MB", "GB", "TB"):
        if n < 1000 or unit == "TB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000
    raise AssertionError  # unreachable


def check_memory(config: RunConfig, longest_episode: int, device: torch.device) -> StepMemory:
    """Refuse (ConfigError, one line) a training step whose estimate exceeds the available memory."""
    tc = config.train
    estimate = estimate_step_memory(config.model, tc.batch_size, longest_episode)
    available = available_bytes(device)
    if available is None:
        return estimate
    processes = int(os.environ.get("LOCAL_WORLD_SIZE", "1")) if device.type == "cpu" else 1
    need = estimate.total * max(1, processes)
    if need > available:
        where = f"on {device}" if device.type == "cuda" else "in RAM"
        each = f" for each of {processes} processes" if processes > 1 else ""
        raise ConfigError(
            f"one training step needs about {format_bytes(estimate.total)}{each} ({estimate.parameters:,} parameters "
            f"with gradients, AdamW and EMA state: {format_bytes(estimate.state_bytes)}; activations for the longest "
            f"episode, {longest_episode} steps: {format_bytes(estimate.activation_bytes)}) but only "
            f"{format_bytes(available)} is available {where}; lower model.d_model, model.expand, model.d_state, "
            "model.history_window or train.batch_size"
        )
    return estimate

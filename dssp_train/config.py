"""Typed configuration: the model, the diffusion schedule and the training run.

Every dataclass validates itself in ``__post_init__`` and raises :class:`ConfigError` with a
one-line message. Presets are data (``dssp_train/presets/*.json``), loaded by :func:`load_preset`;
overrides are ``section.field=value`` strings (``model.d_model=256``, ``train.batch_size=32``).
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from importlib import resources
from typing import Any

from dssp_train.errors import ConfigError

HISTORY_BACKBONES = ("mamba", "transformer")


def _require(cond: bool, message: str) -> None:
    if not cond:
        raise ConfigError(message)


@dataclass
class DiffusionConfig:
    """DDPM training / DDIM sampling schedule (DP3's settings by default)."""

    num_train_timesteps: int = 100
    num_inference_steps: int = 10
    beta_start: float = 1e-4
    beta_end: float = 0.02
    beta_schedule: str = "squaredcos_cap_v2"
    clip_sample: bool = True
    set_alpha_to_one: bool = True
    steps_offset: int = 0
    prediction_type: str = "sample"

    def __post_init__(self):
        _require(self.num_train_timesteps >= 1, "diffusion.num_train_timesteps must be >= 1")
        _require(
            1 <= self.num_inference_steps <= self.num_train_timesteps,
            f"diffusion.num_inference_steps must be in [1, {self.num_train_timesteps}], got {self.num_inference_steps}",
        )
        _require(
            self.beta_schedule in ("linear", "scaled_linear", "squaredcos_cap_v2"),
            f"diffusion.beta_schedule {self.beta_schedule!r} is not one of linear, scaled_linear, squaredcos_cap_v2",
        )
        _require(
            self.prediction_type in ("sample", "epsilon"),
            f"diffusion.prediction_type must be 'sample' or 'epsilon', got {self.prediction_type!r}",
        )


@dataclass
class ModelConfig:
    """DSSP architecture (names as in the paper: N recent state tokens, horizon H, H_a executed)."""

    # Data interface (filled from the dataset when 0).
    point_dim: int = 3  # 3 = xyz, 6 = xyz + rgb
    state_dim: int = 0
    action_dim: int = 0
    n_points: int = 1024
    # Widths.
    d_model: int = 512
    d_state: int = 64
    d_conv: int = 4
    expand: int = 2
    n_history_layers: int = 2
    n_denoiser_layers: int = 8
    # Observation encoder E_obs (DP3's point encoder and state MLP).
    point_widths: list[int] = field(default_factory=lambda: [64, 128, 256])
    point_feature_dim: int = 128
    state_widths: list[int] = field(default_factory=lambda: [64, 64])
    # Horizons.
    n_obs_steps: int = 3  # N
    horizon: int = 8  # H
    n_action_steps: int = 6  # H_a
    # History encoder G_psi and ablation switches (paper Tables 3 and 5).
    history_backbone: str = "mamba"
    history_window: int = 0  # 0 = full history; T_h > 0 = only the last T_h observations
    transformer_heads: int = 8
    use_history: bool = True
    use_recent_states: bool = True
    timestep_decoupled: bool = True
    dynamics_weight: float = 0.05
    diffusion: DiffusionConfig = field(default_factory=DiffusionConfig)

    def __post_init__(self):
        if isinstance(self.diffusion, dict):
            self.diffusion = DiffusionConfig(**_known(DiffusionConfig, self.diffusion, "model.diffusion"))
        _require(self.point_dim in (3, 6), f"model.point_dim must be 3 (xyz) or 6 (xyz+rgb), got {self.point_dim}")
        for name in ("state_dim", "action_dim"):
            _require(getattr(self, name) >= 0, f"model.{name} must be >= 0 (0 = take it from the dataset)")
        for name in ("d_model", "d_state", "d_conv", "expand", "n_denoiser_layers", "n_points", "point_feature_dim"):
            _require(getattr(self, name) >= 1, f"model.{name} must be >= 1, got {getattr(self, name)}")
        _require(self.n_history_layers >= 1, "model.n_history_layers must be >= 1")
        _require(len(self.point_widths) >= 1 and min(self.point_widths) >= 1, "model.point_widths must be positive")
        _require(len(self.state_widths) >= 1 and min(self.state_widths) >= 1, "model.state_widths must be positive")
        _require(self.n_obs_steps >= 1, f"model.n_obs_steps (N) must be >= 1, got {self.n_obs_steps}")
        _require(self.horizon >= 1, f"model.horizon (H) must be >= 1, got {self.horizon}")
        _require(
            1 <= self.n_action_steps <= self.horizon,
            f"model.n_action_steps (H_a) must be in [1, horizon={self.horizon}], got {self.n_action_steps}",
        )
        _require(
            self.history_backbone in HISTORY_BACKBONES,
            f"model.history_backbone must be one of {', '.join(HISTORY_BACKBONES)}, got {self.history_backbone!r}",
        )
        _require(self.history_window >= 0, "model.history_window must be >= 0 (0 = full history)")
        if self.history_backbone == "transformer":
            _require(
                self.d_model % self.transformer_heads == 0,
                f"model.d_model={self.d_model} must be divisible by model.transformer_heads={self.transformer_heads}",
            )
        _require(self.dynamics_weight >= 0, "model.dynamics_weight must be >= 0")
        _require(
            self.use_history or self.use_recent_states,
            "model.use_history and model.use_recent_states cannot both be off: the denoiser would see no observation",
        )

    @property
    def prefix_length(self) -> int:
        """Number of prefix tokens [c_t, z_{t-N+1}, ..., z_t] the denoiser sees."""
        return int(self.use_history) + (self.n_obs_steps if self.use_recent_states else 0)

    @property
    def uses_dynamics_loss(self) -> bool:
        return self.use_history and self.dynamics_weight > 0


@dataclass
class TrainConfig:
    """Optimisation and bookkeeping of one training run."""

    steps: int = 3000
    batch_size: int = 64  # action windows sampled from each trajectory (Appendix C.1)
    lr: float = 1e-4
    betas: list[float] = field(default_factory=lambda: [0.95, 0.999])
    weight_decay: float = 1e-6
    warmup_steps: int = 500
    ema_power: float = 0.75
    ema_max_decay: float = 0.9999
    val_ratio: float = 0.1
    val_every: int = 500
    val_windows: int = 256
    save_every: int = 1000
    log_every: int = 10
    seed: int = 0

    def __post_init__(self):
        _require(self.steps >= 1, f"train.steps must be >= 1, got {self.steps}")
        _require(self.batch_size >= 1, f"train.batch_size must be >= 1, got {self.batch_size}")
        _require(self.lr > 0, "train.lr must be > 0")
        _require(len(self.betas) == 2 and all(0 <= b < 1 for b in self.betas), "train.betas must be two values in [0, 1)")
        _require(self.weight_decay >= 0, "train.weight_decay must be >= 0")
        _require(self.warmup_steps >= 0, "train.warmup_steps must be >= 0")
        _require(0 <= self.val_ratio < 1, f"train.val_ratio must be in [0, 1), got {self.val_ratio}")
        for name in ("val_every", "val_windows", "save_every", "log_every"):
            _require(getattr(self, name) >= 1, f"train.{name} must be >= 1")


@dataclass
class RunConfig:
    """Everything a run directory records: the model, the training, and facts about the data."""

    model: ModelConfig = field(default_factory=ModelConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    preset: str = "custom"
    control_rate_hz: float | None = None  # the rate the data was recorded at; the runtime must match it
    dataset: str | None = None

    def __post_init__(self):
        if isinstance(self.model, dict):
            self.model = ModelConfig(**_known(ModelConfig, self.model, "model"))
        if isinstance(self.train, dict):
            self.train = TrainConfig(**_known(TrainConfig, self.train, "train"))
        _require(
            self.control_rate_hz is None or self.control_rate_hz > 0,
            f"control_rate_hz must be > 0, got {self.control_rate_hz}",
        )

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "RunConfig":
        return cls(**_known(cls, data, "config"))

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2, sort_keys=True)


def _known(cls, data: dict[str, Any], where: str) -> dict[str, Any]:
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    _require(not unknown, f"unknown key(s) in {where}: {', '.join(unknown)} (known: {', '.join(sorted(names))})")
    return dict(data)


def preset_names() -> list[str]:
    files = resources.files("dssp_train") / "presets"
    return sorted(p.name[: -len(".json")] for p in files.iterdir() if p.name.endswith(".json"))


def load_preset(name: str) -> RunConfig:
    """The named preset (``tiny``, ``robotwin``, ``metaworld``, ``adroit``) as a validated RunConfig."""
    names = preset_names()
    _require(name in names, f"unknown preset {name!r}; choose one of: {', '.join(names)}")
    data = json.loads((resources.files("dssp_train") / "presets" / f"{name}.json").read_text())
    data["preset"] = name
    return RunConfig.from_dict(data)


def apply_overrides(config: RunConfig, overrides: list[str]) -> RunConfig:
    """Apply ``section.field=value`` overrides (value parsed as JSON, else kept as a string)."""
    data = config.to_dict()
    for item in overrides:
        _require("=" in item, f"override {item!r} must look like section.field=value, e.g. model.d_model=256")
        key, raw = item.split("=", 1)
        try:
            value = json.loads(raw)
        except json.JSONDecodeError:
            value = raw
        node = data
        parts = key.split(".")
        for part in parts[:-1]:
            _require(isinstance(node.get(part), dict), f"override {item!r}: {part!r} is not a config section")
            node = node[part]
        _require(parts[-1] in node, f"override {item!r}: unknown field {key!r}")
        node[parts[-1]] = value
    return RunConfig.from_dict(data)

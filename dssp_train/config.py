"""Typed configuration: the model, the diffusion schedule and the training run.

Every dataclass validates itself in ``__post_init__`` and raises :class:`ConfigError` with a
one-line message. Presets are data (``dssp_train/presets/*.json``), loaded by :func:`load_preset`;
overrides are ``section.field=value`` strings (``model.d_model=256``, ``train.batch_size=32``).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from importlib import resources
from typing import ClassVar

from dssp_core.errors import ConfigError
from dssp_core.schema import (
    MAX_LAYERS,
    MAX_STEPS,
    MAX_WIDTH,
    Settings,
    control_rate_setting,
    parse_json,
    setting,
)
from dssp_data.model_contract import ModelContract, check_chunk, contract_setting
from dssp_data.observation import ObservationContract

HISTORY_BACKBONES = ("mamba", "transformer")
# What follows the mixer in each denoiser block (README, "The paper's size"): nothing (the Mamba block alone),
# mamba-ssm's GatedMLP (Block with mlp_cls=GatedMLP: 8d/3 hidden, SiLU gate, unmodulated), or DiT's MLP (4d
# hidden, GELU, with its own AdaLN shift/scale/gate on the action tokens).
DENOISER_MLPS = ("none", "gated", "dit")
# Where the predicted chunk starts (README, "Action-chunk alignment"): at the current step t (execute its first
# H_a actions), or at the oldest recent observation t - N + 1 as DP3 does (execute from index N - 1; every
# table of the paper has H_a = H - N + 1).
ACTION_ALIGNMENTS = ("current", "dp3")
# Where DDIM's K timesteps sit among the training timesteps (diffusers' names; DiffusionConfig.timestep_spacing).
TIMESTEP_SPACINGS = ("leading", "trailing")
# The denoiser: blocks with a Mamba mixer (the paper's) or causal self-attention (Table 5's "w/ Trans."), or DP3's
# conditional 1-D UNet with FiLM (the baseline, dssp_train/model/unet.py; the "dp3" presets).
DENOISER_BACKBONES = ("mamba", "transformer", "unet")


def _require(cond: bool, message: str) -> None:
    if not cond:
        raise ConfigError(message)


@dataclass
class DiffusionConfig(Settings):
    """DDPM training / DDIM sampling schedule (DP3's settings by default)."""

    SECTION: ClassVar[str] = "model.diffusion"

    num_train_timesteps: int = setting(100, ge=1, le=100_000)
    num_inference_steps: int = setting(10, ge=1, le=100_000)
    beta_start: float = setting(1e-4, gt=0, lt=1)
    beta_end: float = setting(0.02, gt=0, lt=1)
    beta_schedule: str = setting("squaredcos_cap_v2", choices=("linear", "scaled_linear", "squaredcos_cap_v2"))
    clip_sample: bool = setting(True)
    set_alpha_to_one: bool = setting(True)
    steps_offset: int = setting(0, ge=0, le=100_000)
    prediction_type: str = setting("sample", choices=("sample", "epsilon"))
    # Where the K sampling timesteps sit (diffusers' names): "leading" [0, T/K, ...] reversed, e.g. [90, ..., 0]
    # for 10 of 100 (DP3's); "trailing" ends each interval instead, e.g. [99, 89, ..., 9], so that even K = 1
    # starts at the noise level t = T - 1 (the distilled few-step samplers, dssp-distill).
    timestep_spacing: str = setting("leading", choices=TIMESTEP_SPACINGS)

    def validate(self):
        _require(
            self.num_inference_steps <= self.num_train_timesteps,
            f"model.diffusion.num_inference_steps must be in [1, {self.num_train_timesteps}], got {self.num_inference_steps}",
        )
        _require(
            self.beta_start <= self.beta_end,
            f"model.diffusion.beta_start ({self.beta_start}) must not exceed beta_end ({self.beta_end})",
        )


@dataclass
class ModelConfig(Settings):
    """DSSP architecture (names as in the paper: N recent state tokens, horizon H, H_a executed)."""

    SECTION: ClassVar[str] = "model"

    # Data interface (filled from the dataset when 0). The contract's fields: declared by ModelContract.
    point_dim: int = contract_setting("point_dim", 3)  # 3 = xyz, 6 = xyz + rgb
    state_dim: int = contract_setting("state_dim", 0, unset=0)
    action_dim: int = contract_setting("action_dim", 0, unset=0)
    n_points: int = contract_setting("n_points", 1024)
    # Widths.
    d_model: int = setting(512, ge=1, le=MAX_WIDTH)
    d_state: int = setting(64, ge=1, le=MAX_WIDTH)
    d_conv: int = setting(4, ge=1, le=64)
    expand: int = setting(2, ge=1, le=16)
    n_history_layers: int = setting(2, ge=1, le=MAX_LAYERS)
    n_denoiser_layers: int = setting(8, ge=1, le=MAX_LAYERS)
    # Observation encoder E_obs (DP3's point encoder and state MLP).
    point_widths: list[int] = setting(
        default_factory=lambda: [64, 128, 256], ge=1, le=MAX_WIDTH, min_length=1, max_length=16
    )
    point_feature_dim: int = setting(128, ge=1, le=MAX_WIDTH)
    state_widths: list[int] = setting(default_factory=lambda: [64, 64], ge=1, le=MAX_WIDTH, min_length=1, max_length=16)
    # Horizons.
    n_obs_steps: int = contract_setting("n_obs_steps", 3)  # N
    horizon: int = contract_setting("horizon", 8)  # H
    n_action_steps: int = contract_setting("n_action_steps", 6)  # H_a
    action_alignment: str = setting("current", choices=ACTION_ALIGNMENTS)
    # History encoder G_psi and ablation switches (paper Tables 3 and 5).
    history_backbone: str = setting("mamba", choices=HISTORY_BACKBONES)
    history_window: int = setting(0, ge=0, le=1_000_000)  # 0 = full history; T_h > 0 = only the last T_h observations
    transformer_heads: int = setting(8, ge=1, le=MAX_WIDTH)
    denoiser_backbone: str = setting("mamba", choices=DENOISER_BACKBONES)
    denoiser_mlp: str = setting("none", choices=DENOISER_MLPS)
    use_history: bool = setting(True)
    use_recent_states: bool = setting(True)
    timestep_decoupled: bool = setting(True)
    dynamics_weight: float = setting(0.05, ge=0, le=1000)
    # Training-time real-time chunking (Black et al., arXiv 2512.05964): each training chunk gets its first d actions,
    # d ~ U{0, ..., committed_prefix_max}, given clean and flagged by a learned embedding, and no loss on them, so
    # that at run time the actions committed while a chunk computes condition it directly (no guidance). 0: off.
    committed_prefix_max: int = setting(0, ge=0, le=MAX_STEPS)
    # DP3's UNet (denoiser_backbone "unet"): the widths of its levels, conv kernel, GroupNorm groups, step embedding.
    unet_down_dims: list[int] = setting(
        default_factory=lambda: [512, 1024, 2048], ge=1, le=MAX_WIDTH, min_length=1, max_length=8
    )
    unet_kernel_size: int = setting(5, ge=1, le=31)
    unet_n_groups: int = setting(8, ge=1, le=MAX_WIDTH)
    unet_step_embed_dim: int = setting(128, ge=2, le=MAX_WIDTH)
    diffusion: DiffusionConfig = setting(default_factory=DiffusionConfig)

    def validate(self):
        check_chunk(self.n_obs_steps, self.horizon, self.n_action_steps, self.action_offset, self.SECTION)
        if "transformer" in (self.history_backbone, self.denoiser_backbone):
            _require(
                self.d_model % self.transformer_heads == 0,
                f"model.d_model={self.d_model} must be divisible by model.transformer_heads={self.transformer_heads}",
            )
        if self.denoiser_backbone == "unet":
            self._validate_unet()
        if self.committed_prefix_max:
            _require(
                self.denoiser_backbone != "unet" and self.action_offset == 0,
                "model.committed_prefix_max (training-time real-time chunking) needs a Mamba or Transformer denoiser "
                "and the current action alignment (the committed actions start the chunk)",
            )
            _require(
                self.committed_prefix_max < self.horizon,
                f"model.committed_prefix_max must leave an action to predict: at most horizon - 1 = {self.horizon - 1}, "
                f"got {self.committed_prefix_max}",
            )
        _require(
            self.use_history or self.use_recent_states,
            "model.use_history and model.use_recent_states cannot both be off: the denoiser would see no observation",
        )

    def _validate_unet(self) -> None:
        features = self.point_feature_dim + self.state_widths[-1]
        _require(
            self.d_model == features,
            f"model.denoiser_backbone=unet (DP3) conditions on the observation features themselves, without a projection: "
            f"model.d_model must be point_feature_dim + state_widths[-1] = {features}, got {self.d_model}",
        )
        groups, dims = self.unet_n_groups, self.unet_down_dims
        bad = [d for d in dims if d % groups]
        _require(
            not bad, f"model.unet_down_dims must be multiples of model.unet_n_groups={groups} (GroupNorm), got {dims}"
        )
        _require(
            self.unet_kernel_size % 2 == 1,
            f"model.unet_kernel_size must be odd (same padding), got {self.unet_kernel_size}",
        )
        halvings = 2 ** (len(dims) - 1)
        _require(
            self.horizon % halvings == 0,
            f"model.unet_down_dims has {len(dims)} levels, which halve the horizon {len(dims) - 1} times: model.horizon must "
            f"be a multiple of {halvings}, got {self.horizon}",
        )
        _require(
            self.unet_step_embed_dim % 2 == 0,
            f"model.unet_step_embed_dim must be even (sin and cos), got {self.unet_step_embed_dim}",
        )

    @property
    def action_offset(self) -> int:
        """Index of the chunk's first executed action: N - 1 with DP3's alignment, else 0."""
        return self.n_obs_steps - 1 if self.action_alignment == "dp3" else 0

    @property
    def prefix_length(self) -> int:
        """Number of prefix tokens [c_t, z_{t-N+1}, ..., z_t] the denoiser sees."""
        return int(self.use_history) + (self.n_obs_steps if self.use_recent_states else 0)

    @property
    def uses_dynamics_loss(self) -> bool:
        return self.use_history and self.dynamics_weight > 0


SAMPLINGS = ("trajectory", "windows")  # TrainConfig.sampling


@dataclass
class TrainConfig(Settings):
    """Optimisation and bookkeeping of one training run."""

    SECTION: ClassVar[str] = "train"

    steps: int = setting(3000, ge=1, le=100_000_000)
    # Epochs of trajectory-wise training (one optimisation step reads one trajectory, so an epoch is one pass
    # over the training trajectories: as many steps as there are training episodes). 0: train.steps is the
    # budget; > 0: train.steps = epochs x training episodes, resolved when the run starts (README, "Epochs").
    epochs: int = setting(0, ge=0, le=100_000_000)
    batch_size: int = setting(64, ge=1, le=1_000_000)  # action windows sampled from each trajectory (Appendix C.1)
    lr: float = setting(1e-4, gt=0, le=1)
    betas: list[float] = setting(default_factory=lambda: [0.95, 0.999], ge=0, lt=1, min_length=2, max_length=2)
    weight_decay: float = setting(1e-6, ge=0, le=1)
    warmup_steps: int = setting(500, ge=0, le=100_000_000)
    ema_power: float = setting(0.75, gt=0, le=10)
    ema_max_decay: float = setting(0.9999, ge=0, le=1)
    val_ratio: float = setting(0.1, ge=0, lt=1)
    val_every: int = setting(500, ge=1, le=100_000_000)
    val_windows: int = setting(256, ge=1, le=100_000_000)
    save_every: int = setting(1000, ge=1, le=100_000_000)
    # > 0: also keep the EMA weights every ``keep_every`` steps as RUN/snapshots/step_NNNNNNN/ (model.safetensors and
    # config.json: a run directory export.to_onnx reads), for evaluations along training (the MetaWorld metric)
    keep_every: int = setting(0, ge=0, le=100_000_000)
    # How a step's windows are drawn: "trajectory" (the paper's, Appendix C.1: batch_size windows of one training
    # trajectory, encoded whole) or "windows" (DP3's: batch_size windows drawn uniformly from every training
    # trajectory's windows; a model without history only, which needs no trajectory encoded whole).
    sampling: str = setting("trajectory", choices=SAMPLINGS)
    log_every: int = setting(10, ge=1, le=100_000_000)
    seed: int = setting(0, ge=0, le=2**63 - 1)


DISTILL_METHODS = ("consistency", "trajectory")


@dataclass
class DistillConfig(Settings):
    """A few-step student of a trained run (``dssp-distill``; dssp_train/README.md, "dssp-distill").

    teacher: the teacher's run directory ("" = an ordinary run, not a student). method: "consistency"
    (consistency distillation on the teacher's DDIM grid of ``teacher_steps`` steps) or "trajectory" (the
    student's K-step sampler regressed onto the teacher's ``teacher_steps``-step DDIM output from the same
    noise). freeze_encoders: the observation and history encoders (and the dynamics head) stay the teacher's;
    only the denoiser trains.
    """

    SECTION: ClassVar[str] = "distill"

    teacher: str = setting("")
    method: str = setting("trajectory", choices=DISTILL_METHODS)
    teacher_steps: int = setting(10, ge=2, le=1000)
    freeze_encoders: bool = setting(True)


@dataclass
class RunConfig(Settings):
    """Everything a run directory records: the model, the training, and facts about the data."""

    SECTION: ClassVar[str] = "config"

    model: ModelConfig = setting(default_factory=ModelConfig)
    train: TrainConfig = setting(default_factory=TrainConfig)
    preset: str = setting("custom")
    control_rate_hz: float | None = control_rate_setting()  # the data's rate; the runtime must match it
    dataset: str | None = setting(None)
    # The observation contract the dataset records (point-cloud settings, state/action layout; null: unknown).
    observation: ObservationContract = setting(default_factory=ObservationContract)
    distill: DistillConfig = setting(default_factory=DistillConfig)  # a distilled student's teacher and method

    def validate(self) -> None:
        if self.train.sampling == "windows":
            _require(
                not self.model.use_history,
                "train.sampling=windows draws windows from anywhere in the data, which a model with history cannot "
                "train on (its context needs the trajectory before each window): set model.use_history=false or "
                "train.sampling=trajectory",
            )
            _require(
                not self.distill.teacher,
                "train.sampling=windows is not used for distillation: the student trains on trajectories",
            )

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2, sort_keys=True)

    def contract(self, ddim_timesteps: list[int], inpainting: bool = False) -> ModelContract:
        """What a model of this run promises the robot, with the sampler export chose (K = len(ddim_timesteps)
        timesteps; ``inpainting``: the denoiser takes the committed actions)."""
        m = self.model
        return ModelContract(
            point_dim=m.point_dim,
            n_points=m.n_points,
            state_dim=m.state_dim,
            action_dim=m.action_dim,
            n_obs_steps=m.n_obs_steps,
            horizon=m.horizon,
            n_action_steps=m.n_action_steps,
            action_offset=m.action_offset,
            ddim_timesteps=list(ddim_timesteps),
            inpainting=inpainting,
            control_rate_hz=self.control_rate_hz,
            observation=self.observation,
        )


def preset_names() -> list[str]:
    files = resources.files("dssp_train") / "presets"
    return sorted(p.name[: -len(".json")] for p in files.iterdir() if p.name.endswith(".json"))


def resolve_epochs(config: RunConfig, n_train: int) -> RunConfig:
    """``config`` with train.steps = train.epochs x ``n_train`` (one trajectory per step, Appendix C.1)."""
    data = config.to_dict()
    data["train"]["steps"] = config.train.epochs * n_train
    try:
        return RunConfig.from_dict(data)
    except ConfigError as exc:
        raise ConfigError(f"train.epochs={config.train.epochs} x {n_train} training episodes: {exc}") from None


def load_preset(name: str) -> RunConfig:
    """The named preset (``tiny``, ``robotwin``, ``metaworld``, ``adroit``) as a validated RunConfig."""
    names = preset_names()
    _require(name in names, f"unknown preset {name!r}; choose one of: {', '.join(names)}")
    data = json.loads((resources.files("dssp_train") / "presets" / f"{name}.json").read_text())
    data["preset"] = name
    return RunConfig.from_dict(data)


def apply_overrides(config: RunConfig, overrides: list[str]) -> RunConfig:
    """Apply ``section.field=value`` overrides (value parsed as JSON, else kept as a string), in any order: only the
    result must be valid; when it is not, the error names the first override after which the config was not."""
    data = config.to_dict()
    for item in overrides:
        _set_override(data, item)
    try:
        return RunConfig.from_dict(data)
    except ConfigError:  # applied again one by one: the first after which the config is invalid is named
        data = config.to_dict()
        for item in overrides:
            _set_override(data, item)
            try:
                RunConfig.from_dict(data)
            except ConfigError as exc:
                shown = item if len(item) <= 60 else item[:57] + "..."
                raise ConfigError(f"--set {shown}: {exc}") from None
        raise


def _set_override(data: dict, item: str) -> None:
    """Set one ``section.field=value`` override in the config's dict ``data`` (the field must exist)."""
    _require("=" in item, f"override {item!r} must look like section.field=value, e.g. model.d_model=256")
    key, raw = item.split("=", 1)
    try:
        value = parse_json(raw)
    except ValueError:  # not JSON (a bare word), or a number too long to parse: checked as a string
        value = raw
    node = data
    parts = key.split(".")
    for part in parts[:-1]:
        _require(isinstance(node.get(part), dict), f"override {item!r}: {part!r} is not a config section")
        node = node[part]
    _require(parts[-1] in node, f"override {item!r}: unknown field {key!r}")
    node[parts[-1]] = value

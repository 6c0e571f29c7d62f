"""What a model promises the robot: its point clouds, state and action, horizons, sampler and control rate.

    contract = run_config.contract(ddim_timesteps=[90, 80, ..., 0])   # dssp_train: the run builds it at export
    contract = read_manifest(model_dir).contract                      # dssp_deploy: the runtime reads it back
    contract.n_action_steps, contract.denoise_steps, contract.control_rate_hz, contract.observation

One frozen record, validated once in its constructor, carried by reference: the exporter writes it once into
``dssp_model.json`` (``"contract"``; each ONNX file's metadata carries only its :meth:`ModelContract.digest`), the
runtime, the control loop and ``export.verify`` read its fields. The chunk's bounds (1 <= H_a, H_a + offset <= H)
are :func:`check_chunk`'s, which the training config calls for the same fields.

Shapes it fixes: point_cloud (B, P, point_dim) with P = n_points, agent_pos (B, state_dim), the chunk (B, H, A)
with A = action_dim, executed from index ``action_offset`` for H_a actions.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass
from typing import ClassVar

from dssp_core.errors import ConfigError
from dssp_core.schema import MAX_DIM, MAX_STEPS, Settings, control_rate_setting, setting
from dssp_data.observation import ObservationContract

MAX_POINTS = 1_000_000
MAX_TIMESTEPS = 100_000  # DDPM training timesteps


def check_chunk(n_obs_steps: int, horizon: int, n_action_steps: int, action_offset: int, section: str) -> None:
    """The executed slice chunk[action_offset : action_offset + H_a] must lie inside the H predicted actions, and
    start at the current step (0) or at the oldest recent observation (N - 1, DP3's alignment); else one
    ConfigError line naming ``section``'s fields."""
    if action_offset not in (0, n_obs_steps - 1):
        raise ConfigError(
            f"{section}.action_offset must be 0 or n_obs_steps - 1 = {n_obs_steps - 1}, got {action_offset}"
        )
    if action_offset + n_action_steps > horizon:
        if not action_offset:
            raise ConfigError(f"{section}.n_action_steps (H_a) must be in [1, horizon={horizon}], got {n_action_steps}")
        raise ConfigError(
            f"{section}.n_action_steps (H_a) must be at most horizon - N + 1 = {horizon - action_offset}, got "
            f"{n_action_steps}: DP3's alignment executes the chunk from index N - 1 = {action_offset}"
        )


@dataclass(frozen=True)
class ModelContract(Settings):
    """N = n_obs_steps, H = horizon, H_a = n_action_steps; K = :attr:`denoise_steps`, the number of
    ``ddim_timesteps`` (strictly decreasing: the sampler runs from noise to data); ``inpainting``: the denoiser
    takes the committed actions (real-time chunking); ``control_rate_hz``: the rate of the training data (None: it
    recorded none); ``observation``: the clouds' settings and the state/action layouts training saw. The defaults
    describe a small valid example (the schema's tests)."""

    SECTION: ClassVar[str] = "contract"

    point_dim: int = setting(3, choices=(3, 6))
    n_points: int = setting(64, ge=1, le=MAX_POINTS)
    state_dim: int = setting(7, ge=1, le=MAX_DIM)
    action_dim: int = setting(7, ge=1, le=MAX_DIM)
    n_obs_steps: int = setting(2, ge=1, le=MAX_STEPS)
    horizon: int = setting(4, ge=1, le=MAX_STEPS)
    n_action_steps: int = setting(3, ge=1, le=MAX_STEPS)
    action_offset: int = setting(0, ge=0, le=MAX_STEPS)
    ddim_timesteps: list[int] = setting(
        default_factory=lambda: list(range(90, -1, -10)), ge=0, lt=MAX_TIMESTEPS, min_length=1, max_length=MAX_TIMESTEPS
    )
    inpainting: bool = setting(False)
    control_rate_hz: float | None = control_rate_setting()
    observation: ObservationContract = setting(default_factory=ObservationContract)

    def validate(self) -> None:
        check_chunk(self.n_obs_steps, self.horizon, self.n_action_steps, self.action_offset, self.SECTION)
        steps = self.ddim_timesteps
        if any(a <= b for a, b in zip(steps, steps[1:])):
            raise ConfigError(
                f"{self.SECTION}.ddim_timesteps must decrease strictly (the sampler runs from noise to "
                f"data), got {steps}"
            )
        o = self.observation
        for field, have, want in (
            ("pointcloud.n_points", o.pointcloud and o.pointcloud.n_points, self.n_points),
            ("pointcloud.point_dim", o.pointcloud and o.pointcloud.point_dim, self.point_dim),
            ("state", o.state and o.state.dim, self.state_dim),
            ("action", o.action and o.action.dim, self.action_dim),
        ):
            if have is not None and have != want:
                raise ConfigError(f"{self.SECTION}.observation.{field} makes {have} values but the model takes {want}")

    @property
    def denoise_steps(self) -> int:
        """K: the denoiser's DDIM steps per chunk."""
        return len(self.ddim_timesteps)

    def model_fields(self) -> dict:
        """The training config's model fields this contract carries (:data:`CONTRACT_FIELDS`), as training had them
        (DP3's alignment is an offset of N - 1, with N = 1 the same chunk as the current one)."""
        return {
            "point_dim": self.point_dim,
            "n_points": self.n_points,
            "state_dim": self.state_dim,
            "action_dim": self.action_dim,
            "n_obs_steps": self.n_obs_steps,
            "horizon": self.horizon,
            "n_action_steps": self.n_action_steps,
            "action_alignment": "dp3" if self.action_offset else "current",
        }

    def to_json(self) -> dict:
        """JSON for ``dssp_model.json``: the observation contract's unknown fields as ``"unknown"``."""
        return {**self.to_dict(), "observation": self.observation.to_manifest()}

    @classmethod
    def from_json(cls, values) -> "ModelContract":
        if not isinstance(values, dict):
            raise ConfigError(f"{cls.SECTION} must be a JSON object, got {type(values).__name__}")
        missing = [f"{cls.SECTION}.{name}" for name in cls.field_names() if name not in values]
        if missing:
            raise ConfigError(f"{', '.join(missing)} {'is' if len(missing) == 1 else 'are'} missing")
        return cls.from_dict({**values, "observation": ObservationContract.from_manifest(values.get("observation"))})

    def digest(self) -> str:
        """sha256 of the contract's canonical JSON: what each ONNX file's metadata carries of it."""
        return hashlib.sha256(json.dumps(self.to_json(), sort_keys=True).encode()).hexdigest()


CONTRACT_FIELDS = tuple(ModelContract().model_fields())
"""The training config's model fields the contract carries (action_alignment as action_offset): a manifest's
model_config records the rest."""


def contract_setting(name: str, default, *, unset: int | None = None):
    """The training config's field for the contract's field ``name``, with the contract's range and choices (declared
    once, here) and the config's ``default``; ``unset``: a value the config also takes, meaning "from the dataset"."""
    spec = next(f.metadata["spec"] for f in dataclasses.fields(ModelContract) if f.name == name)
    if unset is not None:
        spec = dataclasses.replace(spec, ge=unset)
    return dataclasses.field(default=default, metadata={"spec": spec})

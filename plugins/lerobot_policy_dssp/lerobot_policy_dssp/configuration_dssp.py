"""``--policy.type=dssp``: the LeRobot config of a DSSP policy.

The model is a ``dssp_train`` preset (``--policy.preset``, default ``tiny``) with ``section.field=value``
overrides as ``dssp-train --set`` takes them (``--policy.overrides='[model.d_model=128]'``). Its data facts
(state, action and cloud sizes, the control rate = the dataset's fps, the observation contract) are filled from
the dataset when the policy is built, and recorded in ``run_config`` (so a saved policy rebuilds without it).

A dataset with no ``observation.pointcloud`` but a depth feature (``depth_key``) with its camera's intrinsics is
trained on the clouds the robot's pipeline makes of each depth frame (``extrinsics``: the camera's pose, the file
dssp-calibrate writes; ``pointcloud``: the point-cloud settings), in a processor step
(:mod:`lerobot_policy_dssp.processor_dssp`); ``depth_camera`` records what that step needs.

Every sample carries its episode's past: ``history`` frames up to the current one, and the ``horizon`` - 1 frames
after it (the action chunk's targets); frames outside the episode come padded and are dropped.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from lerobot.configs.policies import PreTrainedConfig
from lerobot.configs.types import NormalizationMode
from lerobot.optim.optimizers import AdamWConfig
from lerobot.optim.schedulers import LRSchedulerConfig

from dssp_train.config import RunConfig, apply_overrides, load_preset
from dssp_train.training.lr_schedule import cosine_with_warmup

CLOUD_KEY = "observation.pointcloud"
STATE_KEY = "observation.state"
ACTION_KEY = "action"
MAX_HISTORY = 100_000

DEPTH_KEY = "observation.depth"

REFUSE_NO_CLOUD = (
    "the dataset has no observation.pointcloud feature and no depth feature {key} (--policy.depth_key): DSSP trains "
    "on point clouds, from the dataset's clouds or from its depth with the camera's intrinsics"
)


@LRSchedulerConfig.register_subclass("dssp_cosine")
@dataclass
class DSSPCosineSchedulerConfig(LRSchedulerConfig):
    """dssp-train's schedule: linear warm-up, then cosine decay to zero at the last step."""

    num_warmup_steps: int | None = 500

    def build(self, optimizer, num_training_steps: int):
        return cosine_with_warmup(optimizer, self.num_warmup_steps or 0, num_training_steps)


@PreTrainedConfig.register_subclass("dssp")
@dataclass
class DSSPConfig(PreTrainedConfig):
    # The dssp_train preset and its overrides ("section.field=value", as dssp-train --set).
    preset: str = "tiny"
    overrides: list[str] = field(default_factory=list)
    # Frames of the past each sample carries (its own included): the history the model is trained on. Set it to
    # the longest episode (dssp-data inspect) for full-history training; older frames are not seen in training.
    history: int = 64
    # Training on depth (a dataset without observation.pointcloud): the depth feature, the camera's pose (the JSON
    # dssp-calibrate writes) and the point-cloud settings (a JSON file; default: the preset's, else the robot's
    # defaults with the model's n_points).
    depth_key: str = DEPTH_KEY
    extrinsics: str | None = None
    pointcloud: str | None = None
    # What the depth-to-cloud step needs (filled from the dataset and the files above when the policy is first built).
    depth_camera: dict | None = None
    # The resolved dssp_train RunConfig (filled from the dataset when the policy is first built).
    run_config: dict | None = None
    # The model keeps its own normalisers (fitted from the dataset's min/max): LeRobot's processors pass through.
    normalization_mapping: dict[str, NormalizationMode] = field(
        default_factory=lambda: {
            "VISUAL": NormalizationMode.IDENTITY,
            "STATE": NormalizationMode.IDENTITY,
            "ACTION": NormalizationMode.IDENTITY,
        }
    )

    # Checked when first used (the dataset's frames to load, the policy built), not in __post_init__: draccus,
    # which builds this config from lerobot-train's flags, would bury the refusal under its own generic line; from
    # there it is the last line LeRobot prints.
    def run(self) -> RunConfig:
        """The recorded RunConfig, or (before the dataset is seen) the preset with its overrides; an unknown
        preset, a bad override or a history outside [1, MAX_HISTORY] is refused in one line (ValueError)."""
        if isinstance(self.history, bool) or not isinstance(self.history, int) or not 1 <= self.history <= MAX_HISTORY:
            raise ValueError(f"--policy.history must be in [1, {MAX_HISTORY}] frames, got {self.history}")
        if self.run_config is not None:
            return RunConfig.from_dict(self.run_config)
        return apply_overrides(load_preset(self.preset), list(self.overrides))

    @property
    def horizon(self) -> int:
        return self.run().model.horizon

    @property
    def window(self) -> int:
        """Frames each training sample carries: ``history`` up to its own, and the chunk's ``horizon`` - 1 after."""
        return self.history + self.horizon - 1

    @property
    def observation_delta_indices(self) -> list[int]:
        return list(range(1 - self.history, self.horizon))

    @property
    def action_delta_indices(self) -> list[int]:
        return list(range(1 - self.history, self.horizon))

    @property
    def reward_delta_indices(self) -> None:
        return None

    @property
    def drop_n_last_frames(self) -> int:
        """dssp-train's window starts: t in [0, T - H_a] (at least H_a real actions after each)."""
        return self.run().model.n_action_steps - 1

    def get_optimizer_preset(self) -> AdamWConfig:
        t = self.run().train
        return AdamWConfig(lr=t.lr, betas=tuple(t.betas), weight_decay=t.weight_decay)

    def get_scheduler_preset(self) -> DSSPCosineSchedulerConfig:
        return DSSPCosineSchedulerConfig(num_warmup_steps=self.run().train.warmup_steps)

    def validate_features(self) -> None:
        if CLOUD_KEY not in self.input_features:
            raise ValueError(REFUSE_NO_CLOUD.format(key=self.depth_key))
        for key in (STATE_KEY,):
            if key not in self.input_features:
                raise ValueError(f"the dataset has no {key} feature; DSSP needs the robot's state")
        if ACTION_KEY not in self.output_features:
            raise ValueError("the dataset has no action feature")

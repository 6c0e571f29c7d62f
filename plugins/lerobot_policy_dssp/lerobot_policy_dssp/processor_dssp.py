"""The processors of a DSSP policy: LeRobot's usual pipeline with IDENTITY normalisation.

The model normalises its own inputs and outputs (its min/max normalisers are part of its weights and of the
exported graphs), so LeRobot's normaliser steps pass every feature through (the config's normalization_mapping).

On a dataset of depth (the config's ``depth_camera``), :class:`DepthToCloudStep` comes before them: it makes each
frame's cloud by the robot's pipeline (:mod:`lerobot_policy_dssp.depth`), sets ``observation.pointcloud`` and its
``_is_pad`` mask from the depth's, and removes the depth. Its settings (the camera's intrinsics and pose, the
point-cloud settings) are saved in ``policy_preprocessor.json``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from lerobot.configs.types import FeatureType, PipelineFeatureType, PolicyFeature
from lerobot.processor import (
    AddBatchDimensionProcessorStep,
    DeviceProcessorStep,
    NormalizerProcessorStep,
    PolicyAction,
    PolicyProcessorPipeline,
    ProcessorStep,
    ProcessorStepRegistry,
    RenameObservationsProcessorStep,
    TransitionKey,
    UnnormalizerProcessorStep,
)
from lerobot.processor.converters import policy_action_to_transition, transition_to_policy_action
from lerobot.utils.constants import POLICY_POSTPROCESSOR_DEFAULT_NAME, POLICY_PREPROCESSOR_DEFAULT_NAME

from lerobot_policy_dssp.configuration_dssp import CLOUD_KEY, DSSPConfig
from lerobot_policy_dssp.depth import DepthClouds

PAD = "_is_pad"


@ProcessorStepRegistry.register(name="dssp_depth_to_cloud")
@dataclass
class DepthToCloudStep(ProcessorStep):
    """Depth (H, W), (B, H, W) or (B, T, H, W) -> ``observation.pointcloud`` (..., P, 3) float32 in the robot's base
    frame, by :func:`dssp_data.pointcloud.frame_to_cloud`; the depth and its ``_is_pad`` mask are removed, the
    cloud's mask is the depth's. ``history``: the sample's own frame is T's ``history`` - 1 (it names a frame with
    no point in the crop by its dataset index)."""

    depth_camera: dict = field(default_factory=dict)
    history: int = 1

    def __post_init__(self) -> None:
        self._clouds = DepthClouds(self.depth_camera)

    def __call__(self, transition):
        observation = transition.get(TransitionKey.OBSERVATION)
        key = self._clouds.key
        if not isinstance(observation, dict) or key not in observation:
            return transition
        transition = transition.copy()
        observation = dict(observation)
        complementary = dict(transition.get(TransitionKey.COMPLEMENTARY_DATA) or {})
        depth = observation.pop(key)
        pad = observation.pop(key + PAD, complementary.pop(key + PAD, None))  # (in both where LeRobot batches)

        def as_numpy(x):
            return None if x is None else x.detach().cpu().numpy() if torch.is_tensor(x) else np.asarray(x)

        depth = as_numpy(depth)
        t = depth.shape[1] if depth.ndim == 4 else 1
        clouds = self._clouds(
            depth,
            as_numpy(pad),
            self.history - 1 if t > 1 else 0,
            as_numpy(complementary.get("index")),
            as_numpy(complementary.get("episode_index")),
        )
        observation[CLOUD_KEY] = torch.from_numpy(clouds)
        if pad is not None:
            observation[CLOUD_KEY + PAD] = complementary[CLOUD_KEY + PAD] = pad
        transition[TransitionKey.OBSERVATION] = observation
        transition[TransitionKey.COMPLEMENTARY_DATA] = complementary
        return transition

    def get_config(self) -> dict[str, Any]:
        return {"depth_camera": self.depth_camera, "history": self.history}

    def transform_features(self, features):
        observation = dict(features.get(PipelineFeatureType.OBSERVATION, {}))
        observation.pop(self._clouds.key, None)
        observation[CLOUD_KEY] = PolicyFeature(type=FeatureType.STATE, shape=(self._clouds.config.n_points, 3))
        return {**features, PipelineFeatureType.OBSERVATION: observation}


Observations = PolicyProcessorPipeline[dict[str, Any], dict[str, Any]]
Actions = PolicyProcessorPipeline[PolicyAction, PolicyAction]


def make_dssp_pre_post_processors(
    config: DSSPConfig, dataset_stats: dict[str, dict[str, torch.Tensor]] | None = None
) -> tuple[Observations, Actions]:
    input_steps = [
        RenameObservationsProcessorStep(rename_map={}),
        AddBatchDimensionProcessorStep(),
        *([DepthToCloudStep(depth_camera=config.depth_camera, history=config.history)] if config.depth_camera else []),
        DeviceProcessorStep(device=config.device),
        NormalizerProcessorStep(
            features={**config.input_features, **config.output_features},
            norm_map=config.normalization_mapping,
            stats=dataset_stats,
        ),
    ]
    output_steps = [
        UnnormalizerProcessorStep(
            features=config.output_features, norm_map=config.normalization_mapping, stats=dataset_stats
        ),
        DeviceProcessorStep(device="cpu"),
    ]
    return (
        Observations(steps=input_steps, name=POLICY_PREPROCESSOR_DEFAULT_NAME),
        Actions(
            steps=output_steps,
            name=POLICY_POSTPROCESSOR_DEFAULT_NAME,
            to_transition=policy_action_to_transition,
            to_output=transition_to_policy_action,
        ),
    )

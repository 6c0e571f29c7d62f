"""The processors of a DSSP policy: LeRobot's usual pipeline with IDENTITY normalisation.

The model normalises its own inputs and outputs (its min/max normalisers are part of its weights and of the
exported graphs), so LeRobot's normaliser steps pass every feature through (the config's normalization_mapping).
"""

from __future__ import annotations

from typing import Any

import torch
from lerobot.processor import (
    AddBatchDimensionProcessorStep,
    DeviceProcessorStep,
    NormalizerProcessorStep,
    PolicyAction,
    PolicyProcessorPipeline,
    RenameObservationsProcessorStep,
    UnnormalizerProcessorStep,
)
from lerobot.processor.converters import policy_action_to_transition, transition_to_policy_action
from lerobot.utils.constants import POLICY_POSTPROCESSOR_DEFAULT_NAME, POLICY_PREPROCESSOR_DEFAULT_NAME

from lerobot_policy_dssp.configuration_dssp import DSSPConfig


Observations = PolicyProcessorPipeline[dict[str, Any], dict[str, Any]]
Actions = PolicyProcessorPipeline[PolicyAction, PolicyAction]


def make_dssp_pre_post_processors(
    config: DSSPConfig, dataset_stats: dict[str, dict[str, torch.Tensor]] | None = None
) -> tuple[Observations, Actions]:
    input_steps = [
        RenameObservationsProcessorStep(rename_map={}),
        AddBatchDimensionProcessorStep(),
        DeviceProcessorStep(device=config.device),
        NormalizerProcessorStep(features={**config.input_features, **config.output_features},
                                norm_map=config.normalization_mapping, stats=dataset_stats),
    ]
    output_steps = [
        UnnormalizerProcessorStep(features=config.output_features, norm_map=config.normalization_mapping,
                                  stats=dataset_stats),
        DeviceProcessorStep(device="cpu"),
    ]
    return (
        Observations(steps=input_steps, name=POLICY_PREPROCESSOR_DEFAULT_NAME),
        Actions(
            steps=output_steps, name=POLICY_POSTPROCESSOR_DEFAULT_NAME,
            to_transition=policy_action_to_transition, to_output=transition_to_policy_action),
    )

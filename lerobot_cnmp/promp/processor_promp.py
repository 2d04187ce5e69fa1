"""Pre/post-processing of the ProMP baseline policy: LeRobot's standard pipelines, every normalizer passing
through (the ProMP works in the dataset's units, ``ProMPConfig.normalization_mapping``)."""

from __future__ import annotations

from typing import Any

import torch

from lerobot.processor import PolicyAction, PolicyProcessorPipeline, make_default_pre_post_processors

from lerobot_cnmp.promp.configuration_promp import ProMPConfig


def make_promp_pre_post_processors(
    config: ProMPConfig,
    dataset_stats: dict[str, dict[str, torch.Tensor]] | None = None,
) -> tuple[
    PolicyProcessorPipeline[dict[str, Any], dict[str, Any]],
    PolicyProcessorPipeline[PolicyAction, PolicyAction],
]:
    return make_default_pre_post_processors(config, None)

"""Pre/post-processing of the CNMP policy: LeRobot's standard pipeline (rename, batch, device, normalize |
unnormalize, cpu), with its normalizer steps passing CNMP's features through.

CNMP normalizes every SM input -- demonstrations, sensed dims, condition values -- and γ itself, with one set
of per-dim statistics computed from its training demonstrations and saved with its weights
(:class:`lerobot_cnmp.model.normalizer.SMNormalizer`); the policy's action comes out in the dataset's units.
So the processors save, load and push like any other policy's, and ``lerobot-train --policy.path=...``
(fine-tuning, which rebuilds the processors with the new dataset's raw statistics) cannot change CNMP's
scaling: the normalization a fine-tuned model sees is the one it was trained with.
"""

from __future__ import annotations

from typing import Any

import torch

from lerobot.processor import PolicyAction, PolicyProcessorPipeline, make_default_pre_post_processors

from lerobot_cnmp.policy.configuration_cnmp import CNMPConfig


def make_cnmp_pre_post_processors(
    config: CNMPConfig,
    dataset_stats: dict[str, dict[str, torch.Tensor]] | None = None,
) -> tuple[
    PolicyProcessorPipeline[dict[str, Any], dict[str, Any]],
    PolicyProcessorPipeline[PolicyAction, PolicyAction],
]:
    """LeRobot's standard policy pipelines; ``dataset_stats`` are not needed (CNMP keeps its own)."""
    return make_default_pre_post_processors(config, None)

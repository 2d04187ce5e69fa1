"""Pre/post-processing of the CNMP policy: LeRobot's standard pipeline with SM-consistent statistics.

The CNMP conditions on SM points that arrive through three features -- the action window (training),
the sensed ``observation.state`` and the condition values inside ``observation.environment_state`` -- so
all three must be normalized the same way: with the *action* statistics. ``sm_normalization_stats``
derives those statistics; the pipeline itself is LeRobot's default (rename, batch, device, normalize |
unnormalize, cpu), so it saves, loads and pushes like any other policy's.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from lerobot.processor import PolicyAction, PolicyProcessorPipeline, make_default_pre_post_processors
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_STATE

from lerobot_cnmp.conditions import slot_size
from lerobot_cnmp.configuration_cnmp import CNMPConfig


STD_FLOOR = 1e-2
"""An SM dim's normalization std is at least this fraction of the median SM dim's std."""


def _as_np(x) -> np.ndarray:
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


def floored_sm_std(std) -> np.ndarray:
    """The SM (action) std used for normalization: a dim that barely moves (e.g. a wrist held at one angle,
    whose std is IK round-off) would otherwise be scaled up to unit variance, and its noise, far below the
    model's σ floor, would dominate the NLL and its gradients."""
    std = _as_np(std).astype(np.float32).reshape(-1)
    # The median, not the largest: SM dims may mix units (metres, newtons), and one large-unit dim must not
    # flatten the small-unit ones.
    floor = max(STD_FLOOR * float(np.median(std)) if std.size else 0.0, 1e-6)
    return np.maximum(std, floor).astype(np.float32)


def sm_normalization_stats(config: CNMPConfig, dataset_stats: dict[str, dict[str, Any]] | None) -> dict | None:
    """Dataset statistics with ``observation.state`` and the condition values of
    ``observation.environment_state`` expressed in the action (SM) statistics, whose std is floored
    (:func:`floored_sm_std`).

    Condition slots are ``[present, phase, values(D), mask(D)]``: only the values are shifted/scaled; the
    flags, phases and masks get mean 0 / std 1 and pass unchanged."""
    if dataset_stats is None:
        return None
    if ACTION not in dataset_stats or not {"mean", "std"} <= set(dataset_stats[ACTION]):
        raise KeyError(f"dataset statistics need mean and std of {ACTION!r}; got {sorted(dataset_stats)}")
    stats = {k: dict(v) for k, v in dataset_stats.items()}
    mean = _as_np(dataset_stats[ACTION]["mean"]).astype(np.float32).reshape(-1)
    std = floored_sm_std(dataset_stats[ACTION]["std"])
    d = config.sm_dim
    if mean.shape != (d,):
        raise ValueError(f"action statistics have {mean.shape[0]} dims, the policy's SM has {d}")
    stats[ACTION] = {**stats[ACTION], "std": std.copy()}
    if config.robot_state_feature is not None:
        stats[OBS_STATE] = {"mean": mean.copy(), "std": std.copy()}
    env = config.env_state_feature
    if env is not None:
        k = env.shape[-1] // slot_size(d)
        env_mean = np.zeros((k, slot_size(d)), dtype=np.float32)
        env_std = np.ones((k, slot_size(d)), dtype=np.float32)
        env_mean[:, 2 : 2 + d] = mean
        env_std[:, 2 : 2 + d] = std
        stats[OBS_ENV_STATE] = {"mean": env_mean.reshape(-1), "std": env_std.reshape(-1)}
    return stats


def make_cnmp_pre_post_processors(
    config: CNMPConfig,
    dataset_stats: dict[str, dict[str, torch.Tensor]] | None = None,
) -> tuple[
    PolicyProcessorPipeline[dict[str, Any], dict[str, Any]],
    PolicyProcessorPipeline[PolicyAction, PolicyAction],
]:
    """LeRobot's standard policy pipelines, normalizing every SM input with the action statistics."""
    return make_default_pre_post_processors(config, sm_normalization_stats(config, dataset_stats))

"""Defaults chosen by a rule from the training dataset, for settings a config leaves at None ("by the rule").

A rule runs once, when a policy is built to train from a dataset; the value it picks is written into the
config, so the saved checkpoint names it explicitly and loads as it was trained. A policy built without a
dataset (from an env's features, or loading a checkpoint) gets the setting's neutral value.
"""

from __future__ import annotations

from lerobot_cnmp.policy.configuration_cnmp import CNMPConfig


def linear_task_term(config: CNMPConfig) -> bool:
    """``linear_task_term`` for a policy trained on a dataset: on when the episode has an episode-level input
    (task parameters γ, or the conv encoder's embedding of its first camera frames), the SM is in the joint
    layout (the action is commanded as is, not a position the PD law tracks) and there is a single decoder.
    With few demos the MLP's map from γ is biased along the movement and, with the commanded action applied as
    is (MetaWorld's hand deltas), that bias integrates; the linear term gives the network the contextual
    ProMP's linear map from γ (docs/fewdemo.md). From cameras the same holds for the embedding (with
    ``image_encoder.keypoints`` a linear map of image coordinates): on pick-place-v3 from two cameras, 50 demos,
    it took CNMP from 38 % to 66 % (docs/cameras.md). The policy does not know how many of the dataset's
    episodes its training draws will name, so the rule does not depend on the number of demos."""
    return config.episode_dim > 0 and not config.spec.tied and config.n_experts == 1


def resolve_rules(config: CNMPConfig, from_dataset: bool) -> None:
    """Fill the settings left at None: by their rule when ``from_dataset`` (training starts from a dataset,
    not from a checkpoint), else with the neutral value (the network as it was before the setting existed)."""
    if config.linear_task_term is None:
        config.linear_task_term = from_dataset and linear_task_term(config)

"""A checkpoint run on an env/robot whose features differ from those it was trained on stops with an error
that says so, naming the checkpoint's SM and the env's features (not one that reads like a bad --policy.sm),
and an observation wider than the checkpoint reads does not pass silently."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from lerobot.configs import FeatureType, PolicyFeature
from lerobot.configs.policies import PreTrainedConfig
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_STATE

from lerobot_cnmp.api import load_pretrained
from lerobot_cnmp.policy.modeling_cnmp import CNMPPolicy

GOLDEN = Path(__file__).resolve().parent / "golden"


def _on_env_with_action(name: str, action_dim: int):
    """What lerobot-eval does with --policy.path: the checkpoint's config, the env's output features."""
    cfg = PreTrainedConfig.from_pretrained(GOLDEN / name)
    cfg.output_features = {ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(action_dim,))}
    cfg._spec = None  # resolved again against the env's features, as when the policy is built
    return cfg


@pytest.mark.parametrize("name, action_dim", [("cnmp_obstacle2d", 7), ("cnmp_pickplace", 2)])
def test_checkpoint_on_an_env_with_other_actions_names_both(name, action_dim):
    cfg = _on_env_with_action(name, action_dim)
    with pytest.raises(ValueError) as err:
        CNMPPolicy(cfg)
    msg = str(err.value)
    assert "does not match the features" in msg and "checkpoint" in msg, msg
    assert str(list(cfg.sm)) in msg and f"'action': ({action_dim},)" in msg, msg


@pytest.mark.parametrize("width", [1, 7])
def test_an_observation_of_another_width_is_an_error(width):
    policy, _, _ = load_pretrained(GOLDEN / "cnmp_obstacle2d", device="cpu")
    policy.eval()
    policy.reset()
    obs = {OBS_STATE: torch.zeros(1, width), OBS_ENV_STATE: torch.zeros(1, 24)}
    with pytest.raises(ValueError, match=rf"'observation.state' has {width} dims, but this checkpoint was trained on 2"):
        policy.select_action(obs)
    policy.reset()
    assert policy.select_action({**obs, OBS_STATE: torch.zeros(1, 2)}).shape == (1, 2)

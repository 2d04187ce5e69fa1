"""Defaults chosen by a rule from the dataset (lerobot_cnmp.policy.rules): the linear-in-γ decoder term."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata
from lerobot.policies.factory import make_policy

from lerobot_cnmp.policy.configuration_cnmp import CNMPConfig
from lerobot_cnmp.policy.legacy import upgrade_config_dict
from lerobot_cnmp.policy.modeling_cnmp import CNMPPolicy

REPO = Path(__file__).resolve().parents[1]


def _meta(name: str) -> LeRobotDatasetMetadata:
    return LeRobotDatasetMetadata(f"lerobot-cnmp/{name}", root=REPO / "datasets" / name)


def small(**kw) -> CNMPConfig:
    return CNMPConfig(device="cpu", encoder_layers=(16, 16), decoder_layers=(16, 16), **kw)


@pytest.fixture(scope="module")
def push_meta():
    return _meta("cnmp_metaworld_push")


def test_rule_turns_the_term_on_for_a_joint_layout_with_gamma(push_meta):
    policy = make_policy(small(), ds_meta=push_meta)
    assert policy.config.linear_task_term is True  # written into the config: the checkpoint names it
    g = policy.config.task_dim
    assert g == 6 and policy.model.task_gain.shape == (policy.config.sm_dim, (2 + 0) * g)
    assert "model.task_gain" in policy.state_dict()


@pytest.mark.parametrize("kw", [{"linear_task_term": False}, {"use_task_params": False}, {"n_experts": 2}])
def test_rule_keeps_it_off_when_told_or_without_gamma_or_with_experts(push_meta, kw):
    policy = make_policy(small(**kw), ds_meta=push_meta)
    assert policy.config.linear_task_term is False and "model.task_gain" not in policy.state_dict()


def test_rule_keeps_it_off_in_the_tied_layout():
    policy = make_policy(small(state_tracks_action=True), ds_meta=_meta("cnmp_pickplace"))
    assert policy.config.task_dim == 2 and policy.config.linear_task_term is False


def test_without_a_dataset_the_term_is_off(push_meta):
    trained = make_policy(small(), ds_meta=push_meta)
    cfg = small(linear_task_term=None)
    cfg.input_features, cfg.output_features = trained.config.input_features, trained.config.output_features
    assert CNMPPolicy(cfg).config.linear_task_term is False


def test_explicit_true_without_gamma_is_an_error(push_meta):
    with pytest.raises(ValueError, match="linear_task_term=true needs task parameters"):
        make_policy(small(linear_task_term=True, use_task_params=False), ds_meta=push_meta)
    with pytest.raises(ValueError, match="single decoder"):
        small(linear_task_term=True, n_experts=2)


def test_checkpoint_with_the_term_loads_and_acts_identically(push_meta, tmp_path):
    policy = make_policy(small(), ds_meta=push_meta)
    with torch.no_grad():
        policy.model.task_gain.normal_()
    policy.save_pretrained(tmp_path)
    loaded = CNMPPolicy.from_pretrained(tmp_path)
    assert loaded.config.linear_task_term is True
    obs = {"observation.state": torch.tensor([[0.0, 0.6, 0.2, 1.0]]),
           "observation.task_params": torch.tensor([[0.05, 0.7, 0.02, 0.1, 0.8, 0.02]])}
    acts = []
    for p in (policy, loaded):
        p.eval()
        p.reset()
        acts.append(torch.cat([p.select_action(dict(obs)) for _ in range(3)]))
    assert torch.equal(acts[0], acts[1])


def test_trained_configs_from_before_the_setting_load_without_the_term():
    assert upgrade_config_dict({"dataset_fps": 80.0})["linear_task_term"] is False  # a checkpoint's config
    assert "linear_task_term" not in upgrade_config_dict({"dataset_fps": None})  # a config to train from
    assert upgrade_config_dict({"dataset_fps": 80.0, "linear_task_term": True})["linear_task_term"] is True


def _camera_config(**kw) -> CNMPConfig:
    """γ-free, one camera (the cameras-only datasets' shape): the state and the action, joint layout."""
    from lerobot.configs import FeatureType, PolicyFeature

    cfg = small(use_images=True, image_channels=(4, 8), image_embed_dim=6, **kw)
    cfg.input_features = {"observation.state": PolicyFeature(type=FeatureType.STATE, shape=(2,)),
                          "observation.images.top": PolicyFeature(type=FeatureType.VISUAL, shape=(3, 16, 16))}
    cfg.output_features = {"action": PolicyFeature(type=FeatureType.ACTION, shape=(2,))}
    return cfg


@pytest.mark.parametrize("tied", [False, True])
def test_rule_counts_the_image_embedding_as_the_episode_input(tied):
    """From cameras only (no γ) the embedding is the episode-level input: the term is on in the joint layout,
    linear in the embedding, and off in the tied layout (the paper's room, Exp B, keeps its network)."""
    from lerobot_cnmp.policy import rules

    cfg = _camera_config(state_tracks_action=tied)
    policy = CNMPPolicy(cfg)  # resolves the SM layout; no dataset: the term stays off
    assert cfg.task_dim == 0 and cfg.episode_dim == 6 and cfg.linear_task_term is False
    assert rules.linear_task_term(cfg) is (not tied)
    if not tied:
        cfg.linear_task_term = True
        on = CNMPPolicy(cfg)
        assert on.model.task_gain.shape == (cfg.sm_dim, 2 * 6) and policy.model.task_gain is None

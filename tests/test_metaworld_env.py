"""The thin MetaWorld wrapper (cnmp_metaworld): MetaWorld's tasks, experts and success flag, our observation."""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("HF_HUB_OFFLINE", "1")

import numpy as np
import pytest

pytest.importorskip("metaworld")

import lerobot_cnmp.sims  # noqa: E402,F401
from lerobot_cnmp.sims.metaworld.config import CNMPMetaWorldEnv  # noqa: E402
from lerobot_cnmp.sims.metaworld.env import MetaWorldEnv  # noqa: E402
from lerobot_cnmp.sims.metaworld.task import v3_task_names  # noqa: E402
from lerobot_cnmp.sims.metaworld.expert import MetaWorldExpert, expert_policy_name  # noqa: E402


def test_task_names_checked():
    assert {"reach-v3", "push-v3", "pick-place-v3"} <= set(v3_task_names()) and len(v3_task_names()) == 50
    with pytest.raises(ValueError, match="the v3 tasks are"):
        CNMPMetaWorldEnv(task="push-v2")  # LeRobot's own metaworld default, a KeyError there
    with pytest.raises(ValueError, match="path length"):
        CNMPMetaWorldEnv(task="reach-v3", episode_length=501)
    assert expert_policy_name("pick-place-v3") == "SawyerPickPlaceV3Policy"
    cfg = CNMPMetaWorldEnv(task="button-press-v3")
    assert cfg.gym_id == "cnmp/MetaWorld-v0" and cfg.gym_kwargs["task"] == "button-press-v3"


@pytest.mark.parametrize("task", ["reach-v3", "push-v3", "pick-place-v3"])
def test_expert_succeeds_with_random_placements(task):
    env = MetaWorldEnv(task, terminate_on_success=False, max_episode_steps=150)
    gammas = []
    for seed in range(3):
        obs, _ = env.reset(seed=seed)
        assert obs["agent_pos"].shape == (4,) and obs["environment_state"].shape == (6,)
        gammas.append(obs["environment_state"].copy())
        expert = MetaWorldExpert(env)
        expert.reset()
        for k in range(150):
            obs, _, _, _, info = env.step(expert.act(k))
            np.testing.assert_array_equal(obs["environment_state"], gammas[-1])  # γ: the first frame's
            assert info["is_success"] == bool(info["success"])  # MetaWorld's own flag
        assert info["is_success"], (task, seed)
    assert np.ptp(np.stack(gammas)[:, 3:], axis=0).max() > 0.01 or task == "push-v3"  # goals move between seeds
    again, _ = env.reset(seed=1)
    np.testing.assert_allclose(again["environment_state"], gammas[1])  # the seed fixes the placement


def test_an_idle_arm_fails():
    env = MetaWorldEnv("reach-v3", terminate_on_success=False, max_episode_steps=60)
    env.reset(seed=0)
    for _ in range(60):
        _, _, _, truncated, info = env.step(np.zeros(4))
    assert not info["is_success"] and truncated


def test_record_a_metaworld_task(tmp_path):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from lerobot_cnmp.record import record_dataset

    root = record_dataset("cnmp_metaworld", tmp_path / "ds", n_episodes=2, conditions="push-v3", progress=False)
    ds = LeRobotDataset("local/ds", root=root)
    assert ds.meta.total_episodes == 2 and ds.meta.total_frames == 300
    assert set(ds.meta.features) >= {"action", "observation.state", "observation.task_params"}
    assert ds[0]["task"] == "push-v3"

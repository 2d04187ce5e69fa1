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


# --- cameras: the policy sees the hand state and images; γ is ground truth only -------------------------------


def test_cameras_replace_gamma_in_the_observation_and_keep_it_in_info():
    plain = MetaWorldEnv("push-v3", terminate_on_success=False)
    obs0, info0 = plain.reset(seed=3)
    env = MetaWorldEnv("push-v3", terminate_on_success=False, cameras=["corner3", "gripperPOV"], camera_size=48)
    obs, info = env.reset(seed=3)
    assert set(obs) == {"agent_pos", "pixels"} and set(obs["pixels"]) == {"corner3", "gripperPOV"}
    for img in obs["pixels"].values():
        assert img.shape == (48, 48, 3) and img.dtype == np.uint8 and img.std() > 5  # a scene, not a blank
    assert env.observation_space.contains(obs)
    np.testing.assert_array_equal(info["task_params"], obs0["environment_state"])  # γ, not observed
    np.testing.assert_array_equal(info0["task_params"], obs0["environment_state"])
    obs2, _, _, _, info2 = env.step(np.zeros(4))
    np.testing.assert_array_equal(info2["task_params"], info["task_params"])
    other, _ = env.reset(seed=4)  # another object/goal placement: the camera sees it
    assert np.abs(other["pixels"]["corner3"].astype(int) - obs["pixels"]["corner3"].astype(int)).sum() > 0
    env.close()
    plain.close()


@pytest.mark.parametrize("cameras, size, message", [
    (["corner3", "nope"], 64, "unknown camera"),
    ("corner3", 64, "list of camera names"),
    (["corner3", "corner3"], 64, "distinct"),
    (["corner3"], 16, "at least 32"),
])
def test_bad_camera_options_are_clear_errors(cameras, size, message):
    with pytest.raises(ValueError, match=message):
        MetaWorldEnv("push-v3", cameras=cameras, camera_size=size)


def test_camera_config_declares_images_and_no_gamma():
    cfg = CNMPMetaWorldEnv(task="push-v3", cameras=["corner3"], camera_size=64)
    assert "environment_state" not in cfg.features and cfg.features["pixels/corner3"].shape == (64, 64, 3)
    assert cfg.features_map["pixels/corner3"] == "observation.images.corner3"
    assert cfg.ground_truth == {"ground_truth.task_params": "task_params"}
    assert cfg.gym_kwargs["cameras"] == ["corner3"] and cfg.gym_kwargs["camera_size"] == 64
    plain = CNMPMetaWorldEnv(task="push-v3")
    assert "environment_state" in plain.features and plain.ground_truth == {}
    with pytest.raises(ValueError, match="list of camera names"):
        CNMPMetaWorldEnv(task="push-v3", cameras="corner3")


def test_record_cameras_as_video_with_gamma_as_ground_truth(tmp_path):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from lerobot_cnmp.record import record_dataset

    root = record_dataset("cnmp_metaworld", tmp_path / "cam", n_episodes=2, conditions="push-v3", progress=False,
                          cameras=["corner3"], camera_size=64)
    ds = LeRobotDataset("local/cam", root=root)
    feats = ds.meta.features
    assert feats["observation.images.corner3"]["dtype"] == "video"
    assert "observation.task_params" not in feats and "observation.environment_state" not in feats
    assert feats["ground_truth.task_params"]["names"] == ["obj_x", "obj_y", "obj_z", "goal_x", "goal_y", "goal_z"]
    item = ds[0]
    assert tuple(item["observation.images.corner3"].shape) == (3, 64, 64)
    assert not any(k.startswith("observation.") and "task" in k for k in item)
    live = MetaWorldEnv("push-v3", cameras=["corner3"], camera_size=64)  # γ and frame 0 at seed + i
    for ep in (0, 1):
        obs, info = live.reset(seed=ep)
        frame = ds[int(ds.meta.episodes["dataset_from_index"][ep])]
        np.testing.assert_allclose(frame["ground_truth.task_params"].numpy(), info["task_params"], atol=1e-6)
        # the video is near-lossless: the decoded frame is what the camera gives live (within 3 / 255)
        decoded = frame["observation.images.corner3"].numpy().transpose(1, 2, 0)
        assert np.abs(decoded - obs["pixels"]["corner3"] / 255.0).max() <= 3 / 255
    live.close()
    assert ds.meta.features["observation.images.corner3"]["info"]["video.codec"] == "h264"
    card = (root / "README.md").read_text()
    assert "--cameras corner3 --camera_size 64" in card


def test_record_camera_errors(tmp_path):
    from lerobot_cnmp.record import record_dataset

    with pytest.raises(ValueError, match="no camera option"):
        record_dataset("cnmp_obstacle2d", tmp_path / "a", n_episodes=1, progress=False, cameras=["top"])
    with pytest.raises(ValueError, match="camera_size is given without cameras"):
        record_dataset("cnmp_metaworld", tmp_path / "b", n_episodes=1, conditions="push-v3", progress=False,
                       camera_size=64)
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_the_first_camera_frame_shows_this_episodes_goal():
    """MetaWorld moves its goal marker after each step, not at reset: frame 0 must show the new episode's goal
    (where the marker is after a step), not the last episode's."""
    env = MetaWorldEnv("push-v3", terminate_on_success=False, cameras=["corner3"], camera_size=64)

    def goal_pixels(img):  # push's goal marker is pure green
        im = img.astype(int)
        ys, xs = np.nonzero((im[..., 1] > 120) & (im[..., 0] < 80) & (im[..., 2] < 80))
        return np.array([xs.mean(), ys.mean()]) if len(xs) else None

    for seed in (1, 3):
        env.reset(seed=seed - 1)
        for _ in range(5):
            env.step(np.zeros(4))
        obs, _ = env.reset(seed=seed)
        after, _, _, _, _ = env.step(np.zeros(4))
        first, later = goal_pixels(obs["pixels"]["corner3"]), goal_pixels(after["pixels"]["corner3"])
        assert first is not None and later is not None
        np.testing.assert_allclose(first, later, atol=1.0)
    env.close()

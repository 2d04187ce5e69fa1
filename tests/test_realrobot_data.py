"""Tests of tests/realrobot_data.py, the SO-101-shaped LeRobotDataset used by other tests."""

from __future__ import annotations

import os

os.environ.setdefault("HF_HUB_OFFLINE", "1")

import numpy as np
import pytest
import torch

from realrobot_data import (
    ACTION_NAMES,
    CAMERA_KEY,
    ENV_NAMES,
    FPS,
    IMAGE_HW,
    MAX_LEN,
    MIN_LEN,
    REPO_ID,
    ROBOT_TYPE,
    STATE_NAMES,
    TASK,
    make_realrobot_dataset,
)


@pytest.fixture(scope="module")
def video_root(tmp_path_factory):
    return make_realrobot_dataset(tmp_path_factory.mktemp("rr") / "so101", n_episodes=6, seed=0, video=True)


def _columns(ds) -> dict[str, np.ndarray]:
    hf = ds.hf_dataset.with_format("numpy")
    return {k: np.stack(hf[k]) for k in ("observation.state", "action", "observation.environment_state",
                                          "episode_index", "frame_index")}


def test_layout_names_lengths_and_lagging_state(video_root, tmp_path):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset(REPO_ID, root=video_root)
    assert ds.fps == FPS and ds.meta.robot_type == ROBOT_TYPE and ds.num_episodes == 6
    f = ds.features
    assert f["observation.state"]["shape"] == (6,) and f["observation.state"]["names"] == STATE_NAMES
    assert f["action"]["shape"] == (7,) and f["action"]["names"] == ACTION_NAMES
    assert f["observation.environment_state"]["shape"] == (3,)
    assert f["observation.environment_state"]["names"] == ENV_NAMES
    assert f[CAMERA_KEY]["dtype"] == "video" and ds.meta.video_keys == [CAMERA_KEY]
    assert list(ds.meta.tasks.index) == [TASK]

    lengths = [int(n) for n in ds.meta.episodes["length"]]
    assert all(MIN_LEN <= n <= MAX_LEN for n in lengths) and len(set(lengths)) > 1
    assert sum(lengths) == ds.num_frames

    c = _columns(ds)
    for ep, n in enumerate(lengths):
        m = c["episode_index"] == ep
        state, action, env = c["observation.state"][m], c["action"][m], c["observation.environment_state"][m]
        assert len(state) == n and (c["frame_index"][m] == np.arange(n)).all()
        assert np.ptp(env, axis=0).max() == 0  # task parameter constant in an episode
        assert np.all(state[:, 5] >= 0) and np.all(state[:, 5] <= 100)  # gripper 0..100
        # the follower lags the leader: neither the current nor the previous action
        assert np.abs(state[1:] - action[:-1, :6]).mean() > 0.3
        assert np.abs(state - action[:, :6]).mean() > 0.3
        # but it tracks it: both end close to the goal pose, and the action moves smoothly
        assert np.abs(state[-1, :5] - action[-1, :5]).max() < 3.0
        assert np.abs(np.diff(action[:, :5], n=2, axis=0)).max() < 2.0
    goals = c["observation.environment_state"][np.r_[0, np.cumsum(lengths)[:-1]]]
    assert len(np.unique(goals, axis=0)) == 6  # a different goal per episode

    # deterministic for a seed (checked on the camera-less variant, which is faster to build)
    a = _columns(LeRobotDataset(REPO_ID, root=make_realrobot_dataset(tmp_path / "a", 3, seed=1, video=False)))
    b = _columns(LeRobotDataset(REPO_ID, root=make_realrobot_dataset(tmp_path / "b", 3, seed=1, video=False)))
    assert all(np.array_equal(a[k], b[k]) for k in a)
    assert not np.array_equal(a["action"][:10], c["action"][:10])


def test_video_frame_decodes_to_declared_shape(video_root):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset(REPO_ID, root=video_root)
    h, w = IMAGE_HW
    assert tuple(ds.features[CAMERA_KEY]["shape"]) == (h, w, 3)
    first, later = ds[0], ds[40]
    for item in (first, later):
        img = item[CAMERA_KEY]
        assert img.shape == (3, h, w) and img.dtype == torch.float32  # LeRobot returns CHW in [0, 1]
        assert 0.0 <= float(img.min()) and float(img.max()) <= 1.0
        assert item["task"] == TASK
    assert int(later["episode_index"]) == 0
    assert (first[CAMERA_KEY] - later[CAMERA_KEY]).abs().max() > 0.1  # the blob moved
    last = ds[ds.num_frames - 1]  # last frame of the last episode: its own video segment decodes too
    assert last[CAMERA_KEY].shape == (3, h, w)

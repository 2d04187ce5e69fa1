"""Tests of the generic demonstration recorder (``lerobot-cnmp-record``)."""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("HF_HUB_OFFLINE", "1")

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from lerobot_cnmp import record as record_mod
from lerobot_cnmp.execution.conditions import conditions_from_vector
from lerobot_cnmp.sims import SIMS
from lerobot_cnmp.sims.obstacle2d.expert import Obstacle2DExpert

SIM = "cnmp_obstacle2d"
REPO = "lerobot-cnmp/test_obstacle2d"


def _parquet(root: Path) -> pd.DataFrame:
    files = sorted((root / "data").rglob("*.parquet"))
    assert files
    return pd.concat([pd.read_parquet(f) for f in files], ignore_index=True)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("rec") / "ds"
    out = record_mod.record_dataset(SIM, root, n_episodes=4, seed=0, repo_id=REPO, progress=False)
    assert out == root.absolute()
    return root


def test_recorded_dataset_loads(recorded):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset(REPO, root=recorded)
    assert ds.meta.total_episodes == 4 and ds.num_episodes == 4
    assert ds.meta.total_frames == 4 * SIMS[SIM].demo_length
    assert ds.fps == 50
    feats = ds.meta.features
    assert feats["action"]["shape"] in ((2,), [2]) and feats["action"]["names"] == ["x", "y"]
    assert feats["observation.state"]["names"] == ["x", "y"]
    assert tuple(feats["observation.environment_state"]["shape"]) == (24,)
    assert feats["observation.environment_state"]["names"][:6] == [
        "c0_present", "c0_phase", "c0_x", "c0_y", "c0_mask_x", "c0_mask_y",
    ]
    item = ds[0]
    assert item["action"].shape == (2,) and item["observation.state"].shape == (2,)
    assert item["observation.environment_state"].shape == (24,)
    assert item["task"] == "reach the goal around the obstacle"

    df = _parquet(recorded)
    lengths = df.groupby("episode_index").size()
    assert list(lengths) == [200] * 4
    modes = []
    for ep, g in df.groupby("episode_index"):
        state = np.stack(g["observation.state"].to_numpy())
        env_state = np.stack(g["observation.environment_state"].to_numpy())
        action = np.stack(g["action"].to_numpy())
        assert (env_state == env_state[0]).all()  # conditions constant within an episode
        assert conditions_from_vector(env_state[0], sm_dim=2)
        assert state[0, 0] == pytest.approx(0.0, abs=1e-6)  # starts at x = 0
        assert state[-1, 0] == pytest.approx(1.0, abs=0.05)  # ends near x = 1
        # action k is the reference at phase k / (T - 1): the SM trajectory starts at the start state,
        # and the state sensed at frame k is where action k - 1 sent the servo
        np.testing.assert_allclose(action[:, 0], np.arange(200) / 199, atol=1e-6)
        np.testing.assert_allclose(action[0], state[0], atol=1e-6)
        assert np.abs(state[1:] - action[:-1]).max() < 0.015  # servo tracking lag (measured <= 1.2 cm)
        modes.append(int(np.sign(state[len(state) // 2, 1])))  # over (+1) or under (-1) at mid-motion
    assert modes == [1, -1, 1, -1]

    card = (recorded / "README.md").read_text()
    assert "lerobot-cnmp-record --sim cnmp_obstacle2d" in card and "--seed 0" in card
    assert "| over | 2 |" in card and "| under | 2 |" in card
    assert "license" in card.lower()
    assert "CPU cores" in card and "s per episode" in card  # how long generation took, and where
    # no temp folders left next to the dataset
    assert [p.name for p in recorded.parent.iterdir()] == ["ds"]


def test_same_seed_identical(recorded, tmp_path):
    again = record_mod.record_dataset(SIM, tmp_path / "again", n_episodes=4, seed=0, repo_id=REPO, progress=False)
    a, b = _parquet(recorded), _parquet(again)
    assert list(a.columns) == list(b.columns)
    for col in a.columns:
        va, vb = a[col].to_numpy(), b[col].to_numpy()
        if va.dtype == object:
            va, vb = np.stack(va), np.stack(vb)
        np.testing.assert_array_equal(va, vb, err_msg=col)


def test_existing_root_not_overwritten(tmp_path):
    root = tmp_path / "ds"
    root.mkdir()
    (root / "keep.txt").write_text("precious")
    with pytest.raises(FileExistsError, match="overwrite"):
        record_mod.record_dataset(SIM, root, n_episodes=1, progress=False)
    assert [p.name for p in root.iterdir()] == ["keep.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ds"]
    # with overwrite the folder is replaced by the new dataset
    record_mod.record_dataset(SIM, root, n_episodes=1, overwrite=True, progress=False)
    assert not (root / "keep.txt").exists() and (root / "meta" / "info.json").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ds"]


def test_failing_expert_leaves_nothing(tmp_path, monkeypatch):
    def straight_line(self, step):
        task = self.env.task
        tau = min((step + 1) / (self.demo_length - 1), 1.0)
        return (task.start + tau * (task.goal - task.start)).astype(np.float32)

    monkeypatch.setattr(Obstacle2DExpert, "act", straight_line)
    root = tmp_path / "ds"
    # conditions=paper_end (y0 = 0.13): the straight line crosses the obstacle in every episode
    with pytest.raises(record_mod.DemoFailedError, match="episode 0"):
        record_mod.record_dataset(SIM, root, n_episodes=2, conditions="paper_end", progress=False)
    assert not root.exists()
    assert list(tmp_path.iterdir()) == []


def test_bad_arguments(tmp_path):
    with pytest.raises(ValueError, match="cnmp_obstacle2d"):
        record_mod.record_dataset("nope", tmp_path / "x", n_episodes=1)
    with pytest.raises(ValueError, match="n_episodes"):
        record_mod.record_dataset(SIM, tmp_path / "x", n_episodes=0)
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(SystemExit):
        record_mod.main(["--sim", "nope", "--root", str(tmp_path / "x")])
    with pytest.raises(SystemExit):
        record_mod.main(["--sim", SIM, "--root", str(tmp_path / "x"), "--n_episodes", "0"])


def test_cli(tmp_path):
    assert record_mod.main(["--sim", SIM, "--root", str(tmp_path / "cli"), "--n_episodes", "1", "--seed", "3"]) == 0
    assert (tmp_path / "cli" / "meta" / "info.json").exists()
    assert "--seed 3" in (tmp_path / "cli" / "README.md").read_text()
    assert record_mod.main(["--sim", SIM, "--root", str(tmp_path / "cli"), "--n_episodes", "1"]) == 1


def test_record_room_images(tmp_path):
    """Image features: the room's mask is stored as PNG frames and loads back as LeRobot's float CHW."""
    import torch
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from lerobot_cnmp.sims.room.env import RoomEnv

    repo = "lerobot-cnmp/test_room"
    root = record_mod.record_dataset("cnmp_room", tmp_path / "room", n_episodes=2, seed=5, repo_id=repo,
                                     progress=False)
    ds = LeRobotDataset(repo, root=root)
    T = SIMS["cnmp_room"].demo_length
    assert ds.num_episodes == 2 and ds.meta.total_frames == 2 * T == 200
    feat = ds.meta.features["observation.images.top"]
    assert feat["dtype"] == "image" and tuple(feat["shape"]) == (64, 64, 3)
    assert feat["names"] == ["height", "width", "channels"]
    assert tuple(ds.meta.features["observation.environment_state"]["shape"]) == (18,)
    assert not (root / "videos").exists() and not (root / "images").exists()  # embedded PNGs, no video
    env = RoomEnv(render_mode=None)
    for ep in range(2):
        env.reset(seed=5 + ep)
        expected = torch.from_numpy(env.mask).permute(2, 0, 1).float() / 255
        for k in (0, T - 1):
            item = ds[ep * T + k]
            img = item["observation.images.top"]
            assert img.shape == (3, 64, 64) and img.dtype == torch.float32
            torch.testing.assert_close(img, expected, rtol=0, atol=0)
            assert conditions_from_vector(item["observation.environment_state"].numpy(), sm_dim=2)
        np.testing.assert_allclose(ds[ep * T]["observation.state"].numpy(), env.task.start, atol=1e-6)
    env.close()
    card = (root / "README.md").read_text()
    assert "PNG" in card and "CPU cores" in card and "first |" in card


def test_record_shared_family(tmp_path):
    """``--sim cnmp_obstacle2d_shared``: both modes start and end at the same heights (family ``shared``)."""
    from lerobot_cnmp.sims.obstacle2d.task import SHARED_Y0_RANGE

    root = record_mod.record_dataset("cnmp_obstacle2d_shared", tmp_path / "ds", n_episodes=4, seed=0, progress=False)
    df = _parquet(root)
    card = (root / "README.md").read_text()
    assert "--sim cnmp_obstacle2d_shared" in card and "family `shared`" in card
    for e, ep in df.groupby("episode_index"):
        a = np.stack(ep["action"].to_numpy())
        assert SHARED_Y0_RANGE[0] <= a[0, 1] <= SHARED_Y0_RANGE[1]
        assert a[-1, 1] == pytest.approx(a[0, 1], abs=1e-6)
        # even episodes over the obstacle, odd ones under
        assert np.sign(a[100, 1]) == (1 if e % 2 == 0 else -1)


def test_action_noise_perturbs_execution_and_records_the_experts_action(recorded, tmp_path):
    """DART: the env executes action + noise, the dataset keeps the expert's action (the obstacle expert
    replays its path, so its actions do not depend on the state reached: equal to the noise-free run's)."""
    noisy = record_mod.record_dataset(SIM, tmp_path / "noisy", n_episodes=4, seed=0, repo_id=REPO, progress=False,
                                      action_noise="0.05")
    clean_df, noisy_df = _parquet(recorded), _parquet(noisy)
    clean_a, noisy_a = (np.stack(d["action"].to_numpy()) for d in (clean_df, noisy_df))
    clean_s, noisy_s = (np.stack(d["observation.state"].to_numpy()) for d in (clean_df, noisy_df))
    assert np.allclose(clean_a, noisy_a)
    first = clean_df["frame_index"].to_numpy() == 0
    assert np.allclose(clean_s[first], noisy_s[first])
    assert np.abs(clean_s[~first] - noisy_s[~first]).max() > 1e-3  # the executions differ
    card = (noisy / "README.md").read_text()
    assert "DART" in card and "--action_noise 0.05,0.05" in card


@pytest.mark.parametrize("noise, message", [("0.1,0.2,0.3", "has 3 values; the action has 2 dims"),
                                            ("-1", "finite and >= 0"), ("a", "numbers separated by commas")])
def test_bad_action_noise_is_a_clear_error(tmp_path, noise, message):
    with pytest.raises(ValueError, match=message):
        record_mod.record_dataset(SIM, tmp_path / "x", n_episodes=1, action_noise=noise, progress=False)
    assert not (tmp_path / "x").exists()


def test_max_failed_drops_failed_demos_and_records_the_next_seed(tmp_path, monkeypatch):
    """Every other attempt fails (a straight line through the obstacle): with max_failed the failed seeds
    are dropped and listed in the card; one failure more than allowed stops the recording, leaving nothing."""
    real_act, real_reset = Obstacle2DExpert.act, Obstacle2DExpert.reset
    resets = []

    def reset(self):
        resets.append(1)
        return real_reset(self)

    def act(self, step):
        if len(resets) % 2 == 0:  # attempts 1, 3, ...
            task = self.env.task
            tau = min((step + 1) / (self.demo_length - 1), 1.0)
            return (task.start + tau * (task.goal - task.start)).astype(np.float32)
        return real_act(self, step)

    monkeypatch.setattr(Obstacle2DExpert, "reset", reset)
    monkeypatch.setattr(Obstacle2DExpert, "act", act)
    root = record_mod.record_dataset(SIM, tmp_path / "ds", n_episodes=2, seed=10, conditions="paper_end",
                                     max_failed=1, progress=False)
    df = _parquet(root)
    assert sorted(df["episode_index"].unique().tolist()) == [0, 1]
    card = (root / "README.md").read_text()
    assert "reset seeds [11]" in card and "| 1 | 12 |" in card and "--max_failed 1" in card
    resets.clear()
    with pytest.raises(record_mod.DemoFailedError, match="1 failed demos were dropped already"):
        record_mod.record_dataset(SIM, tmp_path / "ds2", n_episodes=3, seed=10, conditions="paper_end",
                                  max_failed=1, progress=False)
    assert not (tmp_path / "ds2").exists()
    with pytest.raises(ValueError, match="max_failed must be >= 0"):
        record_mod.record_dataset(SIM, tmp_path / "ds3", n_episodes=1, max_failed=-1, progress=False)


def test_demo_length_sets_the_frames_per_demo_and_is_in_the_regenerate_command(tmp_path):
    default = SIMS[SIM].demo_length
    root = record_mod.record_dataset(SIM, tmp_path / "long", n_episodes=1, seed=0, progress=False,
                                     demo_length=default + 30)
    assert len(_parquet(root)) == default + 30
    assert f"--demo_length {default + 30}" in (root / "README.md").read_text()
    with pytest.raises(ValueError, match="demo_length"):
        record_mod.record_dataset(SIM, tmp_path / "bad", n_episodes=1, demo_length=1)
    assert not (tmp_path / "bad").exists()


def test_stale_staging_folders_of_killed_recordings_are_removed(tmp_path, capsys):
    import subprocess
    import sys

    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()  # a finished process: its staging folder is stale
    root = tmp_path / "ds"
    stale = tmp_path / f".ds.{gone.pid}.k1ll3d.tmp"
    live = tmp_path / f".ds.{os.getpid()}.running.tmp"  # a recording that still runs (this process)
    legacy = tmp_path / ".ds.ab12cd34.tmp"  # an older recorder's folder: no pid, left alone and named
    other = tmp_path / f".other.{gone.pid}.k1ll3d.tmp"  # another dataset's staging folder
    for folder in (stale, live, legacy, other):
        (folder / "dataset").mkdir(parents=True)
    record_mod.record_dataset(SIM, root, n_episodes=1, progress=False)
    assert not stale.exists()
    assert live.exists() and legacy.exists() and other.exists()
    err = capsys.readouterr().err
    assert f"removed 1 staging folder(s) of killed recordings of {root.absolute()}: ['{stale.name}']" in err
    assert legacy.name in err
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["ds", live.name, legacy.name, other.name])


def test_staging_folder_names_the_recording_process(tmp_path, monkeypatch):
    seen = []
    real_write_card = record_mod.write_card

    def spy(path, **kw):
        seen.append(path)
        return real_write_card(path, **kw)

    monkeypatch.setattr(record_mod, "write_card", spy)
    record_mod.record_dataset(SIM, tmp_path / "ds", n_episodes=1, progress=False)
    staging = seen[0].parent.parent.name  # <staging>/dataset/README.md
    assert staging.startswith(f".ds.{os.getpid()}.") and staging.endswith(".tmp")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ds"]

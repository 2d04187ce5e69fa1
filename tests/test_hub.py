"""Hub round trips against a local folder laid out as the Hub (the Hub itself cannot be reached here).

The ``fake_hub`` fixture replaces the Hub's services (create_repo, upload_folder, the card upload and its
server-side validation, tags) with copies into ``<hub>/<type>s/<repo_id>/``; everything above them -- LeRobot's
``LeRobotDataset.push_to_hub``, our ``push_dataset`` / ``push_checkpoint`` and model card -- runs for real,
and the pushed folders are then loaded back with LeRobot's loaders."""

from __future__ import annotations

import shutil
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from lerobot_cnmp.api import CNMPModel, Condition, load_pretrained
from lerobot_cnmp.hub import HubUnavailableError, push_checkpoint, push_dataset
from lerobot_cnmp.record import main as record_main

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture
def fake_hub(tmp_path, monkeypatch):
    import huggingface_hub.repocard as repocard
    from huggingface_hub import HfApi, constants
    from huggingface_hub.utils import filter_repo_objects

    hub = tmp_path / "hub"

    def folder(repo_id, repo_type):
        return hub / f"{repo_type or 'model'}s" / repo_id

    def create_repo(self, repo_id, repo_type=None, private=False, exist_ok=False, **kw):
        folder(repo_id, repo_type).mkdir(parents=True, exist_ok=exist_ok)
        return SimpleNamespace(repo_id=repo_id)

    def upload_folder(self, repo_id, folder_path, repo_type=None, allow_patterns=None, ignore_patterns=None, **kw):
        src, dst = Path(folder_path), folder(repo_id, repo_type)
        files = [p.relative_to(src).as_posix() for p in src.rglob("*") if p.is_file()]
        for rel in filter_repo_objects(files, allow_patterns=allow_patterns, ignore_patterns=ignore_patterns):
            (dst / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src / rel, dst / rel)
        return SimpleNamespace(repo_url=SimpleNamespace(url=f"https://huggingface.co/{repo_id}"))

    def upload_file(path_or_fileobj, path_in_repo, repo_id, repo_type=None, **kw):
        # as huggingface_hub's: a path (str or Path), bytes or a binary file object
        src = path_or_fileobj
        data = src if isinstance(src, bytes) else src.read() if hasattr(src, "read") else Path(src).read_bytes()
        target = folder(repo_id, repo_type) / path_in_repo
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_bytes(data)

    monkeypatch.setattr(HfApi, "create_repo", create_repo)
    monkeypatch.setattr(HfApi, "upload_folder", upload_folder)
    for name in ("create_branch", "create_tag", "delete_tag"):
        monkeypatch.setattr(HfApi, name, lambda self, *a, **k: None)
    monkeypatch.setattr(repocard, "upload_file", upload_file)
    monkeypatch.setattr(repocard.RepoCard, "validate", lambda self, *a, **k: None)  # a Hub-side service
    monkeypatch.setattr(constants, "HF_HUB_OFFLINE", False)
    return hub


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    tau = np.linspace(0, 1, 40)
    demos = np.stack([np.stack([tau, a * np.sin(np.pi * tau)], 1) for a in (0.3, -0.3, 0.5, -0.5)]).astype(np.float32)
    model = CNMPModel(encoder_layers=(16,), decoder_layers=(16,)).fit(demos, steps=30, batch_size=4, progress=False)
    return model.save(tmp_path_factory.mktemp("ckpt") / "pretrained_model")


def test_dataset_round_trip(fake_hub):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    root = REPO / "datasets" / "cnmp_pickplace"
    url = push_dataset(root, "you/cnmp_pickplace")
    assert url.endswith("datasets/you/cnmp_pickplace")
    pulled = fake_hub / "datasets" / "you" / "cnmp_pickplace"
    back, original = LeRobotDataset("you/cnmp_pickplace", root=pulled), LeRobotDataset("x/y", root=root)
    assert back.num_episodes == original.num_episodes and back.num_frames == original.num_frames
    for i in (0, 437, original.num_frames - 1):
        a, b = original[i], back[i]
        for key in ("action", "observation.state", "observation.task_params"):
            torch.testing.assert_close(a[key], b[key], rtol=0, atol=0)
    card = (pulled / "README.md").read_text()
    assert "LeRobot" in card and "cnmp" in card and "UR10" in card  # LeRobot's card with our description


def test_image_dataset_round_trip(fake_hub, tmp_path):
    """The room's masks (PNG frames in the parquet files) come back from the Hub pixel for pixel."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from lerobot_cnmp.record import record_dataset

    root = record_dataset("cnmp_room", tmp_path / "room", n_episodes=2, seed=3, progress=False)
    push_dataset(root, "you/cnmp_room")
    pulled = fake_hub / "datasets" / "you" / "cnmp_room"
    back, original = LeRobotDataset("you/cnmp_room", root=pulled), LeRobotDataset("x/y", root=root)
    assert back.num_frames == original.num_frames == 200
    for i in (0, 150):
        a, b = original[i], back[i]
        assert a["observation.images.top"].shape == (3, 64, 64)
        for key in ("observation.images.top", "observation.environment_state", "action"):
            torch.testing.assert_close(a[key], b[key], rtol=0, atol=0)
    assert back.meta.features["observation.images.top"]["dtype"] == "image"


def test_checkpoint_round_trip_gives_identical_predictions(fake_hub, checkpoint):
    info = {"overall": {"pc_success": 90.0, "n_episodes": 10}, "per_group": {"cnmp_obstacle2d": {}}}
    url = push_checkpoint(checkpoint, "you/cnmp_toy", eval_info=info)
    assert url.endswith("you/cnmp_toy")
    pulled = fake_hub / "models" / "you" / "cnmp_toy"
    assert {"config.json", "model.safetensors", "README.md"} <= {p.name for p in pulled.iterdir()}
    conds, phases = [Condition(0.0, (0.0, 0.0)), Condition(0.5, (0.5, 0.4))], np.linspace(0, 1, 50)
    mine, theirs = CNMPModel.load(checkpoint).predict(phases, conds), CNMPModel.load(pulled).predict(phases, conds)
    np.testing.assert_array_equal(mine[0], theirs[0])
    np.testing.assert_array_equal(mine[1], theirs[1])
    policy, pre, _ = load_pretrained(pulled)  # the processors and their statistics came along
    assert pre is not None and policy.config.sm_dim == 2
    card = (pulled / "README.md").read_text()
    assert card.startswith("---\n") and "library_name: lerobot" in card and "pc_success 90.0" in card
    assert "lerobot-eval --policy.path=you/cnmp_toy --env.type=cnmp_obstacle2d" in card


def test_offline_push_is_a_clear_error_and_writes_nothing(monkeypatch, checkpoint, tmp_path):
    from huggingface_hub import constants

    monkeypatch.setattr(constants, "HF_HUB_OFFLINE", True)
    before = sorted(p.name for p in Path(checkpoint).iterdir())
    with pytest.raises(HubUnavailableError, match="offline mode"):
        push_checkpoint(checkpoint, "you/cnmp_toy")
    assert sorted(p.name for p in Path(checkpoint).iterdir()) == before  # no card written
    with pytest.raises(HubUnavailableError, match="offline mode"):
        push_dataset(REPO / "datasets" / "cnmp_pickplace", "you/x")
    # the recorder checks before recording: no dataset folder is left behind
    root = tmp_path / "never"
    assert record_main(["--sim", "cnmp_pickplace", "--root", str(root), "--push_to_hub", "--repo_id", "you/x"]) == 1
    assert not root.exists()


def test_repo_id_not_reachable_offline_names_the_problem(monkeypatch):
    from huggingface_hub import constants

    monkeypatch.setattr(constants, "HF_HUB_OFFLINE", True)
    with pytest.raises(FileNotFoundError, match="not a local checkpoint folder.*unreachable"):
        load_pretrained("nobody/no_such_cnmp")


def test_push_needs_a_repo_id_and_a_real_folder(tmp_path):
    with pytest.raises(SystemExit):
        record_main(["--sim", "cnmp_pickplace", "--root", str(tmp_path / "d"), "--push_to_hub"])
    with pytest.raises(FileNotFoundError, match="not a LeRobotDataset"):
        push_dataset(tmp_path, "you/x")

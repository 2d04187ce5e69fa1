"""The Python API's answers to bad input: γ where the model has none (or a re-fit that changes γ), a checkpoint
path that does not exist, and a damaged checkpoint -- each a clear error naming the problem."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from lerobot_cnmp.api import CNMPModel, Condition, load_pretrained
from lerobot_cnmp.policy.checkpoint import CorruptCheckpointError, check_weights_file

TAU = np.linspace(0, 1, 20)
DEMOS = np.stack([np.stack([TAU, a * TAU], 1) for a in (0.3, -0.3, 0.5)]).astype(np.float32)
GAMMA = np.array([[0.3], [-0.3], [0.5]], dtype=np.float32)
SMALL = {"encoder_layers": (8,), "decoder_layers": (8,)}


def fitted(task_params=None) -> CNMPModel:
    return CNMPModel(**SMALL).fit(DEMOS, task_params=task_params, steps=2, batch_size=2, progress=False)


@pytest.fixture(scope="module")
def plain():
    return fitted()


@pytest.fixture(scope="module")
def checkpoint(plain, tmp_path_factory):
    return plain.save(tmp_path_factory.mktemp("ckpt") / "pretrained_model")


def test_gamma_given_to_a_model_without_gamma_is_an_error(plain):
    start = [Condition(0.0, (0.0, 0.0))]
    with pytest.raises(ValueError, match="no task parameters γ .*drop task_params"):
        plain.predict([0.5], start, task_params=[1.0])
    with pytest.raises(ValueError, match="no task parameters γ"):
        plain.predict_mixture([0.5], start, task_params=[1.0])
    plain.predict([0.5], start)  # without γ it predicts


@pytest.mark.parametrize(
    "first, again, match",
    [(None, GAMMA, "fitted without task parameters γ; a re-fit cannot add 1"),
     (GAMMA, None, r"fitted with 1 task parameters γ; give task_params \[N, 1\]"),
     (GAMMA, np.hstack([GAMMA, GAMMA]), "task_params have 2 columns; this model was fitted with 1")],
)
def test_a_refit_keeps_the_gamma_it_was_built_with(first, again, match):
    model = fitted(first)
    with pytest.raises(ValueError, match=match):
        model.fit(DEMOS, task_params=again, steps=1, progress=False)
    model.fit(DEMOS, task_params=first, steps=1, batch_size=2, progress=False)  # the same γ size re-fits


def test_a_missing_local_path_is_named_not_taken_for_a_hub_id(checkpoint):
    typo = checkpoint.parent / "pretrainde_model"
    with pytest.raises(FileNotFoundError, match=f"no checkpoint at {typo}: the folder does not exist .*not a Hub repo id"):
        CNMPModel.load(typo)
    with pytest.raises(FileNotFoundError, match="not a Hub repo id"):
        load_pretrained("outputs/train/nope/pretrained_model")
    # a repo-id-shaped name that is neither a folder nor reachable on the Hub says both
    with pytest.raises(FileNotFoundError, match="not a local checkpoint folder, and as a Hub repo id"):
        CNMPModel.load("you/not_a_folder_here")


@pytest.mark.parametrize("keep", [0, 5, 8, 40, -1])  # bytes kept (-1: all but the last)
def test_a_truncated_weights_file_is_named(checkpoint, tmp_path, keep):
    damaged = tmp_path / "pretrained_model"
    shutil.copytree(checkpoint, damaged)
    weights = damaged / "model.safetensors"
    data = weights.read_bytes()
    weights.write_bytes(data[:keep])
    with pytest.raises(CorruptCheckpointError, match=f"{weights} is truncated or corrupt"):
        CNMPModel.load(damaged)
    with pytest.raises(CorruptCheckpointError, match="truncated or corrupt"):
        check_weights_file(weights)  # what CNMPPolicy / ProMPPolicy._load_as_safetensor run (lerobot-eval's path)


def test_a_whole_weights_file_passes_and_a_damaged_header_is_named(checkpoint, tmp_path):
    weights = checkpoint / "model.safetensors"
    check_weights_file(weights)
    data = bytearray(weights.read_bytes())
    n = int.from_bytes(data[:8], "little")
    data[8 : 8 + n] = b"x" * n  # the header's JSON overwritten
    bad = tmp_path / "model.safetensors"
    bad.write_bytes(bytes(data))
    with pytest.raises(CorruptCheckpointError, match="not a safetensors JSON header"):
        check_weights_file(bad)


def test_a_damaged_config_or_missing_weights_is_named(checkpoint, tmp_path):
    damaged = tmp_path / "pretrained_model"
    shutil.copytree(checkpoint, damaged)
    (damaged / "model.safetensors").unlink()
    with pytest.raises(FileNotFoundError, match="no model.safetensors in"):
        CNMPModel.load(damaged)
    cfg = damaged / "config.json"
    cfg.write_text(json.dumps({"type": "cnmp"})[:7])
    with pytest.raises(ValueError, match=f"{cfg} is not a JSON object"):
        CNMPModel.load(damaged)

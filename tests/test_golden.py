"""Checkpoints recorded before the package's redesign, and for configs added since when they were added
(tests/golden, made by tests/golden/make_golden.py), load with today's code and act identically on their fixed
observation sequence: every committed training config (configs/cnmp_*.json), the mixture and the
image-conditioned one included.

"Identically" is up to float rounding: a BLAS kernel's summation order depends on the CPU it runs on (the
goldens were recorded on one machine, CI runs on another), which moves the last bit of a float32 (relative
1e-7) and, through five Adam steps, a few more. Any change of behaviour (another sampling rule, loss, layer,
normalization or execution step) moves the outputs by orders of magnitude more than TOL allows; the tests
check that in test_golden_tolerance_catches_a_real_change."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from lerobot_cnmp.api import load_pretrained

GOLDEN = Path(__file__).resolve().parent / "golden"
# Acting from the same weights: a few float32 ulps. Training: the losses a few ulps; the weights within a tenth of
# one Adam step (lr 1e-3: Adam divides by the gradient's size, so a weight whose gradient is near zero moves by a
# step-sized amount on a rounding difference; seen up to 2e-5 across two machines, while a sampling rule one
# context point smaller moves the weights by 9e-3).
ACT_TOL = dict(rtol=1e-5, atol=1e-6)
LOSS_TOL = dict(rtol=1e-5, atol=0.0)
WEIGHT_TOL = dict(rtol=0.0, atol=1e-4)
NAMES = sorted(p.name for p in GOLDEN.iterdir() if (p / "config.json").is_file())


def _same_but_data(a: Path, b: Path) -> bool:
    """Two configs that differ only in their dataset and job name (a MetaWorld task made by push's rule)."""
    strip = lambda p: {k: v for k, v in json.loads(p.read_text()).items() if k not in ("dataset", "job_name")}  # noqa: E731
    return strip(a) == strip(b)


def test_every_committed_config_has_a_golden_checkpoint():
    """Every config has a golden checkpoint, except a MetaWorld task's copy of push's config (added after the
    redesign; its network and settings are push's, whose golden checkpoint covers them; a camera config's copy
    is covered by push's camera config)."""
    root = GOLDEN.parents[1] / "configs"

    def push_of(p: Path) -> Path:  # the config a MetaWorld task's config copies: push's (cameras: push's camera one)
        return root / ("cnmp_metaworld_push_cam.json" if p.stem.endswith("_cam") else "cnmp_metaworld_push.json")

    configs = sorted(p.stem for p in root.glob("cnmp_*.json")
                     if p.stem in NAMES or not (p.stem.startswith("cnmp_metaworld_") and _same_but_data(p, push_of(p))))
    assert NAMES == configs


@pytest.mark.parametrize("name", NAMES)
def test_golden_checkpoint_acts_identically(name):
    policy, _, _ = load_pretrained(GOLDEN / name, device="cpu")
    policy.eval()
    rec = np.load(GOLDEN / name / "actions.npz")
    keys = sorted(k[len("obs."):] for k in rec.files if k.startswith("obs."))
    assert keys == sorted(policy.config.input_features)
    obs = [{k: torch.from_numpy(rec[f"obs.{k}"][i]) for k in keys} for i in range(len(rec["select_action"]))]
    torch.manual_seed(1)
    policy.reset()
    steps = np.stack([policy.select_action(dict(o)).numpy() for o in obs])
    np.testing.assert_allclose(steps, rec["select_action"], **ACT_TOL)
    torch.manual_seed(2)
    policy.reset()
    np.testing.assert_allclose(policy.predict_action_chunk(dict(obs[0])).numpy(), rec["chunk"], **ACT_TOL)


def _dataset_root(name: str) -> Path:
    raw = json.loads((GOLDEN.parents[1] / "configs" / f"{name}.json").read_text())
    return GOLDEN.parents[1] / raw["dataset"]["root"]


def _trainable(name: str) -> bool:
    """The golden's training steps can be replayed: its dataset is on disk with the episodes it was recorded on
    (cnmp_room's dataset is not committed; its golden was recorded on an 8-room recording)."""
    info = _dataset_root(name) / "meta" / "info.json"
    if not info.is_file():
        return False
    recorded = int(np.load(GOLDEN / name / "actions.npz")["train_episodes"])
    return json.loads(info.read_text())["total_episodes"] == recorded


TRAINABLE = [n for n in NAMES if _trainable(n)]


@pytest.mark.parametrize("name", TRAINABLE)
def test_golden_training_steps_replay(name):
    """From the recorded initial weights, the same training steps (fixed generator) give the same losses and
    the same weights as the code the goldens were recorded with."""
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata
    from lerobot.policies.factory import make_policy
    from safetensors.torch import load_file

    from golden.make_golden import train_steps

    cfg = PreTrainedConfig.from_pretrained(GOLDEN / name)
    cfg.device = "cpu"
    meta = LeRobotDatasetMetadata(f"lerobot-cnmp/{name}", root=_dataset_root(name))
    policy = make_policy(cfg, ds_meta=meta)
    policy.load_state_dict(load_file(str(GOLDEN / name / "init.safetensors")))
    losses = train_steps(policy, meta.total_episodes)
    np.testing.assert_allclose(np.asarray(losses), np.load(GOLDEN / name / "actions.npz")["losses"], **LOSS_TOL)
    trained = load_file(str(GOLDEN / name / "model.safetensors"))
    state = policy.state_dict()
    assert sorted(state) == sorted(trained)
    for key, value in trained.items():
        torch.testing.assert_close(state[key], value, msg=key, **WEIGHT_TOL)


def test_golden_tolerance_catches_a_real_change():
    """The tolerances are no blanket: a sampling rule one context point smaller moves the losses and the weights
    outside them, and so does a shift of 1e-4 (normalized units) in the decoder's mean output the actions."""
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata
    from lerobot.policies.factory import make_policy
    from safetensors.torch import load_file

    from golden.make_golden import train_steps

    name = "cnmp_obstacle2d"
    cfg = PreTrainedConfig.from_pretrained(GOLDEN / name)
    cfg.device = "cpu"
    cfg.sampling.n_max_context -= 1
    meta = LeRobotDatasetMetadata(f"lerobot-cnmp/{name}", root=_dataset_root(name))
    policy = make_policy(cfg, ds_meta=meta)
    policy.load_state_dict(load_file(str(GOLDEN / name / "init.safetensors")))
    losses = np.asarray(train_steps(policy, meta.total_episodes))
    assert not np.allclose(losses, np.load(GOLDEN / name / "actions.npz")["losses"], **LOSS_TOL)

    policy, _, _ = load_pretrained(GOLDEN / name, device="cpu")
    policy.eval()
    rec = np.load(GOLDEN / name / "actions.npz")
    keys = sorted(k[len("obs."):] for k in rec.files if k.startswith("obs."))
    with torch.no_grad():
        policy.state_dict()["model.decoder.6.bias"][:2] += 1e-4  # the mean half of the Gaussian head
    torch.manual_seed(2)
    policy.reset()
    chunk = policy.predict_action_chunk({k: torch.from_numpy(rec[f"obs.{k}"][0]) for k in keys}).numpy()
    assert not np.allclose(chunk, rec["chunk"], **ACT_TOL)

"""CNMP on a dataset that is not one of our sims: an SO-101 teleop layout (tests/realrobot_data.py) whose
``observation.state`` (6 sensed joints) and ``action`` (7 commands) differ in size, names and meaning, with
episodes of different lengths, a per-episode goal in ``observation.environment_state`` and a video camera.

1. stock ``lerobot-train --policy.type=cnmp`` with no CNMP flag picks the joint SM, γ, fps and duration
   itself, and its checkpoint runs (deterministically, in the dataset's units) after loading;
2. fine-tuning (``--policy.path``) on another dataset keeps the checkpoint's normalization;
3. bad input is a clear error before any training step, and leaves nothing half-written;
4. the bank lerobot-train's policy reads from parquet equals the in-memory API's bank of the same episodes.
"""

from __future__ import annotations

import functools
import json
import os
import re
import subprocess
import sys
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")

import numpy as np
import pytest
import torch

from lerobot.configs import FeatureType, PolicyFeature, PreTrainedConfig
from lerobot.datasets.lerobot_dataset import LeRobotDataset, LeRobotDatasetMetadata
from lerobot.policies.factory import make_policy
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_STATE
from safetensors.torch import load_file

from lerobot_cnmp.api import load_pretrained
from lerobot_cnmp.data.bank import EpisodeBank
from lerobot_cnmp.policy.configuration_cnmp import CNMPConfig, SamplingConfig
from lerobot_cnmp.policy.modeling_cnmp import CNMPPolicy
from realrobot_data import ACTION_NAMES, CAMERA_KEY, FPS, REPO_ID, STATE_NAMES, make_realrobot_dataset

BIN = Path(sys.executable).parent
ENV = {**os.environ, "HF_HUB_OFFLINE": "1", "MUJOCO_GL": "egl"}
TINY = ("--policy.encoder_layers=[32,32]", "--policy.decoder_layers=[32,32]")
NORM_KEYS = ("normalizer.sm_mean", "normalizer.sm_std", "normalizer.task_mean", "normalizer.task_std")


# ---- fixtures: the datasets (built once per module) and one stock training run --------------------------


@pytest.fixture(scope="module")
def root(tmp_path_factory) -> Path:
    """The SO-101 teleop dataset, with its camera as video (seed 0)."""
    return make_realrobot_dataset(tmp_path_factory.mktemp("rr") / "so101", n_episodes=6, seed=0, video=True)


@pytest.fixture(scope="module")
def root2(tmp_path_factory) -> Path:
    """Another dataset in the same layout (other seed: other goals, starts, lengths), camera-less."""
    return make_realrobot_dataset(tmp_path_factory.mktemp("rr2") / "so101", n_episodes=6, seed=5, video=False)


@pytest.fixture(scope="module")
def meta(root) -> LeRobotDatasetMetadata:
    return LeRobotDatasetMetadata(REPO_ID, root=root)


def _lerobot_train(cwd: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [str(BIN / "lerobot-train"), f"--dataset.repo_id={REPO_ID}", "--policy.device=cpu",
         "--policy.push_to_hub=false", "--num_workers=0", *args],
        capture_output=True, text=True, timeout=600, env=ENV, cwd=cwd,
    )


@pytest.fixture(scope="module")
def trained(root, tmp_path_factory):
    """Stock lerobot-train on the video dataset, no CNMP flag: (process, checkpoint folder)."""
    out = tmp_path_factory.mktemp("train")
    proc = _lerobot_train(out, f"--dataset.root={root}", "--policy.type=cnmp", "--steps=20", "--batch_size=4",
                          "--save_freq=20", f"--output_dir={out / 'run'}")
    assert proc.returncode == 0, (proc.stdout[-2000:], proc.stderr[-4000:])
    return proc, out / "run" / "checkpoints" / "last" / "pretrained_model"


@functools.lru_cache(maxsize=4)
def _columns(root: Path) -> dict[str, np.ndarray]:
    """The dataset's numeric columns, in the stored frame order, read through LeRobotDataset (read-only)."""
    ds = LeRobotDataset(REPO_ID, root=root)
    hf = ds.hf_dataset.with_format("numpy")
    keys = (OBS_STATE, ACTION, OBS_ENV_STATE, "episode_index", "frame_index", "timestamp")
    out = {k: np.stack(hf[k]) if hf[k][0].ndim else np.asarray(hf[k]) for k in keys}
    for v in out.values():
        v.setflags(write=False)
    return out


def _raw_obs(root: Path, episode: int = 0, frame: int = 0, state_dims: int = 6) -> dict[str, torch.Tensor]:
    """A raw observation (dataset units) as a robot gives it: a frame's state and the episode's goal."""
    c = _columns(root)
    i = int(np.flatnonzero((c["episode_index"] == episode) & (c["frame_index"] == frame))[0])
    return {
        OBS_STATE: torch.from_numpy(c[OBS_STATE][i, :state_dims].astype(np.float32))[None],
        OBS_ENV_STATE: torch.from_numpy(c[OBS_ENV_STATE][i].astype(np.float32))[None],
    }


def _state_dicts_equal(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


# ---- 1. the real-robot layout through stock lerobot-train ------------------------------------------------


def test_stock_lerobot_train_picks_the_joint_layout(trained, meta):
    proc, ckpt = trained
    log = proc.stdout + proc.stderr
    assert "Could not load libtorchcodec" not in log and "Traceback" not in log, log[-4000:]
    assert (ckpt / "model.safetensors").is_file()
    cfg = json.loads((ckpt / "config.json").read_text())
    assert cfg["type"] == "cnmp"
    assert cfg["sm"] == [f"{OBS_STATE}:{i}" for i in range(6)] + [f"{ACTION}:{i}" for i in range(7)]
    assert cfg["sm_names"] == STATE_NAMES + ACTION_NAMES
    assert cfg["task_features"] == [OBS_ENV_STATE]
    assert cfg["state_tracks_action"] is False and cfg["use_images"] is False
    assert cfg["dataset_fps"] == FPS
    lengths = np.asarray(meta.episodes["length"], dtype=np.float64)
    assert len(set(lengths.tolist())) > 1  # the median is over episodes of different lengths
    assert cfg["demo_duration_s"] == pytest.approx(float(np.median((lengths - 1) / FPS)), rel=1e-6)
    weights = load_file(str(ckpt / "model.safetensors"))
    assert weights["normalizer.sm_mean"].shape == (13,) and weights["normalizer.task_mean"].shape == (3,)
    assert all(bool(torch.isfinite(weights[k]).all()) for k in NORM_KEYS)


def test_checkpoint_loads_deterministically_and_acts_in_dataset_units(trained, root):
    _, ckpt = trained
    p1, pre1, post1 = load_pretrained(ckpt)
    p2, _, _ = load_pretrained(ckpt)
    p3 = CNMPPolicy.from_pretrained(ckpt)
    s1 = p1.state_dict()
    assert _state_dicts_equal(s1, p2.state_dict()) and _state_dicts_equal(s1, p3.state_dict())
    assert p1.config.spec.commanded == list(range(6, 13)) and p1.config.spec.sensed == list(range(6))

    obs = _raw_obs(root)
    for p in (p1, p2, p3):
        p.eval()
        p.reset()
    a1, a2, a3 = (p.select_action(dict(obs)) for p in (p1, p2, p3))
    assert a1.shape == (1, 7) and bool(torch.isfinite(a1).all())
    assert torch.equal(a1, a2) and torch.equal(a1, a3)

    # in the dataset's units: within the recorded actions' range (padded), far from normalized values ~0
    act = torch.from_numpy(_columns(root)[ACTION].astype(np.float32))
    lo, hi = act.min(0).values, act.max(0).values
    pad = (hi - lo) + 1.0
    assert bool(((a1[0] >= lo - pad) & (a1[0] <= hi + pad)).all()), (a1, lo, hi)
    assert float(a1.abs().max()) > 20.0  # joint targets in degrees (e.g. elbow ~90), not z-scores

    # LeRobot's processors pass CNMP's features through: pre -> policy -> post gives the same action
    p1.reset()
    a_proc = post1(p1.select_action(pre1(dict(obs))))
    torch.testing.assert_close(a_proc.cpu(), a1, rtol=0, atol=0)


def test_phase_advances_by_one_over_fps_times_duration(trained, root):
    _, ckpt = trained
    policy = CNMPPolicy.from_pretrained(ckpt)
    policy.eval()
    c = policy.config.execution
    c.phase_stop_threshold = None  # no phase stopping: the phase advances every step
    step = policy.executor.phase_step
    assert step == pytest.approx(1.0 / (FPS * policy.config.demo_duration_s), rel=1e-9)
    obs = _raw_obs(root)
    policy.reset()
    for k in range(6):  # call k + 1 runs at phase k * Δ (the first call runs at 0)
        policy.select_action(dict(obs))
        assert float(policy.executor.phase[0]) == pytest.approx(k * step, rel=1e-5, abs=1e-7)
    c.control_fps = 60
    assert policy.executor.phase_step == pytest.approx(step / 2, rel=1e-9)
    policy.reset()
    for _ in range(4):
        policy.select_action(dict(obs))
    assert float(policy.executor.phase[0]) == pytest.approx(3 * step / 2, rel=1e-5)


# ---- 2. fine-tuning keeps CNMP's normalization -----------------------------------------------------------


def test_finetuning_keeps_the_checkpoint_normalization(trained, root, root2, tmp_path):
    _, ckpt = trained
    proc = _lerobot_train(tmp_path, f"--dataset.root={root2}", f"--policy.path={ckpt}", "--steps=4",
                          "--batch_size=4", "--save_freq=4", f"--output_dir={tmp_path / 'ft'}")
    assert proc.returncode == 0, (proc.stdout[-2000:], proc.stderr[-4000:])
    ft = tmp_path / "ft" / "checkpoints" / "last" / "pretrained_model"
    w0 = load_file(str(ckpt / "model.safetensors"))
    w1 = load_file(str(ft / "model.safetensors"))
    for k in NORM_KEYS:
        assert torch.equal(w0[k], w1[k]), k
    assert any(not torch.equal(w0[k], w1[k]) for k in w0 if not k.startswith("normalizer."))  # it did train

    # what a from-scratch policy on the second dataset normalizes with (the same code lerobot-train runs)
    scratch2 = make_policy(CNMPConfig(device="cpu", encoder_layers=(32, 32), decoder_layers=(32, 32)),
                           ds_meta=LeRobotDatasetMetadata(REPO_ID, root=root2))
    for k in NORM_KEYS:
        assert not torch.allclose(w0[k], scratch2.state_dict()[k]), k  # the datasets' statistics differ

    # one raw observation gets the same normalized context from the original and the fine-tuned model
    original, _, _ = load_pretrained(ckpt)
    finetuned, _, _ = load_pretrained(ft)
    obs = _raw_obs(root2, episode=2, frame=0)
    contexts = []
    for p in (original, finetuned, scratch2):
        p.eval()
        p.reset()
        contexts.append(p.executor.execution_context(dict(obs), torch.zeros(1)))
    a, b, s = contexts
    assert torch.equal(a.values, b.values) and torch.equal(a.phase, b.phase) and torch.equal(a.mask, b.mask)
    assert torch.equal(a.task_params, b.task_params)
    assert torch.equal(original.normalizer.sm(obs[OBS_STATE].new_zeros(1, 13)),
                       finetuned.normalizer.sm(obs[OBS_STATE].new_zeros(1, 13)))
    assert not torch.allclose(a.values, s.values) and not torch.allclose(a.task_params, s.task_params)


# ---- 3. bad input: a clear error before any training step ------------------------------------------------


def _tree(root: Path) -> dict[str, tuple[int, int]]:
    return {str(p.relative_to(root)): (p.stat().st_size, p.stat().st_mtime_ns) for p in root.rglob("*")}


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"sm": ("observation.state:no_such_joint", "action")}, "no_such_joint"),
        ({"sm": ("observation.nope", "action")}, "observation.nope"),
        ({"sm": ("observation.state",)}, "every 'action' dim"),
        ({"sm": ("observation.state:gripper.pos", "action", "action:gripper.force")}, "repeats"),
        ({"task_features": (CAMERA_KEY,)}, "not numeric"),
        ({"task_features": ("observation.goal",)}, "observation.goal"),
        ({"execution": {"feedback_dims": (6,)}}, "must be sensed SM dims"),  # SM dim 6 = action:0, commanded
        ({"execution": {"tracking_dims": (12,)}}, "must be sensed SM dims"),
        ({"state_tracks_action": True}, "state_tracks_action=True"),  # 6 state dims cannot measure 7 actions
        ({"sm": ("observation.state", "action:0@observation.environment_state:goal_x", "action")}, "task frame"),
        ({"sm": ("observation.state:0@observation.environment_state:nope", "action")}, "'nope'"),
        ({"sm": ("observation.state@observation.environment_state:goal_x", "action")}, "one dim with one dim"),
        ({"sm": ("observation.state:0@observation.environment_state:goal_x", "action"), "task_features": ()},
         "not among the task features"),
    ],
)
def test_bad_declarations_are_clear_errors(root, meta, overrides, message):
    before = _tree(root)
    cfg = CNMPConfig(device="cpu", encoder_layers=(32, 32), decoder_layers=(32, 32), **overrides)
    with pytest.raises(ValueError, match=re.escape(message)):
        make_policy(cfg, ds_meta=meta)
    assert cfg.demo_duration_s is None and cfg.dataset_fps is None  # nothing derived from a half-built policy
    assert _tree(root) == before  # nothing written into the dataset


def test_bad_sm_in_lerobot_train_fails_before_training(root, tmp_path):
    proc = _lerobot_train(tmp_path, f"--dataset.root={root}", "--policy.type=cnmp", *TINY,
                          '--policy.sm=["observation.state:no_such_joint","action"]', "--steps=2", "--batch_size=2",
                          f"--output_dir={tmp_path / 'run'}")
    assert proc.returncode != 0
    log = proc.stdout + proc.stderr
    assert "no_such_joint" in log and "ValueError" in log, log[-3000:]
    assert "Start offline training" not in log
    assert not (tmp_path / "run" / "checkpoints").exists()


TINY_FEATURES = {
    OBS_STATE: {"dtype": "float32", "shape": (2,), "names": ["j0.pos", "j1.pos"]},
    ACTION: {"dtype": "float32", "shape": (2,), "names": ["j0.target", "j1.target"]},
}


def _tiny_dataset(root: Path, lengths: list[int], nan_at: tuple[int, int] | None = None) -> Path:
    """A small low-dim dataset written with LeRobot's writer; ``nan_at=(episode, frame)`` puts NaN in the
    action's second dim there (patched into the parquet afterwards, as a corrupt recording would hold it)."""
    ds = LeRobotDataset.create(repo_id="local/tiny", fps=10, features=TINY_FEATURES, root=root, use_videos=False)
    rng = np.random.default_rng(0)
    for n in lengths:
        for _ in range(n):
            ds.add_frame({OBS_STATE: rng.normal(size=2).astype(np.float32),
                          ACTION: rng.normal(size=2).astype(np.float32), "task": "move"})
        ds.save_episode()
    ds.finalize()
    if nan_at is not None:
        import pyarrow as pa
        import pyarrow.parquet as pq

        for f in sorted((root / "data").glob("**/*.parquet")):
            t = pq.read_table(f)
            ep = t.column("episode_index").to_numpy()
            fr = t.column("frame_index").to_numpy()
            hit = (ep == nan_at[0]) & (fr == nan_at[1])
            if not hit.any():
                continue
            act = np.stack(t.column(ACTION).to_numpy(zero_copy_only=False)).astype(np.float32)
            act[hit, 1] = np.nan
            col = pa.FixedSizeListArray.from_arrays(pa.array(act.reshape(-1)), 2) \
                if pa.types.is_fixed_size_list(t.schema.field(ACTION).type) else pa.array(list(act))
            t = t.set_column(t.schema.get_field_index(ACTION), t.schema.field(ACTION), col.cast(t.schema.field(ACTION).type))
            pq.write_table(t, f)
    return root


def test_an_episode_of_one_frame_is_a_clear_error(tmp_path):
    root = _tiny_dataset(tmp_path / "tiny", [5, 1, 4])
    cfg = CNMPConfig(device="cpu", encoder_layers=(32, 32), decoder_layers=(32, 32))
    with pytest.raises(ValueError, match=r"episode\(s\) \[1\] have fewer than 2 frames"):
        make_policy(cfg, ds_meta=LeRobotDatasetMetadata("local/tiny", root=root))
    assert cfg.demo_duration_s is None


def test_nan_in_an_sm_column_names_feature_episode_and_frame(tmp_path):
    root = _tiny_dataset(tmp_path / "tiny", [5, 6, 4], nan_at=(1, 3))
    cfg = CNMPConfig(device="cpu", encoder_layers=(32, 32), decoder_layers=(32, 32))
    with pytest.raises(ValueError, match=r"'action' \(dim 'j1.target'\).*episode 1, frame 3"):
        make_policy(cfg, ds_meta=LeRobotDatasetMetadata("local/tiny", root=root))
    assert cfg.demo_duration_s is None


def test_checkpoint_on_a_robot_with_fewer_state_dims_is_a_clear_error(trained, root):
    _, ckpt = trained
    # the env/robot declares 5 state dims: building the policy for it fails on the SM's dim 5
    cfg = PreTrainedConfig.from_pretrained(ckpt)
    cfg.input_features[OBS_STATE] = PolicyFeature(type=FeatureType.STATE, shape=(5,))
    with pytest.raises(ValueError, match=r"observation\.state"):
        CNMPPolicy.from_pretrained(ckpt, config=cfg)
    # the right robot's policy given a 5-dim observation at run time
    policy, _, _ = load_pretrained(ckpt)
    policy.eval()
    policy.reset()
    with pytest.raises(ValueError, match=r"'observation\.state' has 5 dims, but this checkpoint was trained on 6"):
        policy.select_action(_raw_obs(root, state_dims=5))
    # nothing half-written: the next, valid observation is the episode's first step
    fresh, _, _ = load_pretrained(ckpt)
    fresh.eval()
    fresh.reset()
    assert torch.equal(policy.select_action(_raw_obs(root)), fresh.select_action(_raw_obs(root)))
    # a γ of the wrong size is an error too
    policy.reset()
    bad = {**_raw_obs(root), OBS_ENV_STATE: torch.zeros(1, 2)}
    with pytest.raises(ValueError, match="observation.environment_state"):
        policy.select_action(bad)


# ---- 4. one sampler for both paths -----------------------------------------------------------------------


def test_policy_bank_equals_the_api_bank_of_the_same_episodes(root, meta):
    policy = make_policy(CNMPConfig(device="cpu", encoder_layers=(32, 32), decoder_layers=(32, 32)), ds_meta=meta)
    bank = policy.bank
    c = _columns(root)
    demos, gamma = [], []
    for ep in range(meta.total_episodes):
        m = c["episode_index"] == ep
        order = np.argsort(c["frame_index"][m])
        demos.append(np.concatenate([c[OBS_STATE][m], c[ACTION][m]], axis=1)[order].astype(np.float32))
        gamma.append(c[OBS_ENV_STATE][m][order][0])
    api = EpisodeBank.from_arrays(demos, np.stack(gamma).astype(np.float32), fps=FPS)

    assert bank.n_episodes == api.n_episodes == 6
    np.testing.assert_array_equal(bank.episode_ids, api.episode_ids)
    assert torch.equal(bank.lengths, api.lengths) and torch.equal(bank.starts, api.starts)
    torch.testing.assert_close(bank.values, api.values, rtol=0, atol=0)
    torch.testing.assert_close(bank.phase, api.phase, rtol=0, atol=1e-5)  # timestamps vs j / (T - 1)
    torch.testing.assert_close(bank.task_params, api.task_params, rtol=0, atol=0)
    np.testing.assert_allclose(bank.durations_s, api.durations_s, rtol=1e-6)
    for x, y in zip(bank.sm_stats(), api.sm_stats(), strict=True):
        np.testing.assert_allclose(x, y, rtol=1e-6)
    for x, y in zip(bank.task_stats(), api.task_stats(), strict=True):
        np.testing.assert_allclose(x, y, rtol=1e-6)
    # the policy normalizes with these statistics
    np.testing.assert_allclose(policy.normalizer.sm_mean.numpy(), api.sm_stats()[0], rtol=1e-6)
    assert policy.config.demo_duration_s == pytest.approx(api.median_duration_s(), rel=1e-6)

    # the same draw from both banks for the same generator state
    eps = torch.tensor([0, 3, 5, 3, 1])
    d1 = bank.draw(eps, 12, torch.Generator().manual_seed(4))
    d2 = api.draw(eps, 12, torch.Generator().manual_seed(4))
    torch.testing.assert_close(d1[0], d2[0], rtol=0, atol=0)
    torch.testing.assert_close(d1[1], d2[1], rtol=0, atol=1e-5)
    torch.testing.assert_close(bank.task_params_of(eps), api.task_params_of(eps), rtol=0, atol=0)
    assert list(policy.config.sm_names) == STATE_NAMES + ACTION_NAMES

    # training needs only the episode ids: the draw comes from the bank
    loss, info = policy.forward({"episode_index": torch.tensor([0, 2, 5, 5])})
    assert loss.ndim == 0 and bool(torch.isfinite(loss))
    loss.backward()


def test_sm_declared_by_dim_names_resolves_to_canonical_indices(root, meta):
    """A subset of the state by name, action first: canonical "feature:index" entries, the bank's columns in
    the declared order, and execution reads the one sensed dim and outputs the 7 action dims."""
    cfg = CNMPConfig(device="cpu", encoder_layers=(32, 32), decoder_layers=(32, 32),
                     sm=("action", "observation.state:gripper.pos", "observation.state:0"))
    policy = make_policy(cfg, ds_meta=meta)
    assert cfg.sm == tuple(f"{ACTION}:{i}" for i in range(7)) + (f"{OBS_STATE}:5", f"{OBS_STATE}:0")
    assert list(cfg.sm_names) == ACTION_NAMES + ["gripper.pos", "shoulder_pan.pos"]
    assert cfg.spec.commanded == list(range(7)) and cfg.spec.sensed == [7, 8]
    c = _columns(root)
    expect = np.concatenate([c[ACTION], c[OBS_STATE][:, [5, 0]]], axis=1).astype(np.float32)
    order = np.lexsort((c["frame_index"], c["episode_index"]))
    np.testing.assert_array_equal(policy.bank.values.numpy(), expect[order])
    policy.eval()
    policy.reset()
    obs = _raw_obs(root)
    sensed = policy.executor.sensed_sm(obs)
    expected = (torch.tensor([float(obs[OBS_STATE][0, 5]), float(obs[OBS_STATE][0, 0])]) - policy.normalizer.sm_mean[7:]) \
        / policy.normalizer.sm_std[7:]
    torch.testing.assert_close(sensed[0, 7:], expected)
    assert bool((sensed[0, :7] == 0).all())
    assert policy.select_action(obs).shape == (1, 7)


def test_task_frame_dims_subtract_the_episode_gamma_in_training_and_execution(root, meta):
    """``"observation.state:0@observation.environment_state:goal_x"``: the bank holds the state dim minus the
    episode's first-frame γ dim; execution subtracts the γ read at the episode's first step, and keeps it for
    the episode even when the live γ changes."""
    entry = f"{OBS_STATE}:shoulder_pan.pos@{OBS_ENV_STATE}:goal_x"
    cfg = CNMPConfig(device="cpu", encoder_layers=(32, 32), decoder_layers=(32, 32), sm=(OBS_STATE, entry, ACTION))
    policy = make_policy(cfg, ds_meta=meta)
    assert cfg.sm[6] == f"{OBS_STATE}:0@{OBS_ENV_STATE}:0" and cfg.sm_names[6] == "shoulder_pan.pos-goal_x"
    assert cfg.spec.sensed == list(range(7)) and cfg.spec.commanded == list(range(7, 14))
    c = _columns(root)
    order = np.lexsort((c["frame_index"], c["episode_index"]))
    ep = c["episode_index"][order]
    first = {int(e): c[OBS_ENV_STATE][order][np.flatnonzero(ep == e)[0], 0] for e in np.unique(ep)}
    expect = c[OBS_STATE][order][:, 0].astype(np.float64) - np.array([first[int(e)] for e in ep])
    np.testing.assert_allclose(policy.bank.values[:, 6].numpy(), expect, rtol=1e-6, atol=1e-6)  # float32 storage
    np.testing.assert_array_equal(policy.bank.values[:, :6].numpy(), c[OBS_STATE][order])

    policy.eval()
    policy.reset()
    obs = _raw_obs(root)
    norm = policy.normalizer
    want = (obs[OBS_STATE][0, 0] - obs[OBS_ENV_STATE][0, 0] - norm.sm_mean[6]) / norm.sm_std[6]
    torch.testing.assert_close(policy.executor.sensed_sm(obs)[0, 6], want)
    policy.select_action(obs)
    moved = {**obs, OBS_ENV_STATE: obs[OBS_ENV_STATE] + 1.0}  # γ is the episode's first reading
    torch.testing.assert_close(policy.executor.sensed_sm(moved)[0, 6], want)
    policy.reset()  # a new episode reads γ again
    want2 = (obs[OBS_STATE][0, 0] - moved[OBS_ENV_STATE][0, 0] - norm.sm_mean[6]) / norm.sm_std[6]
    torch.testing.assert_close(policy.executor.sensed_sm(moved)[0, 6], want2)
    assert policy.select_action(moved).shape == (1, 7)


# ---- training options for reactive demonstrators: execution-shaped draws, β-NLL --------------------------


def test_feedback_draws_have_the_shape_of_execution(root, meta):
    cfg = CNMPConfig(device="cpu", encoder_layers=(32, 32), decoder_layers=(32, 32), sampling=SamplingConfig(
        feedback_draw_weight=0.5, draws_per_sample=3, m_max_targets=4))
    policy = make_policy(cfg, ds_meta=meta)
    gen = torch.Generator().manual_seed(0)
    eps = torch.tensor([0, 3])
    context, targets = policy.feedback_draws(eps, gen)
    assert context.phase.shape == (6, 2) and targets.phase.shape == (6, 2 + 4)
    assert torch.equal(context.phase[:, 0], torch.zeros(6))  # the start, as condition_on_start gives it
    assert torch.equal(targets.phase[:, 0], context.phase[:, 1])  # the query "now" is the sensed point's phase
    step = targets.phase[:, 1] - targets.phase[:, 0]  # "next": one frame later (or the last frame itself)
    lengths = policy.bank.lengths[policy.bank.rows(eps.repeat_interleave(3))].float()
    last = targets.phase[:, 0] == 1
    assert torch.all(torch.where(last, step.abs(), (step - 1 / (lengths - 1)).abs()) < 1e-5)
    sensed = torch.zeros(cfg.sm_dim)
    sensed[cfg.spec.sensed] = 1
    assert torch.equal(context.mask, sensed.expand_as(context.mask))  # the sensed dims only, never an action
    assert torch.allclose(context.values[:, 1], targets.values[:, 0])
    assert torch.allclose(context.task_params, policy.normalizer.task(policy.bank.task_params_of(eps)).repeat_interleave(3, 0))
    loss, info = policy.forward({"episode_index": eps}, generator=torch.Generator().manual_seed(1))
    assert torch.isfinite(loss) and {"nll_random", "nll_feedback"} <= set(info)
    assert abs(info["nll"] - (0.5 * info["nll_random"] + 0.5 * info["nll_feedback"])) < 1e-4
    loss.backward()  # both parts reach the weights


def test_feedback_draw_queries_sets_the_uniform_queries(root, meta):
    # None (default): m_max_targets uniform queries besides j and j + 1; 0: exactly execution's two queries
    kw = dict(device="cpu", encoder_layers=(32, 32), decoder_layers=(32, 32), execution={"condition_on_start": False})
    sampling = dict(feedback_draw_weight=1.0, draws_per_sample=2, m_max_targets=4)
    eps = torch.tensor([1, 2])
    for queries, n_targets in ((None, 2 + 4), (0, 2), (3, 2 + 3)):
        policy = make_policy(CNMPConfig(**kw, sampling=SamplingConfig(**sampling, feedback_draw_queries=queries)), ds_meta=meta)
        context, targets = policy.feedback_draws(eps, torch.Generator().manual_seed(0))
        assert context.phase.shape == (4, 1) and targets.phase.shape == (4, n_targets)
        assert torch.equal(targets.phase[:, 0], context.phase[:, 0])  # "now" is the sensed point's phase
        loss, info = policy.forward({"episode_index": eps}, generator=torch.Generator().manual_seed(1))
        assert torch.isfinite(loss) and abs(info["nll"] - info["nll_feedback"]) < 1e-4  # weight 1: feedback only
    for bad in (-1, 1.5):
        with pytest.raises(ValueError, match="feedback_draw_queries must be an integer >= 0"):
            SamplingConfig(feedback_draw_queries=bad)


def test_feedback_draws_need_sensed_dims_and_a_weight_in_0_1(meta):
    with pytest.raises(ValueError, match="feedback_draw_weight must be in"):
        SamplingConfig(feedback_draw_weight=1.5)
    with pytest.raises(ValueError, match="nll_beta must be in"):
        CNMPConfig(nll_beta=-0.1)
    cfg = CNMPConfig(device="cpu", encoder_layers=(32, 32), decoder_layers=(32, 32), sm=("action",),
                     sampling=SamplingConfig(feedback_draw_weight=0.5))
    with pytest.raises(ValueError, match="feedback_draw_weight > 0 needs the joint layout with sensed dims"):
        make_policy(cfg, ds_meta=meta)


def test_beta_nll_weights_each_dim_by_the_detached_variance():
    from lerobot_cnmp.model.cnmp import CNMP, Targets

    g = torch.Generator().manual_seed(0)
    mean = torch.randn(2, 5, 3, generator=g, requires_grad=True)
    raw_std = torch.rand(2, 5, 3, generator=g) + 0.2
    std = raw_std.clone().requires_grad_(True)
    targets = Targets(torch.rand(2, 5, generator=g), torch.randn(2, 5, 3, generator=g), torch.ones(2, 5, dtype=torch.bool))
    plain = CNMP.nll(mean, std, targets)
    assert torch.equal(plain, CNMP.nll(mean, std, targets, beta=0.0))
    per_dim = 0.5 * ((targets.values - mean) / std) ** 2 + std.log() + 0.5 * np.log(2 * np.pi)
    assert torch.allclose(plain, per_dim.sum(-1).mean())
    beta1 = CNMP.nll(mean, std, targets, beta=1.0)
    assert torch.allclose(beta1, (per_dim * raw_std ** 2).sum(-1).mean())
    (grad_mean,) = torch.autograd.grad(beta1, mean)
    # β = 1: the mean's gradient is the squared error's, whatever σ (the plain NLL's is scaled by 1/σ²)
    assert torch.allclose(grad_mean, (mean - targets.values).detach() / 10)
    (grad_plain,) = torch.autograd.grad(plain, mean)
    assert not torch.allclose(grad_plain, grad_mean)


def test_commanded_loss_weight_scales_the_action_dims_terms(meta):
    from lerobot_cnmp.model.cnmp import CNMP, Targets

    with pytest.raises(ValueError, match="commanded_loss_weight must be > 0"):
        CNMPConfig(commanded_loss_weight=0.0)
    with pytest.raises(ValueError, match="commanded_loss_weight applies to the single decoder"):
        CNMPConfig(commanded_loss_weight=2.0, n_experts=2)
    cfg = CNMPConfig(device="cpu", encoder_layers=(32, 32), decoder_layers=(32, 32), commanded_loss_weight=4.0)
    policy = make_policy(cfg, ds_meta=meta)
    spec = policy.config.spec
    w = policy.model.dim_weights
    assert w is not None and w.shape == (spec.size,)
    assert torch.all(w[spec.commanded] == 4.0) and torch.all(w[spec.sensed] == 1.0)
    assert make_policy(CNMPConfig(device="cpu", encoder_layers=(32, 32), decoder_layers=(32, 32)),
                       ds_meta=meta).model.dim_weights is None  # default: Eq. 1 as in the paper
    g = torch.Generator().manual_seed(0)
    mean, std = torch.randn(2, 5, spec.size, generator=g), torch.rand(2, 5, spec.size, generator=g) + 0.2
    targets = Targets(torch.rand(2, 5, generator=g), torch.randn(2, 5, spec.size, generator=g),
                      torch.ones(2, 5, dtype=torch.bool))
    per_dim = 0.5 * ((targets.values - mean) / std) ** 2 + std.log() + 0.5 * np.log(2 * np.pi)
    assert torch.allclose(CNMP.nll(mean, std, targets, dim_weights=w), (per_dim * w).sum(-1).mean())
    assert not torch.allclose(CNMP.nll(mean, std, targets, dim_weights=w), CNMP.nll(mean, std, targets))

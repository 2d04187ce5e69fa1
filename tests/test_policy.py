"""CNMPPolicy with LeRobot: stock batches, processors, execution state, checkpoints, plugin, CLI."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from lerobot.configs import FeatureType, PolicyFeature
from lerobot.datasets.lerobot_dataset import LeRobotDataset, LeRobotDatasetMetadata
from lerobot.policies.factory import make_policy, make_pre_post_processors
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_STATE

from lerobot_cnmp.api import load_pretrained, sm_stats
from lerobot_cnmp.execution.conditions import Condition, encode_conditions
from lerobot_cnmp.policy.configuration_cnmp import CNMPConfig
from lerobot_cnmp.execution.config import ExecutionConfig
from lerobot_cnmp.policy.modeling_cnmp import CNMPPolicy
from lerobot_cnmp.policy.processor_cnmp import make_cnmp_pre_post_processors

REPO = Path(__file__).resolve().parents[1]
DATASET = REPO / "datasets" / "cnmp_obstacle2d"
REPO_ID = "lerobot-cnmp/cnmp_obstacle2d"
BIN = Path(sys.executable).parent


@pytest.fixture(scope="module")
def meta():
    return LeRobotDatasetMetadata(REPO_ID, root=DATASET)


def small_config(**kw) -> CNMPConfig:
    kw.setdefault("state_tracks_action", True)
    return CNMPConfig(device="cpu", encoder_layers=(32, 32), decoder_layers=(32, 32), **kw)


@pytest.fixture(scope="module")
def policy_and_data(meta):
    cfg = small_config()
    policy = make_policy(cfg, ds_meta=meta)
    ds = LeRobotDataset(REPO_ID, root=DATASET, delta_timestamps=None)
    assert cfg.action_delta_indices is None  # one frame per sample: its episode id
    return policy, ds


def test_dataset_has_declared_features(meta):
    assert meta.total_episodes == 64
    assert meta.features[ACTION]["shape"] == (2,) and meta.features[OBS_STATE]["shape"] == (2,)
    assert meta.features[OBS_ENV_STATE]["shape"] == (24,)
    assert set(np.asarray(meta.episodes["length"]).tolist()) == {200}
    assert (DATASET / "README.md").is_file()


def test_stock_batch_draws_from_the_whole_episode(policy_and_data):
    """A lerobot-train batch names episodes; each item's observations and queries come from its whole episode."""
    policy, ds = policy_and_data
    items = [ds[i] for i in (0, 57, 199, 200, 12799)]
    batch = torch.utils.data.default_collate(items)
    gen = torch.Generator().manual_seed(0)
    episodes = policy.episodes_for(batch["episode_index"].repeat_interleave(40), gen)
    phases = episodes.phase.reshape(5, -1)
    assert float(phases.min()) < 0.05 and float(phases.max()) > 0.95  # not a window around the anchor
    bank = policy.bank
    rows = bank.rows(batch["episode_index"])
    raw = policy.normalizer.sm_inverse(episodes.values.reshape(5, -1, 2))
    for b, row in enumerate(rows.tolist()):  # every drawn point is a frame of that item's episode
        frames = bank.values[int(bank.starts[row]): int(bank.starts[row]) + 200]
        d = (raw[b][:, None, :] - frames[None]).abs().amax(-1).amin(-1)
        assert float(d.max()) < 1e-4
    loss, info = policy.forward(batch)
    assert loss.ndim == 0 and torch.isfinite(loss) and {"nll", "mae", "std"} <= set(info)
    loss.backward()


def test_forward_rejects_bad_batches(policy_and_data):
    policy, ds = policy_and_data
    batch = torch.utils.data.default_collate([ds[3], ds[4]])
    with pytest.raises(KeyError, match="episode_index"):
        policy.forward({k: v for k, v in batch.items() if k != "episode_index"})
    with pytest.raises(KeyError, match="not in the CNMP's demonstrations"):
        policy.forward({**batch, "episode_index": torch.tensor([3, 999])})
    orphan = CNMPPolicy(policy.config)  # no demonstrations in memory
    with pytest.raises(RuntimeError, match="in memory"):
        orphan.forward(batch)


def test_dataset_missing_task_params_is_rejected(meta):
    with pytest.raises(ValueError, match="observation.task_params"):
        make_policy(small_config(use_task_params=True), ds_meta=meta)


def test_sm_inputs_share_the_sm_statistics(policy_and_data):
    """Sensed state and condition values are normalized by the policy with the demos' SM statistics (saved with
    its weights); LeRobot's processors pass them through and the action comes back in the data's units."""
    policy, _ = policy_and_data
    mean, std = policy.bank.sm_stats()
    np.testing.assert_allclose(policy.normalizer.sm_mean.numpy(), mean)
    pre, post = make_cnmp_pre_post_processors(policy.config)
    cond = encode_conditions([Condition(0.5, (0.5, 0.4)), Condition(1.0, (np.nan, 0.1), dims=(1,))], 2, 4)
    obs = {OBS_STATE: torch.tensor([0.2, -0.1]), OBS_ENV_STATE: torch.from_numpy(cond)}
    out = pre(obs)
    torch.testing.assert_close(out[OBS_STATE][0], obs[OBS_STATE])  # identity
    policy.reset()
    ctx = policy.executor.execution_context(out, torch.zeros(1))
    torch.testing.assert_close(ctx.values[0, 0], torch.from_numpy((np.array([0.5, 0.4]) - mean) / std).float())
    assert float(ctx.values[0, 1, 0]) == 0.0 and float(ctx.values[0, 1, 1]) == pytest.approx((0.1 - mean[1]) / std[1])
    start = policy.config.env_condition_slots
    torch.testing.assert_close(ctx.values[0, start], torch.from_numpy((np.array([0.2, -0.1]) - mean) / std).float())
    action = post(torch.tensor([[0.3, 0.7]]))
    torch.testing.assert_close(action, torch.tensor([[0.3, 0.7]]))


def _obs(n_envs: int, seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    cond = np.stack([encode_conditions([Condition(0.5, (0.5, float(rng.uniform(-1, 1))))], 2, 4) for _ in range(n_envs)])
    return {OBS_STATE: torch.from_numpy(rng.normal(size=(n_envs, 2)).astype(np.float32)),
            OBS_ENV_STATE: torch.from_numpy(cond)}


def test_select_action_phase_per_env_and_reset(policy_and_data):
    policy, _ = policy_and_data
    policy.eval()
    policy.config.execution.phase_stop_threshold = None  # random states: no tracking to judge here
    try:
        policy.reset()
        step = 1 / 199
        assert policy.config.demo_duration_s == pytest.approx(199 / 50) and policy.config.dataset_fps == 50
        assert policy.executor.phase_step == pytest.approx(step)  # derived from the dataset's timestamps
        a = policy.select_action(_obs(3))
        assert a.shape == (3, 2) and torch.isfinite(a).all()
        torch.testing.assert_close(policy.executor.phase, torch.zeros(3))  # the first step is at t = 0
        for _ in range(9):
            policy.select_action(_obs(3))
        torch.testing.assert_close(policy.executor.phase, torch.full((3,), 9 * step))
        policy.reset()
        policy.select_action(_obs(3))
        torch.testing.assert_close(policy.executor.phase, torch.zeros(3))
        # Each env of a batch is conditioned on its own observation: env 1 alone gives env 1's action.
        policy.reset()
        many = policy.select_action(_obs(3, seed=5))
        policy.reset()
        obs = _obs(3, seed=5)
        one = policy.select_action({k: v[1:2] for k, v in obs.items()})
        torch.testing.assert_close(many[1:2], one)
        # The phase saturates at 1.
        for _ in range(250):
            policy.select_action(_obs(3))
        assert float(policy.executor.phase.max()) == 1.0
    finally:
        policy.config.execution.phase_stop_threshold = ExecutionConfig.phase_stop_threshold


@pytest.mark.parametrize(
    "mutate, err, match",
    [
        (lambda o: {**o, OBS_ENV_STATE: o[OBS_ENV_STATE][:, :23]}, ValueError, "multiple of the slot size"),
        (lambda o: {**o, OBS_STATE: torch.full_like(o[OBS_STATE], float("nan"))}, ValueError, "NaN"),
        (lambda o: {**o, OBS_STATE: o[OBS_STATE][:, :1]}, ValueError, "dims"),
        (lambda o: {OBS_ENV_STATE: o[OBS_ENV_STATE]}, KeyError, "observation.state"),
    ],
)
def test_select_action_bad_inputs(policy_and_data, mutate, err, match):
    policy, _ = policy_and_data
    policy.reset()
    with pytest.raises(err, match=match):
        policy.select_action(mutate(_obs(2)))


def test_condition_phase_outside_range_is_rejected(policy_and_data):
    policy, _ = policy_and_data
    obs = _obs(1)
    env = obs[OBS_ENV_STATE].clone()
    env[0, 1] = 1.5
    policy.reset()
    with pytest.raises(ValueError, match="outside"):
        policy.select_action({**obs, OBS_ENV_STATE: env})


def test_empty_context_is_rejected(policy_and_data):
    policy, _ = policy_and_data
    policy.config.execution.online_feedback = policy.config.execution.condition_on_start = False
    try:
        policy.reset()
        with pytest.raises(ValueError, match="empty context"):
            policy.select_action({**_obs(1), OBS_ENV_STATE: torch.zeros(1, 24)})
    finally:
        policy.config.execution.online_feedback = policy.config.execution.condition_on_start = True


def test_programmatic_loading_restores_the_normalization(policy_and_data, meta, tmp_path):
    """The SM statistics travel in the weights: load_pretrained and a config-only rebuild (LeRobot's
    pretrained_path=None trap) both execute bit-identically to the trained policy."""
    policy, _ = policy_and_data
    pre, post = make_pre_post_processors(policy.config, dataset_stats=meta.stats)
    ckpt = tmp_path / "pretrained_model"
    policy.save_pretrained(ckpt)
    pre.save_pretrained(ckpt)
    post.save_pretrained(ckpt)

    from lerobot.configs.policies import PreTrainedConfig

    naive_cfg = PreTrainedConfig.from_pretrained(ckpt)
    assert naive_cfg.pretrained_path is None
    naive_pre, naive_post = make_pre_post_processors(naive_cfg)
    loaded, lpre, lpost = load_pretrained(ckpt)
    np.testing.assert_array_equal(sm_stats(loaded)["sm"]["mean"], sm_stats(policy)["sm"]["mean"])
    obs = _obs(2, seed=3)
    policy.eval()
    want = []
    for p, pr, po in ((policy, pre, post), (loaded, lpre, lpost), (CNMPPolicy.from_pretrained(ckpt), naive_pre, naive_post)):
        p.eval()
        p.reset()
        want.append(po(p.select_action(pr(dict(obs)))))
    assert torch.equal(want[0], want[1]) and torch.equal(want[0], want[2])  # bit-identical


def test_plugin_discovery_in_fresh_process():
    code = (
        "from lerobot.utils.import_utils import register_third_party_plugins\n"
        "register_third_party_plugins()\n"
        "from lerobot.configs.policies import PreTrainedConfig\n"
        "from lerobot.envs.configs import EnvConfig\n"
        "from lerobot.policies.factory import get_policy_class\n"
        "print(get_policy_class('cnmp').__name__, 'cnmp_obstacle2d' in EnvConfig.get_known_choices())\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                         env={**os.environ, "HF_HUB_OFFLINE": "1"})
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.strip().splitlines()[-1] == "CNMPPolicy True"


def _train_then_eval(tmp_path, config: str, dataset: Path, train_args: list[str], eval_args: list[str]) -> Path:
    """lerobot-train with ``configs/<config>`` on ``dataset`` (a few steps), then lerobot-eval of its checkpoint;
    returns the checkpoint folder. Both CLIs run as subprocesses, as a user runs them."""
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "MUJOCO_GL": "egl"}
    train = subprocess.run(
        [str(BIN / "lerobot-train"), f"--config_path={REPO / 'configs' / config}", f"--dataset.root={dataset}",
         "--num_workers=0", "--policy.device=cpu", f"--output_dir={tmp_path / 'train'}", *train_args],
        capture_output=True, text=True, timeout=600, env=env, cwd=tmp_path,
    )
    assert train.returncode == 0, train.stderr[-4000:]
    ckpt = tmp_path / "train" / "checkpoints" / "last" / "pretrained_model"
    assert (ckpt / "model.safetensors").is_file() and (ckpt / "config.json").is_file()
    ev = subprocess.run(
        [str(BIN / "lerobot-eval"), f"--policy.path={ckpt}", "--policy.device=cpu",
         f"--output_dir={tmp_path / 'eval'}", *eval_args],
        capture_output=True, text=True, timeout=600, env=env, cwd=tmp_path,
    )
    assert ev.returncode == 0, ev.stderr[-4000:]
    assert "pc_success" in (tmp_path / "eval" / "eval_info.json").read_text()
    return ckpt


def test_lerobot_train_then_eval_smoke(tmp_path):
    """A few steps of the stock CLI: lerobot-train on the committed dataset, then lerobot-eval on the sim."""
    ckpt = _train_then_eval(
        tmp_path, "cnmp_obstacle2d.json", DATASET,
        ["--steps=10", "--batch_size=4", "--save_freq=10", "--log_freq=5"],
        ["--env.type=cnmp_obstacle2d", "--eval.n_episodes=2", "--eval.batch_size=2"],
    )
    cfg = json.loads((ckpt / "config.json").read_text())
    assert cfg["demo_duration_s"] == pytest.approx(199 / 50) and cfg["dataset_fps"] == 50
    assert cfg["sm"] == ["action:0", "action:1"] and cfg["sm_names"] == ["x", "y"]


def test_image_cnmp_through_lerobot_train_and_eval(tmp_path):
    """The image path of the stock CLI: a few room demos recorded with their masks, lerobot-train with
    configs/cnmp_room.json (conv encoder), lerobot-eval on cnmp_room with the via-point condition."""
    from lerobot_cnmp.record import record_dataset

    root = record_dataset("cnmp_room", tmp_path / "room", n_episodes=3, seed=7, progress=False)
    ckpt = _train_then_eval(
        tmp_path, "cnmp_room.json", root,
        ["--steps=4", "--batch_size=2", "--save_freq=4", "--log_freq=2"],
        ["--env.type=cnmp_room", "--env.condition=via", "--eval.n_episodes=1", "--eval.batch_size=1"],
    )
    cfg = json.loads((ckpt / "config.json").read_text())
    assert cfg["use_images"] and cfg["input_features"]["observation.images.top"]["shape"] == [3, 64, 64]


def test_start_and_current_state_enter_the_context(policy_and_data):
    """After reset the first sensed state is kept as a condition at t = 0; the current state enters at τ - Δ."""
    policy, _ = policy_and_data
    policy.reset()
    first, later = _obs(2, seed=1), _obs(2, seed=2)
    policy.select_action(first)
    policy.select_action(later)
    ctx = policy.executor.execution_context(later, policy.executor.phase)
    k = policy.config.env_condition_slots
    torch.testing.assert_close(ctx.values[:, k], policy.normalizer.sm(first[OBS_STATE]))
    assert bool((ctx.phase[:, k] == 0).all())
    torch.testing.assert_close(ctx.values[:, k + 1], policy.normalizer.sm(later[OBS_STATE]))
    torch.testing.assert_close(ctx.phase[:, k + 1], (policy.executor.phase - policy.executor.phase_step).clamp(min=0))
    policy.reset()
    assert policy.executor.start is None and policy.executor.phase is None and policy.executor.target is None and not policy.executor.has_inputs


# ---- online execution: phase stopping, PD, open loop (paper Sec. III) ----------------------------------


def _tracking_obs(policy, env_state, states):
    return {OBS_STATE: states, OBS_ENV_STATE: env_state}


def test_phase_stops_while_tracking_error_is_large_and_resumes(policy_and_data):
    policy, _ = policy_and_data
    policy.reset()
    obs = _obs(2, seed=7)
    policy.select_action(obs)  # step 0: phase 0, commands a target per env
    step = policy.executor.phase_step
    raw = policy.normalizer.sm_inverse  # the policy tracks in normalized SM units; observations are raw
    far = raw(policy.executor.target + torch.tensor([[0.0, 0.0], [50.0, 50.0]]))  # env 0 tracked, env 1 far off (held)
    policy.select_action({**obs, OBS_STATE: far})
    torch.testing.assert_close(policy.executor.phase, torch.tensor([step, 0.0]))  # env 1 stalls, env 0 goes on
    for _ in range(3):
        far = raw(policy.executor.target + torch.tensor([[0.0, 0.0], [50.0, 50.0]]))
        policy.select_action({**obs, OBS_STATE: far})
    torch.testing.assert_close(policy.executor.phase, torch.tensor([4 * step, 0.0]))
    policy.select_action({**obs, OBS_STATE: raw(policy.executor.target)})  # released: error 0
    torch.testing.assert_close(policy.executor.phase, torch.tensor([5 * step, step]))
    assert policy.executor.tracking_error(policy.executor.target.clone()).abs().max() == 0


def test_feedback_dims_limit_the_tracking_error(policy_and_data):
    policy, _ = policy_and_data
    policy.config.execution.feedback_dims = (0,)
    try:
        policy.reset()
        obs = _obs(1, seed=8)
        policy.select_action(obs)
        off_in_y = policy.executor.target + torch.tensor([[0.0, 5.0]])  # only the unwatched dim is off
        assert float(policy.executor.tracking_error(off_in_y)[0]) == 0.0
        ctx = policy.executor.execution_context({**obs, OBS_STATE: off_in_y}, policy.executor.phase)
        torch.testing.assert_close(ctx.mask[0, -1], torch.tensor([1.0, 0.0]))  # current state: x only
        policy.config.execution.feedback_dims, policy.config.execution.tracking_dims = None, (1,)  # feed both back, track y only
        off_in_x = policy.executor.target + torch.tensor([[5.0, 0.0]])
        sigma_y = float(policy.executor.reference_std[0, 1])  # the error is in units of the predicted σ
        assert float(policy.executor.tracking_error(off_in_x)[0]) == 0.0
        assert float(policy.executor.tracking_error(off_in_y)[0]) == pytest.approx(5.0 / sigma_y, rel=1e-6)
        policy.config.execution.phase_stop_units = "normalized"  # old checkpoints' units
        assert float(policy.executor.tracking_error(off_in_y)[0]) == 5.0
        ctx = policy.executor.execution_context({**obs, OBS_STATE: off_in_x}, policy.executor.phase)
        torch.testing.assert_close(ctx.mask[0, -1], torch.tensor([1.0, 1.0]))
    finally:
        policy.config.execution.feedback_dims = policy.config.execution.tracking_dims = None
        policy.config.execution.phase_stop_units = "sigma"


def test_open_loop_replays_the_plan(policy_and_data):
    policy, _ = policy_and_data
    policy.config.execution.online_feedback = False
    try:
        policy.reset()
        obs = _obs(1, seed=9)
        first = policy.select_action(obs)
        # Whatever the sensed state does later, the open loop ignores it and always advances.
        a = policy.select_action({**obs, OBS_STATE: obs[OBS_STATE] + 3.0})
        b_policy = CNMPPolicy(policy.config)
        b_policy.load_state_dict(policy.state_dict())
        b_policy.eval()
        b_policy.select_action(obs)
        b = b_policy.select_action(obs)
        torch.testing.assert_close(a, b)
        torch.testing.assert_close(policy.executor.phase, torch.tensor([policy.executor.phase_step]))
        assert first.shape == (1, 2)
        ctx = policy.executor.execution_context(obs, policy.executor.phase)
        assert ctx.phase.shape[1] == policy.config.env_condition_slots + 1  # conditions + start, no current state
    finally:
        policy.config.execution.online_feedback = True


def test_pd_law_and_sigma_scaled_gains(policy_and_data):
    policy, _ = policy_and_data
    cfg = policy.config.execution
    std = torch.tensor([[1e-4, 0.01], [0.05, 10.0]])
    kp, kd = policy.executor.pd_gains(std)
    torch.testing.assert_close(kp, torch.full_like(std, cfg.pd_kp))
    torch.testing.assert_close(kd, torch.full_like(std, cfg.pd_kd))
    cfg.sigma_scaled_gains = True
    try:
        k, _ = policy.executor.pd_gains(std)
        assert bool(((k >= cfg.kp_min) & (k <= cfg.kp_max)).all())
        assert float(k[0, 0]) == pytest.approx(cfg.kp_max) and float(k[1, 1]) == pytest.approx(cfg.kp_min)  # low σ stiff
    finally:
        cfg.sigma_scaled_gains = False
    # pd_dims: the PD law on x only; y is commanded the prediction itself (kp = 1, kd = 0).
    cfg.pd_kp, cfg.pd_kd, cfg.pd_dims = 0.5, 0.2, (0,)
    try:
        kp, kd = policy.executor.pd_gains(std)
        torch.testing.assert_close(kp, torch.tensor([[0.5, 1.0], [0.5, 1.0]]))
        torch.testing.assert_close(kd, torch.tensor([[0.2, 0.0], [0.2, 0.0]]))
        cfg.pd_kd = 0.0
        policy.reset()
        obs = _obs(1, seed=4)
        policy.select_action(obs)  # first step: e_prev = e
        state = obs[OBS_STATE]
        action = policy.select_action(obs)
        n = policy.normalizer
        sn = n.sm(state)
        torch.testing.assert_close(action[:, 0], n.sm_inverse(sn + 0.5 * (policy.executor.target - sn))[:, 0])
        torch.testing.assert_close(action[:, 1], n.sm_inverse(policy.executor.target)[:, 1])
    finally:
        cfg.pd_kp, cfg.pd_kd, cfg.pd_dims = 1.0, 0.0, None
    # kp = 1, kd = 0: the command is the predicted SM itself.
    policy.reset()
    obs = _obs(1, seed=4)
    action = policy.select_action(obs)
    torch.testing.assert_close(action, policy.normalizer.sm_inverse(policy.executor.target))


@pytest.mark.parametrize(
    "field, value, match",
    [
        ("phase_stop_threshold", -0.1, "phase_stop_threshold"),
        ("phase_stop_threshold", 0.0, "phase_stop_threshold"),
        ("pd_kp", -1.0, "PD gains"),
        ("pd_kd", -0.5, "PD gains"),
        ("kp_min", 2.0, "kp_min"),
        ("phase_step", 1.5, "phase_step"),
        ("feedback_dims", (), "feedback_dims"),
        ("pd_dims", (), "pd_dims"),
    ],
)
def test_bad_execution_config_is_rejected(field, value, match):
    with pytest.raises(ValueError, match=match):
        ExecutionConfig(**{field: value})
    with pytest.raises(ValueError, match=match):  # the section given as a dict
        CNMPConfig(execution={field: value})


def test_feedback_dims_outside_the_sm_are_rejected(meta):
    with pytest.raises(ValueError, match="feedback_dims"):
        make_policy(small_config(execution={"feedback_dims": (0, 5)}), ds_meta=meta)


def test_new_batch_of_envs_starts_at_phase_zero(policy_and_data):
    """A batch of another size is a new set of episodes: every env starts at t = 0, from its own state."""
    policy, _ = policy_and_data
    policy.reset()
    for _ in range(5):
        policy.select_action(_obs(3, seed=11))
    obs = _obs(2, seed=12)
    policy.select_action(obs)
    torch.testing.assert_close(policy.executor.phase, torch.zeros(2))
    torch.testing.assert_close(policy.executor.start, policy.normalizer.sm(obs[OBS_STATE]))


def test_pickplace_gamma_reaches_the_policy_through_lerobots_rollout():
    """γ leaves the env as environment_state, the env preprocessor renames it observation.task_params, the
    policy (built from the pick-and-place dataset, untrained) conditions on it, and a changed γ changes
    the prediction."""
    from lerobot.envs.factory import make_env, make_env_pre_post_processors
    from lerobot.scripts.lerobot_eval import rollout

    from lerobot_cnmp.policy.configuration_cnmp import TASK_PARAMS
    from lerobot_cnmp.sims.pickplace.config import CNMPPickPlaceEnv

    root = REPO / "datasets" / "cnmp_pickplace"
    pp_meta = LeRobotDatasetMetadata("lerobot-cnmp/cnmp_pickplace", root=root)
    cfg = small_config(execution={"feedback_dims": (0, 1, 2, 3, 4, 5)})
    policy = make_policy(cfg, ds_meta=pp_meta)
    assert policy.config.task_dim == 2 and policy.config.sm_dim == 7
    pre, post = make_cnmp_pre_post_processors(policy.config)
    seen = []
    env_cfg = CNMPPickPlaceEnv(task_params=(3.0, 6.0), render_mode=None, episode_length=5)
    env = next(iter(make_env(env_cfg, n_envs=1)[env_cfg.type].values()))
    env_pre, env_post = make_env_pre_post_processors(env_cfg, policy.config)
    original = policy.select_action

    def spy(batch, **kw):
        seen.append(batch[TASK_PARAMS].clone())
        return original(batch, **kw)

    policy.select_action = spy
    try:
        data = rollout(env, policy, env_pre, env_post, pre, post, seeds=[0])
    finally:
        del policy.select_action
        env.close()
    assert data["action"].shape[-1] == 7 and len(seen) == 5
    np.testing.assert_allclose(seen[0][0].numpy(), [3.0, 6.0], atol=1e-5)  # γ arrives in its units
    g = policy.episode_inputs({TASK_PARAMS: seen[0]})
    stats = sm_stats(policy)["task"]
    np.testing.assert_allclose(g[0].numpy(), (np.array([3.0, 6.0]) - stats["mean"]) / stats["std"], rtol=1e-5)
    # the policy uses γ: another γ, same state, another prediction
    batch = pre({OBS_STATE: torch.zeros(1, 7), TASK_PARAMS: torch.tensor([[3.0, 6.0]])})
    other = pre({OBS_STATE: torch.zeros(1, 7), TASK_PARAMS: torch.tensor([[9.0, 11.0]])})  # extrapolated: accepted
    policy.reset()
    a = policy.predict_action_chunk(batch)
    policy.reset()
    b = policy.predict_action_chunk(other)
    assert not torch.allclose(a, b)


def test_numpy_execution_matches_torch_and_follows_weight_changes(policy_and_data):
    policy, _ = policy_and_data
    policy.eval()
    env = torch.from_numpy(encode_conditions([Condition(0.5, (0.5, 0.4))], 2, 4))[None]
    batch = {OBS_STATE: torch.tensor([[0.1, 0.2]]), OBS_ENV_STATE: env}

    def actions(numpy_execution: bool) -> torch.Tensor:
        policy.config.execution.numpy_execution = numpy_execution
        policy.reset()
        return torch.stack([policy.select_action(dict(batch)) for _ in range(3)])

    try:
        assert not isinstance(policy.network(), torch.nn.Module)
        torch.testing.assert_close(actions(True), actions(False), atol=1e-5, rtol=1e-5)
        before = actions(True)
        with torch.no_grad():  # a weight update (as an optimizer step makes) must reach the numpy copy
            policy.model.decoder[-1].bias.add_(0.5)
        after = actions(True)
        torch.testing.assert_close(after, actions(False), atol=1e-5, rtol=1e-5)
        assert not torch.allclose(before, after)
        policy.train()
        assert policy.network() is policy.model  # training runs torch
    finally:
        with torch.no_grad():
            policy.model.decoder[-1].bias.sub_(0.5)
        policy.config.execution.numpy_execution = True
        policy.eval()


IMG = "observation.images.top"


def image_config(**kw) -> CNMPConfig:
    kw.setdefault("use_images", True)
    cfg = small_config(image_channels=(4, 8), image_embed_dim=6, demo_duration_s=19.0, **kw)
    cfg.input_features = {OBS_STATE: PolicyFeature(type=FeatureType.STATE, shape=(2,)),
                          IMG: PolicyFeature(type=FeatureType.VISUAL, shape=(1, 16, 16))}
    cfg.output_features = {ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(2,))}
    return cfg


class _Frames:
    """First frames of 3 episodes, as FirstFrames returns them."""

    def __init__(self):
        self.images = torch.rand(3, 1, 16, 16)

    def __call__(self, episode_index):
        return {IMG: self.images[episode_index.long()]}


def test_images_condition_the_cnmp_through_a_conv_encoder():
    from lerobot_cnmp.data.bank import EpisodeBank

    torch.manual_seed(0)
    policy = CNMPPolicy(image_config())
    assert policy.config.episode_dim == 6 and policy.model.task_dim == 6
    policy.set_bank(EpisodeBank.from_arrays([np.random.randn(20, 2).astype(np.float32) for _ in range(3)]), None)
    policy._first_frames = _Frames()
    loss, _ = policy.forward({"episode_index": torch.tensor([0, 1, 2])})
    loss.backward()
    conv = policy.image_encoders[IMG.replace(".", "_")].conv[0].weight
    assert torch.isfinite(loss) and conv.grad is not None and conv.grad.abs().sum() > 0  # the encoder learns
    policy.eval()
    obs = {OBS_STATE: torch.zeros(1, 2), IMG: torch.zeros(1, 1, 16, 16)}
    policy.reset()
    a = policy.predict_action_chunk(dict(obs))
    policy.reset()
    b_ = policy.predict_action_chunk({**obs, IMG: torch.ones(1, 1, 16, 16)})
    assert not torch.allclose(a, b_)  # another image, another prediction
    # the image of the episode's first step conditions the whole episode (as the first frame does in training)
    policy.reset()
    first = policy.select_action(dict(obs))
    second_same = policy.select_action({**obs, IMG: torch.ones(1, 1, 16, 16)})
    policy.reset()
    policy.select_action(dict(obs))
    second_ref = policy.select_action(dict(obs))
    assert first.shape == (1, 2) and torch.equal(second_same, second_ref)
    with pytest.raises(KeyError, match=IMG):
        policy.reset()
        policy.select_action({OBS_STATE: torch.zeros(1, 2)})
    card = str(policy.generate_model_card("you/rooms", repo_id="you/cnmp_img"))
    assert "conv encoder" in card and "[4, 8], embedding 6" in card
    assert "CNMPModel.load" not in card  # the in-memory API takes no images


def test_image_config_errors():
    cfg = image_config()
    cfg.input_features[IMG] = PolicyFeature(type=FeatureType.VISUAL, shape=(1, 3, 3))
    with pytest.raises(ValueError, match="sides of at least 4"):
        CNMPPolicy(cfg)
    cfg = small_config(use_images=True)
    cfg.input_features = {OBS_STATE: PolicyFeature(type=FeatureType.STATE, shape=(2,))}
    cfg.output_features = {ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(2,))}
    with pytest.raises(ValueError, match="no image feature"):
        CNMPPolicy(cfg)
    off = image_config(use_images=False)
    assert off.image_keys == [] and CNMPPolicy(off).model.task_dim == 0


def test_mixture_policy_follows_the_committed_expert_and_loads_bit_identically(meta, tmp_path):
    """n_experts > 1: select_action commands the expert the mode rule follows (first step: the most probable),
    runs the torch model, and save_pretrained -> from_pretrained executes bit-identically."""
    policy = make_policy(small_config(n_experts=3), ds_meta=meta)
    policy.eval()
    assert {"decoders.weights.0", "gate.weight"} <= set(policy.model.state_dict())
    assert policy.network() is policy.model  # no numpy copy of a mixture
    obs = _obs(2, seed=3)
    policy.reset()
    ctx = policy.executor.execution_context(dict(obs), torch.zeros(2))
    means, _, probs = policy.model.mixture(ctx, torch.zeros(2, 1))
    policy.reset()
    action = policy.select_action(dict(obs))
    k = probs.argmax(-1)
    assert torch.equal(policy.executor.modes.current, k)
    # tied layout, kp = 1, kd = 0: the command is the followed expert's μ(τ = 0)
    torch.testing.assert_close(action, policy.normalizer.sm_inverse(means[torch.arange(2), k, 0]))
    actions = [action] + [policy.select_action(dict(obs)) for _ in range(4)]
    ckpt = tmp_path / "mixture"
    policy.save_pretrained(ckpt)
    loaded = CNMPPolicy.from_pretrained(ckpt)
    loaded.eval()
    assert loaded.config.n_experts == 3
    loaded.reset()
    again = [loaded.select_action(dict(obs)) for _ in range(5)]
    assert all(torch.equal(a, b) for a, b in zip(actions, again, strict=True))
    # a mixture checkpoint does not load into a single-decoder CNMP (nor the reverse): a clear error
    cfg = json.loads((ckpt / "config.json").read_text())
    cfg["n_experts"] = 1
    (ckpt / "config.json").write_text(json.dumps(cfg))
    with pytest.raises(Exception) as err:  # the saved shared trunk needs experts (draccus wraps our message)
        CNMPPolicy.from_pretrained(ckpt)
    chain, e = [], err.value
    while e is not None:
        chain.append(str(e))
        e = e.__cause__ or e.__context__
    assert any("n_experts is 1" in m for m in chain), chain
    cfg.pop("mixture")  # the single decoder's settings: no shared trunk
    (ckpt / "config.json").write_text(json.dumps(cfg))
    with pytest.raises(ValueError, match="do not fit"):
        CNMPPolicy.from_pretrained(ckpt)


def test_bad_camera_input_is_a_clear_error_naming_the_feature():
    """A camera at another resolution, a grayscale frame where color was trained, channels last: each a
    ValueError naming the image feature and the trained shape (a missing camera: KeyError, tested above)."""
    cfg = image_config()
    cfg.input_features[IMG] = PolicyFeature(type=FeatureType.VISUAL, shape=(3, 16, 16))
    policy = CNMPPolicy(cfg)
    from lerobot_cnmp.data.bank import EpisodeBank

    policy.set_bank(EpisodeBank.from_arrays([np.random.randn(20, 2).astype(np.float32) for _ in range(3)]), None)
    policy.eval()
    for img, extra in ((torch.zeros(1, 3, 32, 32), ""), (torch.zeros(1, 1, 16, 16), "grayscale"),
                       (torch.zeros(1, 16, 16, 3), "channels last")):
        policy.reset()
        with pytest.raises(ValueError, match=rf"{IMG}.*\[B, 3, 16, 16\]" + (f".*{extra}" if extra else "")):
            policy.select_action({OBS_STATE: torch.zeros(1, 2), IMG: img})
    policy.reset()
    assert policy.select_action({OBS_STATE: torch.zeros(1, 2), IMG: torch.zeros(1, 3, 16, 16)}).shape == (1, 2)


def test_keypoint_centered_encoder_trains_and_saves_its_mean_image(tmp_path):
    from lerobot_cnmp.data.bank import EpisodeBank

    torch.manual_seed(0)
    from lerobot_cnmp.policy.image_config import ImageEncoderConfig

    policy = CNMPPolicy(image_config(image_encoder=ImageEncoderConfig(keypoints=True, shift=2, downsample=2, center=True,
                                                                      final_point_weight=1.0)))
    enc = policy.image_encoders[IMG.replace(".", "_")]
    assert enc.keypoints and isinstance(enc.conv[0], torch.nn.AvgPool2d) and enc.mean_image.shape == (1, 16, 16)
    policy.set_bank(EpisodeBank.from_arrays([np.random.randn(20, 2).astype(np.float32) for _ in range(3)]), None)
    policy._first_frames = _Frames()
    with torch.no_grad():
        enc.mean_image.copy_(policy._first_frames.images.mean(0))
    loss, info = policy.forward({"episode_index": torch.tensor([0, 1, 2])})
    loss.backward()
    assert torch.isfinite(loss) and enc.conv[1].weight.grad.abs().sum() > 0
    assert info["final_point_mse"] > 0 and policy.final_point_head.weight.grad.abs().sum() > 0
    last = policy.bank.points_of(torch.tensor([1]), (1.0,))
    torch.testing.assert_close(last[0, 0], policy.bank.values[policy.bank.starts[1] + policy.bank.lengths[1] - 1])
    policy.save_pretrained(tmp_path)
    back = CNMPPolicy.from_pretrained(tmp_path)
    torch.testing.assert_close(back.image_encoders[IMG.replace(".", "_")].mean_image, enc.mean_image)
    assert back.config.image_encoder.center and back.config.image_encoder.downsample == 2


def test_auxiliary_head_predicts_the_sm_at_each_point_phase():
    """point_phases: the head outputs one SM point per phase, and the loss compares them with the demo's SM at
    frame round(phase * (length - 1)) (a head that predicts exactly those points has zero auxiliary error)."""
    from lerobot_cnmp.data.bank import EpisodeBank
    from lerobot_cnmp.policy.image_config import ImageEncoderConfig

    demos = [np.arange(20 * 2, dtype=np.float32).reshape(20, 2) + 100 * i for i in range(3)]
    bank = EpisodeBank.from_arrays(demos)
    points = bank.points_of(torch.tensor([2, 0]), (0.0, 0.5, 1.0))
    torch.testing.assert_close(points, torch.from_numpy(np.stack([demos[2][[0, 10, 19]], demos[0][[0, 10, 19]]])))
    torch.manual_seed(0)
    enc = ImageEncoderConfig(keypoints=True, final_point_weight=1.0, point_phases=[0.0, 0.5, 1.0])
    policy = CNMPPolicy(image_config(image_encoder=enc))
    assert policy.final_point_head.out_features == 3 * 2
    policy.set_bank(bank, None)
    policy._first_frames = _Frames()
    # a head that ignores the embedding and outputs the normalized points of episode 1 at the three phases
    target = policy.normalizer.sm(bank.points_of(torch.tensor([1]), enc.point_phases)).flatten()
    with torch.no_grad():
        policy.final_point_head.weight.zero_()
        policy.final_point_head.bias.copy_(target)
    _, info = policy.forward({"episode_index": torch.tensor([1])})
    assert info["final_point_mse"] < 1e-10
    _, info = policy.forward({"episode_index": torch.tensor([0])})
    # summed over the phases (each point weighs as the last alone), averaged over the SM dims
    expected = (target.view(3, 2) - policy.normalizer.sm(bank.points_of(torch.tensor([0]), enc.point_phases))[0])
    assert info["final_point_mse"] == pytest.approx(expected.square().mean(-1).sum().item(), rel=1e-5)
    for bad in ([], [1.5], [-0.1, 1.0], [float("nan")], ["a"], 0.5):
        with pytest.raises(ValueError, match="image_encoder.point_phases"):
            ImageEncoderConfig(point_phases=bad)

"""The executor room: conditions from the user, chunks, RTC through LeRobot's engine, phase stopping in σ
units with a timeout, and old flat configs."""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from lerobot.configs.policies import PreTrainedConfig
from lerobot.utils.constants import OBS_ENV_STATE, OBS_STATE

from lerobot_cnmp.api import CNMPModel, load_pretrained
from lerobot_cnmp.policy.configuration_cnmp import CNMPConfig
from lerobot_cnmp.execution.config import ExecutionConfig
from lerobot_cnmp.execution.conditions import parse_conditions
from lerobot_cnmp.policy.modeling_cnmp import CNMPPolicy

T = 100
FPS = 50.0


def demos(n: int = 24, seed: int = 0) -> np.ndarray:
    """x goes 0 -> 1, y = a sin(πt/2) ends at the amplitude a in [-1, 1]: a goal on y picks the demo family."""
    t = np.linspace(0, 1, T)
    a = np.linspace(-1, 1, n)
    return np.stack([np.stack([t, ai * np.sin(np.pi * t / 2)], -1) for ai in a]).astype(np.float32)


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory) -> Path:
    torch.manual_seed(0)
    model = CNMPModel(encoder_layers=(64, 64), decoder_layers=(64, 64), sampling={"n_max_context": 4, "m_max_targets": 8})
    model.fit(demos(), steps=1500, batch_size=16, progress=False, fps=FPS)
    return model.save(tmp_path_factory.mktemp("cnmp") / "pretrained_model")


@pytest.fixture()
def policy(ckpt):
    p, _, _ = load_pretrained(ckpt)
    p.eval()
    p.reset()
    p.set_conditions(None)
    return p


def obs(state=(0.0, 0.0), n=1) -> dict:
    """An observation without environment_state conditions (a robot's), state in the SM's units."""
    return {OBS_STATE: torch.tensor([state], dtype=torch.float32).repeat(n, 1),
            OBS_ENV_STATE: torch.zeros(n, 4 * 6)}


def full_plan(policy, state=(0.0, 0.0)) -> torch.Tensor:
    steps = int(np.ceil(1 / policy.executor.phase_step)) + 1
    policy.reset()
    return policy.predict_action_chunk(obs(state), n_steps=steps)[0]


# ---- conditions from the user ------------------------------------------------------------------------------


def test_user_goal_is_reached_and_a_moving_goal_replans_at_once(policy):
    names = list(policy.config.sm_names)
    assert len(names) == 2
    y = names[1]
    policy.set_conditions([{"t": 1.0, y: 0.8}])
    plan = full_plan(policy)
    assert abs(float(plan[-1, 1]) - 0.8) < 0.15, plan[-1]
    policy.set_conditions(json.dumps([{"t": 1.0, y: -0.5}]))
    assert abs(float(full_plan(policy)[-1, 1]) + 0.5) < 0.15
    # mid-episode: halfway through, the goal moves; the next plan already heads for the new goal
    def first_half():
        policy.set_conditions([{"t": 1.0, y: 0.8}])
        policy.reset()
        s = torch.zeros(1, 2)
        for _ in range(50):
            s = policy.select_action({**obs(), OBS_STATE: s})
        return s

    s = first_half()
    before = policy.predict_action_chunk({**obs(), OBS_STATE: s}, n_steps=200)[0, -1, 1]
    s = first_half()
    policy.set_conditions([{"t": 1.0, y: -0.8}])
    after = policy.predict_action_chunk({**obs(), OBS_STATE: s}, n_steps=200)[0, -1, 1]
    # the goal moved from +0.8 to -0.8 halfway (y is already ~0.4 there): the plan turns towards it at once
    assert float(before) > 0.5 and float(after) < float(before) - 0.5, (before, after)


def test_conditions_in_seconds_files_and_the_config(policy, ckpt, tmp_path):
    c = policy.config
    y = c.sm_names[1]
    half = 0.5 * c.demo_duration_s
    a = parse_conditions([{"time_s": half, y: 0.3}], c.spec, c.demo_duration_s, 8, c.sm_names)
    assert a[0].phase == pytest.approx(0.5) and a[0].mask().tolist() == [0.0, 1.0] and a[0].values[1] == pytest.approx(0.3)
    f = tmp_path / "goal.json"
    f.write_text(json.dumps({"t": 1.0, y: 0.8}))
    g = tmp_path / "goal.yaml"
    g.write_text(f"- t: 1.0\n  {y}: 0.8\n")
    for spec in (str(f), str(g)):
        policy.set_conditions(spec)
        assert abs(float(full_plan(policy)[-1, 1]) - 0.8) < 0.15
    # --policy.conditions: the config's conditions are validated and used when the policy is built
    cfg = PreTrainedConfig.from_pretrained(ckpt, cli_overrides=[f"--conditions={f}"])
    built = CNMPPolicy.from_pretrained(ckpt, config=cfg)
    assert len(built.executor.conditions) == 1 and built.executor.conditions[0].phase == 1.0


_CKPT: list[str] = []


@pytest.fixture(autouse=True)
def _remember(ckpt):
    _CKPT[:] = [str(ckpt)]


@pytest.mark.parametrize(
    "conditions, match",
    [
        ([{"t": 1.0, "nope": 1.0}], "unknown dim 'nope'"),
        ([{"t": 1.0, "Y": float("nan")}], "NaN"),
        ([{"t": 1.5, "Y": 0.0}], "outside \\[0, 1\\]"),
        ([{"t": -0.1, "Y": 0.0}], "outside \\[0, 1\\]"),
        ([{"t": 0.5, "Y": 0.0}] * 9, "at most 8"),
        ([{"t": 0.5, "time_s": 1.0, "Y": 0.0}], "exactly one of 't'"),
        ([{"Y": 0.0}], "exactly one of 't'"),
        ([{"t": 0.5}], "constrains no dim"),
        ([{"t": 0.5, "Y": "high"}], "not a number"),
        ("[{t: 1", "neither JSON"),
        ("goal", "neither JSON"),
        ("missing.json", "does not exist"),
    ],
)
def test_bad_conditions_are_clear_errors_before_anything_moves(policy, conditions, match):
    y = policy.config.sm_names[1]
    if isinstance(conditions, list):
        conditions = [{(y if k == "Y" else k): v for k, v in c.items()} for c in conditions]
    with pytest.raises((ValueError, FileNotFoundError), match=match):
        policy.set_conditions(conditions)
    # and at construction, from the config (--policy.conditions)
    cfg = PreTrainedConfig.from_pretrained(_CKPT[0])
    cfg.conditions = conditions if isinstance(conditions, str) else json.dumps(conditions)
    with pytest.raises((ValueError, FileNotFoundError), match=match):
        CNMPPolicy.from_pretrained(_CKPT[0], config=cfg)


def test_capacity_is_a_model_setting_not_the_dataset(policy):
    """A CNMP whose observations carry no condition slots (a robot) still takes the user's goals."""
    c = policy.config
    assert c.max_conditions == 8 and c.env_condition_slots == 4
    y = c.sm_names[1]
    policy.set_conditions([{"t": 1.0, y: 0.8}])
    policy.reset()
    robot_obs = {OBS_STATE: torch.zeros(1, 2)}  # no environment_state at all
    steps = int(np.ceil(1 / policy.executor.phase_step)) + 1
    plan = policy.predict_action_chunk(robot_obs, n_steps=steps)[0]
    assert abs(float(plan[-1, 1]) - 0.8) < 0.15
    with pytest.raises(ValueError, match="max_conditions=8"):
        policy.set_conditions([{"t": k / 10, y: 0.0} for k in range(5)])  # 5 + 4 env slots > 8


# ---- chunks ------------------------------------------------------------------------------------------------


def test_chunk_is_the_open_loop_plan_with_sigma_and_advances_the_phase(policy):
    e = policy.config.execution
    e.online_feedback = False
    try:
        policy.reset()
        steps = [policy.select_action(obs((0.0, 0.1))) for _ in range(12)]
        policy.reset()
        chunk, std = policy.predict_action_chunk(obs((0.0, 0.1)), n_steps=12, return_std=True)
        assert chunk.shape == (1, 12, 2) and std.shape == (1, 12, 2) and bool((std > 0).all())
        torch.testing.assert_close(chunk[0], torch.cat(steps), rtol=1e-5, atol=1e-6)
        d = policy.executor.phase_step
        assert float(policy.executor.phase[0]) == pytest.approx(11 * d, rel=1e-5)
        nxt = policy.predict_action_chunk(obs((0.0, 0.1)), n_steps=3)  # continues where the chunk ended
        policy.reset()
        ref = policy.predict_action_chunk(obs((0.0, 0.1)), n_steps=15)
        torch.testing.assert_close(nxt[0], ref[0, 12:], rtol=1e-5, atol=1e-6)
        assert policy.predict_action_chunk(obs()).shape[1] == e.n_action_steps == policy.config.n_action_steps
    finally:
        e.online_feedback = True


# ---- phase stopping: σ units and the timeout --------------------------------------------------------------


def test_phase_stop_timeout_releases_a_blocked_robot(policy, caplog):
    e = policy.config.execution
    assert e.phase_stop_units == "sigma" and e.phase_stop_threshold == 3.0 and e.phase_stop_timeout_s == 2.0
    e.phase_stop_timeout_s = 0.1  # 5 steps at 50 fps
    try:
        policy.reset()
        blocked = obs((0.0, 0.0))
        policy.select_action(blocked)
        far = {**blocked, OBS_STATE: torch.tensor([[5.0, 5.0]])}  # stuck far from every commanded point
        phases = []
        with caplog.at_level(logging.WARNING, logger="lerobot_cnmp.execution.executor"):
            for _ in range(9):
                policy.select_action(far)
                phases.append(float(policy.executor.phase[0]))
        assert phases[:5] == [0.0] * 5  # held while within the timeout
        assert phases[5] > 0 and phases[8] > phases[5]  # then it advances again
        assert sum("phase_stop_timeout_s" in r.message for r in caplog.records) == 1  # warned once
        assert float(policy.executor.tracking_error(policy.normalizer.sm(far[OBS_STATE]))[0]) > e.phase_stop_threshold
    finally:
        e.phase_stop_timeout_s = 2.0


def test_sigma_units_divide_by_the_predicted_sigma(policy):
    policy.reset()
    policy.select_action(obs())
    ex = policy.executor
    off = ex.target + torch.tensor([[0.0, 0.2]])
    assert float(ex.tracking_error(off)[0]) == pytest.approx(0.2 / float(ex.reference_std[0, 1]), rel=1e-5)


# ---- old checkpoints ------------------------------------------------------------------------------------------


def test_old_flat_config_loads_with_its_own_semantics(ckpt, tmp_path):
    """A config.json written before `execution` existed: flat keys move under `execution`, its threshold keeps
    its normalized units and no timeout; a null threshold stays null (never stop)."""
    old = json.loads((ckpt / "config.json").read_text())
    execution = old.pop("execution")
    flat = {k: v for k, v in execution.items() if k not in ("phase_stop_units", "phase_stop_timeout_s", "n_action_steps")}
    for k in ("control_fps", "phase_step", "online_feedback", "condition_on_start", "feedback_dims", "tracking_dims",
              "phase_stop_threshold", "pd_kp", "pd_kd", "pd_dims", "sigma_scaled_gains", "sigma_ref", "kp_min", "kp_max",
              "numpy_execution"):
        old[k] = flat[k]
    old.pop("max_conditions"), old.pop("conditions")
    old["phase_stop_threshold"], old["pd_kp"] = None, 0.7
    folder = tmp_path / "old"
    folder.mkdir()
    for f in ckpt.iterdir():
        (folder / f.name).write_bytes(f.read_bytes())
    (folder / "config.json").write_text(json.dumps(old))
    cfg = PreTrainedConfig.from_pretrained(folder)
    assert isinstance(cfg, CNMPConfig)
    assert cfg.execution.phase_stop_threshold is None and cfg.execution.pd_kp == 0.7
    assert cfg.execution.phase_stop_units == "normalized" and cfg.execution.phase_stop_timeout_s is None
    policy = CNMPPolicy.from_pretrained(folder)
    assert policy.select_action(obs()).shape == (1, 2)
    # saving writes the new layout, which loads back the same
    policy.save_pretrained(tmp_path / "new")
    saved = json.loads((tmp_path / "new" / "config.json").read_text())
    assert saved["execution"]["phase_stop_units"] == "normalized" and "pd_kp" not in saved
    assert PreTrainedConfig.from_pretrained(tmp_path / "new").execution == cfg.execution
    assert ExecutionConfig().phase_stop_threshold == 3.0


# ---- RTC through LeRobot's own engine -----------------------------------------------------------------------


class _Robot:
    """What RTCInferenceEngine reads from its robot wrapper."""

    robot_type = "sim_point"
    action_features = {"x": float, "y": float}


def _run_rtc(ckpt, use_leftover: bool, n_actions: int = 95) -> tuple[np.ndarray, list[bool]]:
    """Drive LeRobot's RTCInferenceEngine at FPS on a point robot whose state reaches each command; the executed
    actions, and per chunk whether the engine passed leftovers. ``use_leftover=False`` hides them from the
    policy (plain chunking from the phase clock), the baseline."""
    from lerobot.policies.rtc.configuration_rtc import RTCConfig
    from lerobot.rollout.inference import RTCInferenceEngine
    from lerobot.rollout.inference.rtc import supports_rtc_inference

    policy, pre, post = load_pretrained(ckpt)
    policy.eval()
    policy.config.execution.n_action_steps = 40
    assert supports_rtc_inference(policy)
    calls = []
    original = policy.predict_action_chunk

    def spy(batch, inference_delay=0, prev_chunk_left_over=None, **kw):
        calls.append(prev_chunk_left_over is not None)
        return original(batch, inference_delay=inference_delay,
                        prev_chunk_left_over=prev_chunk_left_over if use_leftover else None, **kw)

    policy.predict_action_chunk = spy
    hw = {OBS_STATE: {"dtype": "float32", "shape": (2,), "names": ["x", "y"]}}
    engine = RTCInferenceEngine(policy, pre, post, _Robot(), RTCConfig(execution_horizon=10), hw, task="", fps=FPS,
                                device="cpu", rtc_queue_threshold=20)
    engine.reset()
    engine.start()
    engine.resume()
    state = np.zeros(2, dtype=np.float32)
    actions = []
    t0, tick = time.perf_counter(), 0
    try:
        while len(actions) < n_actions and tick < 60 * FPS and not engine.failed:
            engine.notify_observation({"x": float(state[0]), "y": float(state[1])})
            a = engine.get_action(None)
            if a is not None:
                state = a.numpy().astype(np.float32)  # a position servo: the state reaches the command
                actions.append(state.copy())
            tick += 1
            time.sleep(max(0.0, t0 + tick / FPS - time.perf_counter()))  # a control loop at FPS
    finally:
        engine.stop()
    assert not engine.failed and len(actions) >= n_actions, len(actions)
    return np.stack(actions), calls


def test_rtc_through_lerobots_engine_has_no_jump_at_chunk_boundaries(ckpt):
    """Bound: no step of the executed sequence (chunk boundaries included) exceeds 3x the largest step of any
    demonstration. Without the leftovers (the same engine, chunks planned from the phase clock) it does."""
    demo_step = float(np.abs(np.diff(demos(), axis=1)).max())
    actions, calls = _run_rtc(ckpt, use_leftover=True)
    assert sum(calls) >= 3, calls  # several chunks, merged with leftovers by LeRobot's queue
    rtc_jump = float(np.abs(np.diff(actions, axis=0)).max())
    actions, _ = _run_rtc(ckpt, use_leftover=False)
    plain_jump = float(np.abs(np.diff(actions, axis=0)).max())
    print(f"RTC: largest executed step {rtc_jump:.4f} (without leftovers {plain_jump:.4f}), largest demo step "
          f"{demo_step:.4f}, chunks {len(calls)}")
    assert rtc_jump <= 3 * demo_step, (rtc_jump, demo_step)
    assert plain_jump > 3 * demo_step, (plain_jump, demo_step)

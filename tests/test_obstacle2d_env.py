"""Tests of the MuJoCo 2D obstacle sim, its scripted expert and its LeRobot EnvConfig."""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("HF_HUB_OFFLINE", "1")

import gymnasium as gym
import numpy as np
import pytest

import lerobot_cnmp.sims  # noqa: F401  (registers the gym id and the EnvConfig)
from lerobot_cnmp.execution.conditions import Condition, conditions_from_vector
from lerobot_cnmp.sims.obstacle2d.config import CNMPObstacle2DEnv
from lerobot_cnmp.sims.obstacle2d.env import Obstacle2DEnv
from lerobot_cnmp.sims.obstacle2d.model import AGENT_RADIUS, HOLD_STEPS, OBSTACLE_CENTER, OBSTACLE_RADIUS, PUSH_DISTANCE
from lerobot_cnmp.sims.obstacle2d.task import (
    CONDITION_CHOICES,
    ENV_STATE_DIM,
    H_RANGE,
    P_RANGE,
    Y0_RANGE,
    Obstacle2DTask,
)
from lerobot_cnmp.sims.obstacle2d.expert import Obstacle2DExpert

T = 200


def run_expert(env: Obstacle2DEnv, seed: int, options=None, steps: int = T):
    obs, info = env.reset(seed=seed, options=options)
    expert = Obstacle2DExpert(env, demo_length=T)
    expert.reset()
    traj, infos = [obs["agent_pos"].copy()], [info]
    for k in range(steps):
        obs, _, terminated, truncated, info = env.step(expert.act(k))
        traj.append(obs["agent_pos"].copy())
        infos.append(info)
        if terminated or truncated:
            break
    return np.array(traj), infos


def _normalize(conds):
    return [
        (round(c.phase, 5), tuple(round(v, 5) for v in c.values), tuple(range(2)) if c.dims is None else c.dims)
        for c in conds
    ]


def test_family_keeps_clearance():
    tau = np.linspace(0.0, 1.0, 4001)
    worst = np.inf
    for mode in (1, -1):
        for y0 in np.linspace(*Y0_RANGE, 11):
            for h in np.linspace(*H_RANGE, 7):
                for p in np.linspace(*P_RANGE, 9):
                    xy = Obstacle2DTask(mode, mode * y0, mode * h, p).position(tau)
                    d = np.linalg.norm(xy - OBSTACLE_CENTER, axis=-1) - OBSTACLE_RADIUS - AGENT_RADIUS
                    worst = min(worst, d.min())
    assert worst >= 0.05, worst


def test_task_position_vectorized_and_endpoints():
    task = Obstacle2DTask(-1, -0.2, -0.4, 1.1)
    xy = task.position(np.array([0.0, 0.5, 1.0]))
    assert xy.shape == (3, 2)
    np.testing.assert_allclose(xy[0], [0.0, -0.2])
    np.testing.assert_allclose(xy[1], [0.5, -0.4])
    np.testing.assert_allclose(xy[2], [1.0, -0.2], atol=1e-12)
    assert task.position(0.3).shape == (2,)


def test_reset_deterministic_and_observation_shapes():
    env = Obstacle2DEnv()
    obs1, _ = env.reset(seed=7)
    task1, conds1 = env.task, list(env.conditions)
    traj1, _ = run_expert(env, 7, steps=30)
    obs2, _ = env.reset(seed=7)
    assert env.task == task1 and env.conditions == conds1
    traj2, _ = run_expert(env, 7, steps=30)
    np.testing.assert_array_equal(traj1, traj2)
    for k in obs1:
        np.testing.assert_array_equal(obs1[k], obs2[k])
    assert set(obs1) == {"agent_pos", "environment_state"}
    assert obs1["agent_pos"].shape == (2,) and obs1["agent_pos"].dtype == np.float32
    assert obs1["environment_state"].shape == (ENV_STATE_DIM,) == (24,)
    assert obs1["environment_state"].dtype == np.float32
    assert env.observation_space.contains(obs1)
    # start state is the reference's start
    np.testing.assert_allclose(obs1["agent_pos"], env.task.start, atol=1e-6)
    assert env.task_description == "reach the goal around the obstacle"
    env.reset(seed=8)
    assert env.task != task1


@pytest.mark.parametrize("conditions", CONDITION_CHOICES)
def test_conditions_encoded_and_constant(conditions):
    env = Obstacle2DEnv(conditions=conditions)
    for seed in range(8):
        obs, _ = env.reset(seed=seed)
        decoded = conditions_from_vector(obs["environment_state"], sm_dim=2)
        assert _normalize(decoded) == _normalize(env.conditions)
        assert 1 <= len(env.conditions) <= (3 if conditions == "start_goal_early" else 2)
        obs2, *_ = env.step(env.task.position(0.01))
        np.testing.assert_array_equal(obs["environment_state"], obs2["environment_state"])
        # the conditions lie on the hidden reference
        for c in env.conditions:
            np.testing.assert_allclose(env.task.position(c.phase), c.values, atol=1e-9)
        if conditions == "paper_via":
            assert env.conditions == [Condition(0.5, (0.5, 0.55))] and env.task.mode == 1
        elif conditions == "paper_early":
            assert env.conditions == [Condition(0.2, (0.2, -0.37))] and env.task.mode == -1
            assert P_RANGE[0] <= env.task.p <= P_RANGE[1]
        elif conditions == "paper_end":
            assert env.conditions == [Condition(1.0, (1.0, 0.13))] and env.task.y0 == 0.13


def test_mode_option():
    env = Obstacle2DEnv(conditions="random")
    for seed in range(6):
        for mode in (1, -1):
            env.reset(seed=seed, options={"mode": mode})
            assert env.task.mode == mode and np.sign(env.task.y0) == mode
    env = Obstacle2DEnv(conditions="paper_via")
    with pytest.raises(ValueError, match="mode"):
        env.reset(seed=0, options={"mode": -1})


@pytest.mark.parametrize("conditions", CONDITION_CHOICES)
def test_expert_succeeds(conditions):
    env = Obstacle2DEnv(conditions=conditions, terminate_on_success=False)
    n_seeds = 30 if conditions in ("random", "mixed") else 10
    kinds = set()
    for seed in range(n_seeds):
        traj, infos = run_expert(env, seed)
        assert len(traj) == T + 1
        last = infos[-1]
        assert last["is_success"], (seed, env.task, env.conditions, last)
        assert not any(i["contact"] for i in infos)
        assert last["conditions_passed"] == len(env.conditions)
        assert last["goal_error"] <= 0.05
        kinds.add(env.condition_kind)
        # position tracking: the sensed path follows the reference closely
        ref = env.task.position(np.linspace(0, 1, 2001))
        dev = np.min(np.linalg.norm(traj[:, None, :] - ref[None], axis=-1), axis=1)
        assert dev.max() < 0.01
    if conditions == "random":
        assert kinds == {f"random/{v}" for v in ("via", "early", "end", "via+end", "via_y")}


def test_straight_line_hits_obstacle():
    env = Obstacle2DEnv(conditions="paper_end", terminate_on_success=False)  # y0 = 0.13: line crosses
    env.reset(seed=0)
    start, goal = env.task.start, env.task.goal
    infos = []
    for k in range(T):
        tau = min((k + 1) / (T - 1), 1.0)
        *_, info = env.step(start + tau * (goal - start))
        infos.append(info)
    assert infos[-1]["contact"]
    assert not any(i["is_success"] for i in infos)
    # it slides around the obstacle and reaches the goal, but the contact makes it a failure
    assert infos[-1]["goal_error"] < 0.05


def test_terminate_on_success():
    env = Obstacle2DEnv(conditions="mixed", terminate_on_success=True)
    traj, infos = run_expert(env, 3, steps=T + 50)
    assert infos[-1]["is_success"]
    assert len(traj) <= T + 1
    assert sum(i["is_success"] for i in infos) == 1  # terminated at the first successful step


def test_bad_options_raise():
    with pytest.raises(ValueError, match="paper_via"):
        Obstacle2DEnv(conditions="bogus")
    with pytest.raises(ValueError, match="push"):
        Obstacle2DEnv(perturbation="shove")
    with pytest.raises(ValueError, match="render_mode"):
        Obstacle2DEnv(render_mode="human")
    env = Obstacle2DEnv()
    with pytest.raises(ValueError, match="mode"):
        env.reset(seed=0, options={"mode": 0})
    with pytest.raises(ValueError, match="unknown reset options"):
        env.reset(seed=0, options={"color": 1})
    with pytest.raises(ValueError, match="paper_early"):
        CNMPObstacle2DEnv(conditions="bogus")
    with pytest.raises(ValueError, match="hold"):
        CNMPObstacle2DEnv(perturbation="bogus")


def test_render():
    env = Obstacle2DEnv(conditions="random")
    env.reset(seed=1)
    img = env.render()
    env.close()
    assert img.shape == (256, 256, 3) and img.dtype == np.uint8
    assert img.std() > 5
    assert len(np.unique(img.reshape(-1, 3), axis=0)) > 10


def test_push_perturbation():
    base = Obstacle2DEnv(conditions="random", terminate_on_success=False)
    env = Obstacle2DEnv(conditions="random", perturbation="push", terminate_on_success=False)
    for seed in range(5):
        ref, _ = run_expert(base, seed)
        traj, infos = run_expert(env, seed)
        assert env.task == base.task
        flags = np.array([i["perturbed"] for i in infos])
        k = int(np.argmax(flags))  # first step reporting the push
        assert 50 <= k <= 120 and flags[k:].all() and not flags[:k].any()
        np.testing.assert_array_equal(traj[:k], ref[:k])
        jump = traj[k] - ref[k]
        assert np.linalg.norm(jump) == pytest.approx(PUSH_DISTANCE, abs=1e-5)
        # away from the obstacle, never into it
        assert np.dot(jump, ref[k] - OBSTACLE_CENTER) > 0
        assert not infos[-1]["contact"]
        # only once: after the push the servo brings it back
        assert np.linalg.norm(traj[-1] - ref[-1]) < 0.01


def test_hold_perturbation():
    env = Obstacle2DEnv(conditions="random", perturbation="hold", terminate_on_success=False)
    for seed in range(3):
        traj, infos = run_expert(env, seed)
        flags = np.array([i["perturbed"] for i in infos])
        k = int(np.argmax(flags))
        assert 50 <= k <= 120 and flags[k:].all() and not flags[:k].any()
        held = traj[k : k + HOLD_STEPS + 1]
        assert np.all(held == traj[k])  # still for HOLD_STEPS steps
        assert np.linalg.norm(traj[k + HOLD_STEPS + 1] - traj[k]) > 1e-4  # then released
        assert not infos[-1]["contact"]


def test_gym_make_and_lerobot_make_env():
    from lerobot.envs.factory import make_env

    env = gym.make("cnmp/Obstacle2D-v0", disable_env_checker=True, max_episode_steps=123)
    assert env.get_wrapper_attr("_max_episode_steps") == 123
    env.close()

    cfg = CNMPObstacle2DEnv(conditions="mixed", episode_length=250)
    assert cfg.type == "cnmp_obstacle2d" and cfg.gym_id == "cnmp/Obstacle2D-v0"
    envs = make_env(cfg, n_envs=2)
    vec = envs["cnmp_obstacle2d"][0]
    try:
        obs, _ = vec.reset(seed=[0, 1])
        assert obs["agent_pos"].shape == (2, 2) and obs["environment_state"].shape == (2, 24)
        assert tuple(vec.call("_max_episode_steps")) == (250, 250)
        assert list(vec.call("task_description")) == ["reach the goal around the obstacle"] * 2
        for _ in range(3):
            obs, reward, terminated, truncated, info = vec.step(obs["agent_pos"])
        assert "is_success" in info and info["is_success"].shape == (2,)
        frames = vec.call("render")
        assert frames[0].shape == (256, 256, 3)
    finally:
        vec.close()


# --- the shared family, the new pushes and the rate-limited actuator (issue 16) --------------------------

def test_shared_family_modes_share_start_and_goal_and_keep_clearance():
    from lerobot_cnmp.sims.obstacle2d.task import SHARED_Y0_RANGE

    rng = np.random.default_rng(0)
    tau = np.linspace(0.0, 1.0, 2001)
    worst, y0s = np.inf, {1: [], -1: []}
    for _ in range(400):
        task = Obstacle2DTask.sample(rng, family="shared")
        assert SHARED_Y0_RANGE[0] <= task.y0 <= SHARED_Y0_RANGE[1] and np.sign(task.h) == task.mode
        np.testing.assert_allclose(task.goal, [1.0, task.y0])
        y0s[task.mode].append(task.y0)
        xy = task.position(tau)
        worst = min(worst, (np.linalg.norm(xy - OBSTACLE_CENTER, axis=-1) - OBSTACLE_RADIUS - AGENT_RADIUS).min())
    assert worst >= 0.05, worst
    # both modes cover the same start heights: a start (or goal) does not name the mode
    assert abs(np.mean(y0s[1]) - np.mean(y0s[-1])) < 0.03 and min(map(len, y0s.values())) > 150
    # their average runs through the obstacle
    over, under = Obstacle2DTask(1, 0.0, 0.55, 1.2), Obstacle2DTask(-1, 0.0, -0.55, 1.2)
    mean = (over.position(tau) + under.position(tau)) / 2
    assert (np.linalg.norm(mean - OBSTACLE_CENTER, axis=-1) < OBSTACLE_RADIUS).any()


@pytest.mark.parametrize("conditions", ["random", "start_goal", "start_goal_early"])
def test_shared_family_expert_succeeds(conditions):
    env = Obstacle2DEnv(conditions=conditions, family="shared", terminate_on_success=False, render_mode=None)
    for seed in range(4):
        _, infos = run_expert(env, seed)
        assert infos[-1]["is_success"], (seed, infos[-1])
        if conditions.startswith("start_goal"):
            c = env.conditions
            assert c[0].phase == 0.0 and c[1].phase == 1.0 and c[0].values[1] == pytest.approx(c[1].values[1])
            assert len(c) == (3 if conditions == "start_goal_early" else 2)
            if len(c) == 3:
                assert 0.15 <= c[2].phase <= 0.3


def test_shared_family_rejects_the_paper_sets():
    for conditions in ("mixed", "paper_via", "paper_early", "paper_end"):
        with pytest.raises(ValueError, match="mirrored"):
            Obstacle2DEnv(conditions=conditions, family="shared")
        with pytest.raises(ValueError, match="mirrored"):
            CNMPObstacle2DEnv(conditions=conditions, family="shared")
    with pytest.raises(ValueError, match="family"):
        CNMPObstacle2DEnv(conditions="random", family="overlap")
    with pytest.raises(ValueError, match="actuator"):
        Obstacle2DEnv(actuator="motor")
    cfg = CNMPObstacle2DEnv(conditions="random", family="shared", actuator="rate_limited", perturbation="push_toward")
    assert cfg.gym_kwargs["family"] == "shared" and cfg.gym_kwargs["actuator"] == "rate_limited"


@pytest.mark.parametrize("perturbation", ["push_toward", "push_random"])
def test_new_pushes(perturbation):
    from lerobot_cnmp.sims.obstacle2d.model import PUSH_MIN_CLEARANCE

    base = Obstacle2DEnv(conditions="random", terminate_on_success=False, render_mode=None)
    env = Obstacle2DEnv(conditions="random", perturbation=perturbation, terminate_on_success=False, render_mode=None)
    toward = []
    for seed in range(6):
        ref, _ = run_expert(base, seed)
        traj, infos = run_expert(env, seed)
        assert env.task == base.task
        k = int(np.argmax([i["perturbed"] for i in infos]))
        assert 50 <= k <= 120
        np.testing.assert_array_equal(traj[:k], ref[:k])
        jump = traj[k] - ref[k]
        assert 0.0 < np.linalg.norm(jump) <= PUSH_DISTANCE + 1e-6
        clear = np.linalg.norm(traj[k] - OBSTACLE_CENTER) - OBSTACLE_RADIUS - AGENT_RADIUS
        assert clear >= PUSH_MIN_CLEARANCE - 1e-6
        toward.append(np.dot(jump, OBSTACLE_CENTER - ref[k]) / np.linalg.norm(jump) / np.linalg.norm(OBSTACLE_CENTER - ref[k]))
    if perturbation == "push_toward":
        assert min(toward) > 0.999
    else:  # random directions: not all toward, not all away
        assert min(toward) < 0 < max(toward)


def test_rate_limited_actuator_lags_and_open_loop_falls_behind():
    from lerobot_cnmp.sims.obstacle2d.model import CONTROL_FPS, RATE_LIMIT

    servo = Obstacle2DEnv(conditions="random", terminate_on_success=False, render_mode=None)
    lagging = Obstacle2DEnv(conditions="random", actuator="rate_limited", terminate_on_success=False, render_mode=None)
    behind, fails = [], 0
    for seed in range(8):
        ref, ref_infos = run_expert(servo, seed, steps=300)
        traj, infos = run_expert(lagging, seed, steps=300)
        assert ref_infos[-1]["is_success"]
        speed = np.linalg.norm(np.diff(traj, axis=0), axis=1) * CONTROL_FPS
        assert speed.max() <= RATE_LIMIT * 1.1  # the servo follows its set point, which moves at most RATE_LIMIT
        behind.append(np.linalg.norm(traj[100] - ref[100]))
        fails += not any(i["is_success"] for i in infos)
    assert min(behind) > 0.05  # halfway through the demo schedule the lagging body is well behind
    assert fails >= 6  # the expert's schedule replayed open loop misses the conditions

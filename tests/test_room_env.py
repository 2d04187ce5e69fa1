"""Tests of the MuJoCo room sim (image observations), its planner, its scripted expert and its EnvConfig."""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("HF_HUB_OFFLINE", "1")

import time

import gymnasium as gym
import mujoco
import numpy as np
import pytest

import lerobot_cnmp.sims  # noqa: F401  (registers the gym id and the EnvConfig)
from lerobot_cnmp.execution.conditions import conditions_from_vector
from lerobot_cnmp.sims.room.config import CNMPRoomEnv
from lerobot_cnmp.sims.room.env import RoomEnv
from lerobot_cnmp.sims.room.model import AGENT_RADIUS, ENV_STATE_DIM
from lerobot_cnmp.sims.room.planner import MARGIN, MIN_CLEARANCE, distance_to_obstacles, path_clearance, plan_path, waypoints
from lerobot_cnmp.sims.room.task import (
    CONDITION_CHOICES,
    DEMO_LENGTH,
    END_X_RANGE,
    LEFT_X_RANGE,
    LENGTH_RANGE,
    RIGHT_X_RANGE,
    START_X_RANGE,
    VIA_PHASE_RANGE,
    WIDTH_RANGE,
    Y_RANGE,
    Obstacle,
    RoomTask,
)
from lerobot_cnmp.sims.room.expert import RoomExpert

T = DEMO_LENGTH


@pytest.fixture(scope="module")
def env():
    e = RoomEnv(terminate_on_success=False)
    yield e
    e.close()


def run_expert(env: RoomEnv, seed: int, options=None, steps: int = T):
    obs, info = env.reset(seed=seed, options=options)
    expert = RoomExpert(env, demo_length=T)
    expert.reset()
    traj, infos = [obs["agent_pos"].copy()], [info]
    for k in range(steps):
        obs, _, terminated, truncated, info = env.step(expert.act(k))
        traj.append(obs["agent_pos"].copy())
        infos.append(info)
        if terminated or truncated:
            break
    return np.array(traj), infos


def analytic_mask(task: RoomTask, size: int) -> np.ndarray:
    """Pixel centres inside an obstacle rectangle; row 0 = top of the room (y = 1), column 0 = x = 0."""
    c = (np.arange(size) + 0.5) / size
    x, y = np.meshgrid(c, 1.0 - c)
    inside = np.zeros((size, size), dtype=bool)
    for ob in task.obstacles:
        x0, x1, y0, y1 = ob.rect
        inside |= (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
    return inside


def test_task_sampling_ranges_and_determinism():
    tasks = [RoomTask.sample(np.random.default_rng(seed)) for seed in range(300)]
    assert RoomTask.sample(np.random.default_rng(7)) == tasks[7]
    assert len(set(tasks)) == len(tasks)
    assert {t.layout for t in tasks} == {"bottom-first", "top-first"}
    for t in tasks:
        left, right = t.obstacles
        assert {left.wall, right.wall} == {"bottom", "top"}
        assert LEFT_X_RANGE[0] <= left.x <= LEFT_X_RANGE[1] and RIGHT_X_RANGE[0] <= right.x <= RIGHT_X_RANGE[1]
        for ob in t.obstacles:
            assert WIDTH_RANGE[0] <= ob.width <= WIDTH_RANGE[1]
            assert LENGTH_RANGE[0] <= ob.length <= LENGTH_RANGE[1]
            x0, x1, y0, y1 = ob.rect
            assert (y0 == 0.0) if ob.wall == "bottom" else (y1 == 1.0)  # attached to its wall
        assert START_X_RANGE[0] <= t.start[0] <= START_X_RANGE[1]
        assert END_X_RANGE[0] <= t.end[0] <= END_X_RANGE[1]
        assert Y_RANGE[0] <= t.start[1] <= Y_RANGE[1] and Y_RANGE[0] <= t.end[1] <= Y_RANGE[1]


def test_planned_path_keeps_clearance():
    tau = np.linspace(0.0, 1.0, 501)
    worst, worst_obstacle = np.inf, np.inf
    for seed in range(300):
        task = RoomTask.sample(np.random.default_rng(seed))
        worst = min(worst, path_clearance(task))
        path = plan_path(task, tau)
        worst = min(worst, distance_to_obstacles(task, path).min())
        # to the obstacles alone the path keeps at least MARGIN: it only changes gaps between them
        for ob in task.obstacles:
            x0, x1, y0, y1 = ob.rect
            dx = np.maximum(np.maximum(x0 - path[:, 0], path[:, 0] - x1), 0.0)
            dy = np.maximum(np.maximum(y0 - path[:, 1], path[:, 1] - y1), 0.0)
            worst_obstacle = min(worst_obstacle, np.hypot(dx, dy).min())
        np.testing.assert_allclose(path[0], task.start, atol=1e-12)
        np.testing.assert_allclose(path[-1], task.end, atol=1e-12)
        assert np.all(np.diff(path[:, 0]) >= 0)  # left to right, never back
        # zero velocity at both ends (minimum-jerk time law)
        assert np.linalg.norm(plan_path(task, 1e-3) - path[0]) < 1e-6
        assert np.linalg.norm(plan_path(task, 1 - 1e-3) - path[-1]) < 1e-6
        # the gap waypoints are on the path, between the obstacle and the wall it does not touch
        xs, ys = waypoints(task)
        assert np.all(np.diff(xs) > 0)
        for ob, yc in zip(task.obstacles, ys[1::2][:2]):
            assert ob.rect[3] < yc if ob.wall == "bottom" else yc < ob.rect[2]
    assert worst >= MIN_CLEARANCE == AGENT_RADIUS + 0.03, worst
    assert worst_obstacle >= MARGIN, worst_obstacle


def test_planned_curve_never_overshoots_its_waypoints():
    """PCHIP is monotone between waypoints: y(x) stays within each pair of neighbouring waypoints' y
    (up to the linear interpolation between the dense arc-length samples, ~1e-8)."""
    for seed in range(20):
        task = RoomTask.sample(np.random.default_rng(seed))
        xs, ys = waypoints(task)
        path = plan_path(task, np.linspace(0.0, 1.0, 2001))
        for k in range(len(xs) - 1):
            seg = path[(path[:, 0] >= xs[k]) & (path[:, 0] <= xs[k + 1]), 1]
            assert seg.min() >= min(ys[k], ys[k + 1]) - 1e-6 and seg.max() <= max(ys[k], ys[k + 1]) + 1e-6


def test_mask_matches_obstacles(env):
    agreements = []
    for seed in range(15):
        obs, _ = env.reset(seed=seed)
        mask = obs["pixels"]["top"]
        assert mask.shape == (64, 64, 3) and mask.dtype == np.uint8
        assert set(np.unique(mask)) <= {0, 255}
        assert (mask == mask[..., :1]).all()  # the three channels are equal
        agree = np.mean((mask[..., 0] == 255) == analytic_mask(env.task, 64))
        assert agree >= 0.97, (seed, agree)
        agreements.append(agree)
        # orientation: the bottom obstacle's foot is near the last row, the top one's near row 0
        for ob in env.task.obstacles:
            col = int(ob.x * 64)
            assert mask[63 if ob.wall == "bottom" else 0, col, 0] == 255
        # the agent (at the start) is hidden; the mask is static within the episode
        obs2, *_ = env.step(env.task.end)
        np.testing.assert_array_equal(obs2["pixels"]["top"], mask)
    # one sample per pixel at its centre: only pixels with an edge through their centre may differ
    # (a half-pixel shift of the camera would cost ~1.5 % here)
    assert np.mean(agreements) >= 0.998, agreements
    small = RoomEnv(image_size=32, render_mode=None)
    obs, _ = small.reset(seed=3)
    small.close()
    assert obs["pixels"]["top"].shape == (32, 32, 3)
    assert np.mean((obs["pixels"]["top"][..., 0] == 255) == analytic_mask(small.task, 32)) >= 0.97


@pytest.mark.parametrize("condition", CONDITION_CHOICES)
def test_expert_succeeds(condition):
    env = RoomEnv(condition=condition, terminate_on_success=False, render_mode=None)
    for seed in range(20):
        traj, infos = run_expert(env, seed)
        assert len(traj) == T + 1
        last = infos[-1]
        assert last["is_success"], (seed, env.task, last)
        assert not any(i["collision"] for i in infos)
        assert last["conditions_passed"] == len(env.conditions)
        assert last["end_error"] < 0.01 and last["at_rest"]
        assert last["min_clearance"] >= 0.02  # surface gap: at least 2 cm from obstacles and walls
        # position tracking: the sensed path follows the plan closely (stiff servos)
        ref = env.task.position(np.linspace(0, 1, 2001))
        dev = np.min(np.linalg.norm(traj[:, None, :] - ref[None], axis=-1), axis=1)
        assert dev.max() < 0.02
    env.close()


def test_collision_fails_and_terminates():
    o = Obstacle
    task = RoomTask((o(0.3, 0.14, 0.6, "bottom"), o(0.7, 0.1, 0.6, "top")), (0.1, 0.5), (0.9, 0.5))
    env = RoomEnv(terminate_on_success=False, render_mode=None)
    env.reset(seed=0, options={"task": task})
    for k in range(60):  # slowly to the right at y = 0.5: into the left obstacle (x from 0.23, y up to 0.6)
        obs, reward, terminated, truncated, info = env.step([0.1 + 0.005 * (k + 1), 0.5])
        if terminated:
            break
    assert terminated and not truncated and info["collision"] and not info["is_success"] and reward == 0.0
    assert obs["agent_pos"][0] == pytest.approx(0.23 - AGENT_RADIUS, abs=0.01)  # stopped at the face
    # a wall counts too
    env.reset(seed=0, options={"task": task})
    for _ in range(20):
        *_, terminated, _, info = env.step([0.0, 0.5])
        if terminated:
            break
    assert terminated and info["collision"]
    env.close()


def test_contacts_agree_with_geometry(env):
    """MuJoCo sees the obstacles where they are placed each episode (bounding volumes follow the size)."""
    rng = np.random.default_rng(0)
    for seed in range(10):
        env.reset(seed=seed)
        for p in rng.uniform(-0.01, 1.01, size=(100, 2)):
            d = float(distance_to_obstacles(env.task, p))
            if abs(d - AGENT_RADIUS) < 1e-3:
                continue
            env.data.qpos[:2] = p
            mujoco.mj_forward(env.model, env.data)
            assert env._in_contact() == (d < AGENT_RADIUS), (seed, p, d)


@pytest.mark.parametrize("condition,phases", [("start_end", "0,1"), ("via_end", "v,1"), ("via", "v")])
def test_conditions_encoded(condition, phases):
    env = RoomEnv(condition=condition, render_mode=None)
    ref = RoomEnv(condition="start_end", render_mode=None)
    for seed in range(5):
        obs, _ = env.reset(seed=seed)
        ref.reset(seed=seed)
        assert env.task == ref.task  # the room of a seed does not depend on the condition
        assert obs["environment_state"].shape == (ENV_STATE_DIM,) == (18,)
        decoded = conditions_from_vector(obs["environment_state"], sm_dim=2)
        assert len(decoded) == len(phases.split(","))
        for c, p in zip(decoded, phases.split(",")):
            if p == "v":
                assert VIA_PHASE_RANGE[0] <= c.phase <= VIA_PHASE_RANGE[1]
                assert c.phase == pytest.approx(env.via_phase, abs=1e-6)
            else:
                assert c.phase == float(p)
            assert c.dims == (0, 1)
            np.testing.assert_allclose(c.values, plan_path(env.task, c.phase), atol=1e-5)
        obs2, *_ = env.step(env.task.start)
        np.testing.assert_array_equal(obs["environment_state"], obs2["environment_state"])
        np.testing.assert_allclose(obs["agent_pos"], env.task.start, atol=1e-6)  # starts at the start
    # explicit room and via phase
    task = RoomTask.sample(np.random.default_rng(123))
    obs, _ = env.reset(seed=0, options={"task": task, "via_phase": 0.4})
    assert env.task == task
    if "v" in phases:
        assert conditions_from_vector(obs["environment_state"], sm_dim=2)[0].phase == pytest.approx(0.4)
    env.close()
    ref.close()


def test_reset_deterministic_and_fast(env):
    traj1, _ = run_expert(env, 11, steps=30)
    task1 = env.task
    traj2, _ = run_expert(env, 11, steps=30)
    assert env.task == task1
    np.testing.assert_array_equal(traj1, traj2)
    obs, _ = env.reset(seed=11)
    assert env.observation_space.contains(obs)
    assert env.task_description == "cross the room from left to right around the obstacles"
    t0 = time.perf_counter()
    run_expert(env, 12)
    assert time.perf_counter() - t0 < 0.5  # reset (mask render) + 100 steps; measured ~0.02 s


def test_terminate_on_success_and_truncation():
    env = RoomEnv(condition="via", terminate_on_success=True, render_mode=None)
    traj, infos = run_expert(env, 3, steps=T + 20)
    assert infos[-1]["is_success"] and sum(i["is_success"] for i in infos) == 1
    env = RoomEnv(terminate_on_success=False, max_episode_steps=10, render_mode=None)
    env.reset(seed=0)
    for k in range(10):
        *_, terminated, truncated, _ = env.step(env.task.start)
    assert truncated and not terminated and k == 9


def test_bad_options_raise(env):
    with pytest.raises(ValueError, match="via_end"):
        RoomEnv(condition="bogus")
    with pytest.raises(ValueError, match="image_size"):
        RoomEnv(image_size=8)
    with pytest.raises(ValueError, match="unknown reset options"):
        env.reset(seed=0, options={"mode": 1})
    with pytest.raises(ValueError, match="RoomTask"):
        env.reset(seed=0, options={"task": "room"})
    with pytest.raises(ValueError, match="via_phase"):
        env.reset(seed=0, options={"via_phase": 1.5})
    with pytest.raises(RuntimeError, match="reset"):
        RoomEnv(render_mode=None).step([0.5, 0.5])


def test_render(env):
    env.reset(seed=1)
    img = env.render()
    assert img.shape == (256, 256, 3) and img.dtype == np.uint8
    assert len(np.unique(img.reshape(-1, 3), axis=0)) > 10


def test_env_config():
    cfg = CNMPRoomEnv()
    assert cfg.type == "cnmp_room" and cfg.gym_id == "cnmp/Room-v0" and cfg.fps == 50
    assert cfg.episode_length == 150 and cfg.condition == "start_end"
    assert cfg.features["pixels/top"].shape == (64, 64, 3)
    assert cfg.features["environment_state"].shape == (18,)
    assert cfg.features_map["pixels/top"] == "observation.images.top"
    cfg = CNMPRoomEnv(image_size=32, condition="via")
    assert cfg.features["pixels/top"].shape == (32, 32, 3)
    assert cfg.gym_kwargs["image_size"] == 32 and cfg.gym_kwargs["condition"] == "via"
    with pytest.raises(ValueError, match=r"unknown condition 'bogus' for cnmp_room; choose one of"):
        CNMPRoomEnv(condition="bogus")
    with pytest.raises(ValueError, match="image_size"):
        CNMPRoomEnv(image_size=8)
    env = gym.make(cfg.gym_id, disable_env_checker=True, **cfg.gym_kwargs)
    try:
        assert env.get_wrapper_attr("_max_episode_steps") == 150
        obs, _ = env.reset(seed=0)
        assert obs["pixels"]["top"].shape == (32, 32, 3)
    finally:
        env.close()


def test_lerobot_preprocess_observation(env):
    from lerobot.envs.utils import preprocess_observation

    obs, _ = env.reset(seed=5)
    out = preprocess_observation(obs)
    img = out["observation.images.top"]
    assert tuple(img.shape) == (1, 3, 64, 64) and str(img.dtype) == "torch.float32"
    assert float(img.min()) >= 0.0 and float(img.max()) <= 1.0
    np.testing.assert_allclose(img[0].numpy(), obs["pixels"]["top"].transpose(2, 0, 1) / 255.0)
    assert tuple(out["observation.environment_state"].shape) == (1, 18)
    assert tuple(out["observation.state"].shape) == (1, 2)

"""Tests of the UR10 pick-and-place sim (CNMP paper, Sec. IV-C) and its scripted expert."""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco
import numpy as np
import pytest

from lerobot_cnmp.sims.pickplace.env import PickPlaceEnv
from lerobot_cnmp.sims.pickplace.kinematics import home_configuration, reference_trajectory
from lerobot_cnmp.sims.pickplace.model import TARGET_HALF, TARGET_XY
from lerobot_cnmp.sims.pickplace.planner import (
    PAPER_EXTRAPOLATION,
    PAPER_INTERPOLATION,
    PAPER_TRAIN_GRID,
    PHASE_STEPS,
    TRAIN_OBJECT_RANGE,
    TRAIN_OBSTACLE_RANGE,
    grasp_height,
    is_extrapolation,
)
from lerobot_cnmp.sims.pickplace.expert import PickPlaceExpert

T = 200


@pytest.fixture(scope="module")
def env():
    e = PickPlaceEnv(render_mode=None, terminate_on_success=False)
    yield e
    e.close()


def rollout(env: PickPlaceEnv, task_params, actions=None, steps: int = T, seed: int = 0):
    """Run ``actions`` (default: the expert's) from a reset; returns per-step obs, actions, infos, rel.

    ``rel`` is the object's position relative to the tool point after each step (both from the same
    kinematics pass), in metres.
    """
    obs, info = env.reset(seed=seed, options={"task_params": task_params})
    if actions is None:
        expert = PickPlaceExpert(env, demo_length=T)
        expert.reset()
        actions = np.stack([expert.act(k) for k in range(steps)])
    states, infos, rel = [obs["agent_pos"]], [info], []
    for a in actions[:steps]:
        obs, _, terminated, truncated, info = env.step(a)
        states.append(obs["agent_pos"])
        infos.append(info)
        rel.append(env.data.body("object").xpos - env.data.site("tcp").xpos)
        if terminated or truncated:
            break
    return np.array(states), np.asarray(actions), infos, np.array(rel)


@pytest.mark.parametrize("task_params", PAPER_TRAIN_GRID + PAPER_INTERPOLATION)
def test_expert_succeeds(env, task_params):
    states, actions, infos, rel = rollout(env, task_params)
    last = infos[-1]
    assert last["is_success"], last
    assert not any(i["wall_contact"] for i in infos)
    assert last["lifted"] and last["over_wall"] and last["released"] and last["object_on_target"]
    # success only once the object was put down and let go
    first = next(k for k, i in enumerate(infos) if i["is_success"])
    assert first > PHASE_STEPS["placed"]
    # the servos track the commanded joints closely (state after step k vs command k)
    err = np.abs(states[1:, :6] - actions[: len(states) - 1, :6])
    assert np.degrees(err.max()) < 0.2
    # the object does not slip in the gripper while carried
    carry = rel[PHASE_STEPS["lifted"] : PHASE_STEPS["arc_end"]]
    assert np.abs(carry - carry[0]).max() < 0.002
    assert np.all(np.abs(env.object_pos[:2] - TARGET_XY) < TARGET_HALF)


@pytest.mark.parametrize("task_params", PAPER_EXTRAPOLATION)
def test_extrapolated_heights_run(env, task_params):
    ref = reference_trajectory(task_params)
    assert ref.shape == (T, 7) and np.all(np.isfinite(ref))
    states, _, infos, _ = rollout(env, task_params)
    assert len(infos) == T + 1 and np.all(np.isfinite(states))
    print(f"extrapolation {task_params}: success={infos[-1]['is_success']}")


def test_extrapolation_is_flagged_not_refused():
    assert not any(is_extrapolation(g) for g in (*PAPER_TRAIN_GRID, *PAPER_INTERPOLATION))
    assert all(is_extrapolation(g) for g in PAPER_EXTRAPOLATION)
    assert is_extrapolation((1.5, 4.0)) and is_extrapolation((4.0, 8.5))


def test_grasp_height_is_linear_over_the_trained_range():
    """No kink between the demos' object heights (2 and 6 cm): a model can interpolate it."""
    h = np.linspace(2.0, 6.0, 41)
    z = np.array([grasp_height(v) for v in h])
    residual = z - np.polyval(np.polyfit(h, z, 1), h)
    assert np.abs(residual).max() < 1e-4  # within 0.1 mm of a straight line (the clamp's tail at 2 cm)
    assert grasp_height(1.0) >= 0.0094  # clamped below the knee: pads stay above the table


def test_object_held_by_friction_only(env):
    m = env.model
    assert m.neq == 0  # no weld / connect constraint anywhere
    obj = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "object")
    assert m.body_parentid[obj] == 0 and m.jnt_type[m.body_jntadr[obj]] == mujoco.mjtJoint.mjJNT_FREE
    # open the gripper in the middle of the carry: the object drops and the episode fails
    gamma = (4.0, 6.0)
    actions = reference_trajectory(gamma).astype(np.float32)
    k_open = (PHASE_STEPS["lifted"] + PHASE_STEPS["arc_end"]) // 2 - 10
    actions[k_open:, 6] = 0.0
    _, _, infos, _ = rollout(env, gamma, actions)
    assert infos[k_open]["lifted"]
    assert not any(i["is_success"] for i in infos)
    assert not infos[-1]["object_on_target"]
    assert env.object_pos[2] < 0.04 / 2 + 0.005  # back down on the table
    assert env.object_pos[1] < 0.0  # on the pick side of the wall


@pytest.mark.parametrize("task_params", [(2.0, 8.0), (6.0, 4.0)])
def test_trajectory_through_wall_fails(env, task_params):
    # arc apex with the object's bottom at the height of the carry, far below the wall top
    actions = reference_trajectory(task_params, clearance=-task_params[1] / 100.0)
    _, _, infos, _ = rollout(env, task_params, actions)
    assert infos[-1]["wall_contact"]
    assert not infos[-1]["over_wall"]
    assert not any(i["is_success"] for i in infos)


def test_bad_reset_options_raise(env):
    with pytest.raises(ValueError, match="color"):
        env.reset(seed=0, options={"color": 1})
    with pytest.raises(ValueError, match="task_param"):
        env.reset(seed=0, options={"task_param": (2, 2)})
    with pytest.raises(ValueError, match="obstacle height"):
        env.reset(seed=0, options={"task_params": (2.0, 30.0)})
    with pytest.raises(ValueError, match="object height"):
        env.reset(seed=0, options={"task_params": (0.0, 4.0)})
    with pytest.raises(ValueError, match="two"):
        env.reset(seed=0, options={"task_params": (2.0, 4.0, 6.0)})
    with pytest.raises(ValueError, match="render_mode"):
        PickPlaceEnv(render_mode="human")
    # keys LeRobot adds are accepted
    obs, _ = env.reset(seed=0, options={"lerobot_new_rollout": True, "task_params": (3, 5)})
    np.testing.assert_allclose(obs["environment_state"], [3.0, 5.0])


def test_reset_sampling_observation_and_no_leak(env):
    gammas = []
    for seed in range(20):
        obs, info = env.reset(seed=seed)
        gammas.append(obs["environment_state"])
        assert obs["agent_pos"].shape == (7,) and obs["agent_pos"].dtype == np.float32
        assert obs["environment_state"].shape == (2,) and obs["environment_state"].dtype == np.float32
        np.testing.assert_allclose(obs["agent_pos"][:6], home_configuration(), atol=1e-6)
        assert obs["agent_pos"][6] == 0.0  # open
        assert not info["is_success"] and not info["wall_contact"] and not info["lifted"]
    gammas = np.array(gammas)
    assert np.all((gammas[:, 0] >= TRAIN_OBJECT_RANGE[0]) & (gammas[:, 0] <= TRAIN_OBJECT_RANGE[1]))
    assert np.all((gammas[:, 1] >= TRAIN_OBSTACLE_RANGE[0]) & (gammas[:, 1] <= TRAIN_OBSTACLE_RANGE[1]))
    assert gammas.std(axis=0).min() > 0.5
    fixed = PickPlaceEnv(task_params=(3.0, 6.0), render_mode=None)
    for seed in range(2):
        np.testing.assert_allclose(fixed.reset(seed=seed)[0]["environment_state"], [3.0, 6.0])
    with pytest.raises(ValueError, match="object height"):
        PickPlaceEnv(task_params=(20.0, 6.0))
    obs_a, _ = env.reset(seed=7)
    obs_b, _ = env.reset(seed=7)
    np.testing.assert_array_equal(obs_a["environment_state"], obs_b["environment_state"])

    # an episode after another gamma is identical to one in a fresh env
    fresh = PickPlaceEnv(render_mode=None, terminate_on_success=False)
    rollout(env, (9.0, 11.0), steps=120)
    a, _, _, _ = rollout(env, (2.0, 2.0), steps=120)
    b, _, _, _ = rollout(fresh, (2.0, 2.0), steps=120)
    np.testing.assert_array_equal(a, b)


def test_reference_trajectory_shape_and_continuity():
    ref = reference_trajectory((3.0, 6.0))
    assert ref.shape == (T, 7) and np.all(np.isfinite(ref))
    np.testing.assert_allclose(ref[0, :6], home_configuration(), atol=1e-9)
    grip = ref[:, 6]
    assert grip.min() >= 0.0 and grip.max() <= 1.0
    assert grip[0] == 0.0 and grip[-1] == 0.0
    assert np.all(grip[PHASE_STEPS["closed"] : PHASE_STEPS["placed"] + 1] == 1.0)
    # smooth in time: no joint moves more than 2.5 deg per 20 ms step
    assert np.degrees(np.abs(np.diff(ref[:, :6], axis=0)).max()) < 2.5
    # continuous in gamma: a 1 mm change of either height moves no joint by 1 deg or more
    for gamma in [(2.0, 2.0), (2.0, 8.0), (6.0, 4.0), (4.0, 7.0), (9.0, 11.0)]:
        base = reference_trajectory(gamma)
        for d in [(0.1, 0.0), (0.0, 0.1)]:
            other = reference_trajectory((gamma[0] + d[0], gamma[1] + d[1]))
            assert np.degrees(np.abs(other[:, :6] - base[:, :6]).max()) < 1.0
    # the expert replays it, holding the last row
    env = PickPlaceEnv(render_mode=None)
    env.reset(seed=0, options={"task_params": (3.0, 6.0)})
    expert = PickPlaceExpert(env, demo_length=T)
    expert.reset()
    np.testing.assert_allclose(expert.act(10), ref[10], atol=1e-6)
    np.testing.assert_allclose(expert.act(T + 30), ref[-1], atol=1e-6)


def test_terminate_on_success_and_truncation():
    env = PickPlaceEnv(render_mode=None, terminate_on_success=True, max_episode_steps=250)
    _, _, infos, _ = rollout(env, (3.0, 3.0), steps=T)
    assert infos[-1]["is_success"] and sum(i["is_success"] for i in infos) == 1
    env = PickPlaceEnv(render_mode=None, terminate_on_success=False, max_episode_steps=5)
    env.reset(seed=0)
    hold = np.concatenate([home_configuration(), [0.0]]).astype(np.float32)
    for k in range(5):
        _, _, terminated, truncated, _ = env.step(hold)
    assert truncated and not terminated


def test_render():
    env = PickPlaceEnv(render_size=128)
    env.reset(seed=1)
    img = env.render()
    env.close()
    assert img.shape == (128, 128, 3) and img.dtype == np.uint8
    assert img.std() > 5
    assert len(np.unique(img.reshape(-1, 3), axis=0)) > 50
    assert PickPlaceEnv(render_mode=None).render() is None

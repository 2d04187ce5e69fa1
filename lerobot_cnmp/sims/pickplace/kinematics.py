"""The arm's kinematics: the scene's model for IK, damped-least-squares IK of the tool pose on MuJoCo site
Jacobians, the home configuration, and the expert's joint-space reference (its Cartesian plan solved point by
point, warm-started along the path)."""

from __future__ import annotations

import functools

import mujoco
import numpy as np

from lerobot_cnmp.sims.pickplace.model import JOINT_LIMITS, JOINT_NAMES, MJCF
from lerobot_cnmp.sims.pickplace.planner import DEMO_LENGTH, HOME_TCP, TOOL_ROT, WALL_CLEARANCE, tcp_plan

_HOME_SEED = np.array([np.pi, -np.pi / 2, np.pi / 2, -np.pi / 2, -np.pi / 2, 0.0])


@functools.lru_cache(maxsize=1)
def kinematic_model() -> mujoco.MjModel:
    """The scene's model, used for IK only (the arm's kinematics do not depend on gamma)."""
    model = mujoco.MjModel.from_xml_string(MJCF)
    # the IK addresses the arm as qpos[:6] / dofs [:6]
    for i, name in enumerate(JOINT_NAMES):
        j = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)
        assert model.jnt_qposadr[j] == i and model.jnt_dofadr[j] == i, "arm joints must come first"
    return model


def ik(model, data, site_id, target_pos, target_rot, q0, tol=1e-10, max_iter=100, damping=1e-4):
    """Damped-least-squares IK of the 6-DoF tool pose from ``q0``; returns ``(q, residual)``."""
    q = np.array(q0, dtype=np.float64)
    jacp = np.zeros((3, model.nv))
    jacr = np.zeros((3, model.nv))
    lam2 = damping**2
    err = np.inf
    for _ in range(max_iter):
        data.qpos[:6] = q
        mujoco.mj_kinematics(model, data)
        mujoco.mj_comPos(model, data)
        rot = data.site_xmat[site_id].reshape(3, 3)
        e = np.concatenate(
            [
                target_pos - data.site_xpos[site_id],
                0.5 * sum(np.cross(rot[:, i], target_rot[:, i]) for i in range(3)),
            ]
        )
        err = float(np.linalg.norm(e))
        if err < tol:
            break
        mujoco.mj_jacSite(model, data, jacp, jacr, site_id)
        J = np.vstack([jacp[:, :6], jacr[:, :6]])
        q = q + J.T @ np.linalg.solve(J @ J.T + lam2 * np.eye(6), e)
    return q, err


@functools.lru_cache(maxsize=1)
def home_configuration() -> np.ndarray:
    """Joint angles of the home pose: tool point at ``HOME_TCP``, pointing down."""
    model = kinematic_model()
    data = mujoco.MjData(model)
    sid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, "tcp")
    q, err = ik(model, data, sid, HOME_TCP, TOOL_ROT, _HOME_SEED, max_iter=500, damping=1e-3)
    if err > 1e-8:  # pragma: no cover - constants are fixed
        raise RuntimeError(f"home IK did not converge (residual {err:.3g})")
    q.setflags(write=False)
    return q


def reference_trajectory(
    task_params, demo_length: int = DEMO_LENGTH, clearance: float = WALL_CLEARANCE
) -> np.ndarray:
    """The expert's joint-space reference for gamma (cm): float64 ``[T, 7]`` (6 joints in rad, gripper).

    Each point of :func:`tcp_plan` is solved by IK warm-started from the previous one (the first from
    :func:`home_configuration`), so the trajectory is a smooth, continuous function of gamma.
    """
    pos, grip = tcp_plan(task_params, demo_length, clearance)
    model = kinematic_model()
    data = mujoco.MjData(model)
    sid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, "tcp")
    q = home_configuration().copy()
    out = np.zeros((len(pos), 7))
    for t, p in enumerate(pos):
        q, err = ik(model, data, sid, p, TOOL_ROT, q)
        if err > 1e-6:
            raise RuntimeError(f"IK failed at step {t} for task_params {task_params} (residual {err:.3g})")
        out[t, :6] = q
    if np.any(out[:, :6] < JOINT_LIMITS[:, 0]) or np.any(out[:, :6] > JOINT_LIMITS[:, 1]):
        raise RuntimeError(f"reference for task_params {task_params} leaves the joint limits")
    out[:, 6] = grip
    return out

"""MuJoCo pick-and-place sim with a UR10-like arm (CNMP paper, Sec. IV-C).

A 6-DoF arm with the UR10's published DH kinematics and a parallel two-finger gripper picks a box whose
height varies and places it on a target area beyond a thin wall whose height varies, carrying it along an
arc over the wall, as in the pick-and-place experiment of Seker et al. (RSS 2019, Fig. 7-8, Table I). The
task parameters are ``gamma = (object height, obstacle height)`` in **centimetres**; the paper trains on
``gamma_object in {2, 6}`` x ``gamma_obstacle in {2, 4, 6, 8}`` (``PAPER_TRAIN_GRID``) and tests inside
(``PAPER_INTERPOLATION``) and outside (``PAPER_EXTRAPOLATION``) that range (:mod:`lerobot_cnmp.sims.pickplace.planner`).

The sim is split by concept: :mod:`~lerobot_cnmp.sims.pickplace.model` (the MJCF scene and its constants),
:mod:`~lerobot_cnmp.sims.pickplace.planner` (γ and the expert's Cartesian plan),
:mod:`~lerobot_cnmp.sims.pickplace.kinematics` (IK and the joint-space reference),
:mod:`~lerobot_cnmp.sims.pickplace.control` (the servo step) and this env.

Layout (metres, world frame, table top at z = 0): arm base (DH frame 0) at the origin on the table; pick
spot at ``PICK_XY`` = (0.70, -0.25), wall (0.40 long in x, 0.02 thick) centred at (0.70, 0.00), target area
(0.10 x 0.10, green) centred at ``TARGET_XY`` = (0.70, 0.25). The object is a 4 x 4 cm box of mass 0.15 kg.

Action (7 floats): the six joint position targets (radians, base .. wrist3) and a gripper command in [0, 1]
(0 open, 1 closed). Observation: ``agent_pos`` = the six measured joint angles and the measured gripper
closure in the same [0, 1] convention (holding the 4 cm box reads about 0.71); ``environment_state`` =
gamma (cm), float32 [2] (the vector key LeRobot's rollout passes on to policies; the env config's
preprocessor renames it ``observation.task_params``, the dataset feature).
Control at 50 Hz (10 physics steps of 2 ms). Each arm joint is a stiff servo (position gain plus damping
towards a commanded velocity): over a control step the target ramps from the previous command to the new
one (rate-limited to the UR10's joint speeds) with the ramp's velocity fed forward, so the joints reach the
command at the end of the step (expert tracking error < 0.05 deg). Links are gravity compensated. The
fingers are position servos (about 15 N squeeze, 25 N force limit) driven by the one gripper command. The
grasp is physical: the box is held only by the friction of the finger pads (condim 4, friction 1.5,
stiff solref 0.004) squeezing it, with no weld or attachment. The integrator is semi-implicit Euler with
the servo damping explicit: with implicit damping MuJoCo's contact solver does not see the damped arm
dynamics and the box creeps in the grasp by a few millimetres during fast carries.

Success (``info["is_success"]``, every step): the object was lifted off the table, carried over the wall
(it crossed the wall's footprint above the wall top) with no contact at all between the wall and the
arm, gripper or object so far, released (gripper open, object touching no part of the robot) and is at
rest, upright, on the target area.

:func:`~lerobot_cnmp.sims.pickplace.kinematics.reference_trajectory` computes the scripted expert's joint
trajectory for any gamma without stepping
the sim: a Cartesian plan of the gripper's tool point converted to joints by damped-least-squares IK on
MuJoCo site Jacobians, warm-started along the path from the fixed home configuration.
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco  # noqa: E402
import numpy as np  # noqa: E402
from gymnasium import spaces  # noqa: E402

from lerobot_cnmp.sims.base import MujocoSimEnv, contacts_with  # noqa: E402
from lerobot_cnmp.sims.pickplace.control import servo_control_step  # noqa: E402
from lerobot_cnmp.sims.pickplace.kinematics import home_configuration  # noqa: E402
from lerobot_cnmp.sims.pickplace.model import (  # noqa: E402
    ARM_POS_CTRL,
    ARM_VEL_CTRL,
    CONTROL_FPS,
    FINGER_CLOSED,
    FINGER_CTRL,
    FINGER_OPEN,
    JOINT_LIMITS,
    JOINT_NAMES,
    MJCF,
    OBJECT_HALF_WIDTH,
    OBJECT_MASS,
    PICK_XY,
    TABLE_TOP,
    TARGET_HALF,
    TARGET_XY,
    WALL_HALF_LENGTH,
    WALL_HALF_THICKNESS,
    WALL_XY,
)
from lerobot_cnmp.sims.pickplace.planner import (  # noqa: E402
    TRAIN_OBJECT_RANGE,
    TRAIN_OBSTACLE_RANGE,
    check_task_params,
)

# Success thresholds.
LIFT_THRESHOLD = 0.015  # object bottom above the table to count as lifted
REST_HEIGHT_TOL = 0.005
REST_SPEED_TOL = 0.05
UPRIGHT_COS = np.cos(np.deg2rad(15.0))
RELEASED_GRIPPER = 0.5  # measured closure below this counts as open


class PickPlaceEnv(MujocoSimEnv):
    """UR10-like arm picking a box and placing it beyond a wall; see the module docstring.

    Args:
        task_params: a fixed gamma ``(object_cm, obstacle_cm)`` for the resets that do not set one; None
            (default) draws gamma uniformly from the training range at each reset.
        render_mode: ``"rgb_array"`` or None.
        render_size: side of the square rendered image, pixels.
        terminate_on_success: end the episode (``terminated=True``) as soon as it is successful.
        max_episode_steps: if given, the env truncates itself at this many steps (``gym.make`` normally
            handles this through its ``TimeLimit`` wrapper instead).

    ``reset(options=...)`` accepts ``{"task_params": (object_cm, obstacle_cm)}``; without it gamma is the
    constructor's ``task_params`` or, if that is None, drawn uniformly from the training range (object in
    [2, 6] cm, obstacle in [2, 8] cm).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": CONTROL_FPS}
    camera = "scene"

    def __init__(
        self,
        task_params=None,
        render_mode: str | None = "rgb_array",
        render_size: int = 256,
        terminate_on_success: bool = True,
        max_episode_steps: int | None = None,
    ):
        self.fixed_task_params = None if task_params is None else check_task_params(task_params)
        self._init_options(render_mode, render_size, terminate_on_success, max_episode_steps)

        self.model = mujoco.MjModel.from_xml_string(MJCF)
        self.data = mujoco.MjData(self.model)
        m = self.model

        def gid(name):
            return mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, name)

        self._wall_gid = gid("wall")
        self._table_gid = gid("table")
        self._object_gid = gid("object")
        self._object_bid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "object")
        base_bid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "base_link")
        robot_bodies = [b for b in range(m.nbody) if b == base_bid or self._is_descendant(b, base_bid)]
        self._robot_geom_mask = np.isin(m.geom_bodyid, robot_bodies)
        self._object_qadr = m.jnt_qposadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, "object")]
        self._object_vadr = m.jnt_dofadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, "object")]
        self._arm_qadr = np.array(
            [m.jnt_qposadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, n)] for n in JOINT_NAMES]
        )
        self._finger_qadr = np.array(
            [m.jnt_qposadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, f"finger_{s}")] for s in ("left", "right")]
        )

        self.observation_space = spaces.Dict(
            {
                "agent_pos": spaces.Box(-np.inf, np.inf, shape=(7,), dtype=np.float32),
                "environment_state": spaces.Box(-np.inf, np.inf, shape=(2,), dtype=np.float32),
            }
        )
        low = np.concatenate([JOINT_LIMITS[:, 0], [0.0]]).astype(np.float32)
        high = np.concatenate([JOINT_LIMITS[:, 1], [1.0]]).astype(np.float32)
        self.action_space = spaces.Box(low, high, dtype=np.float32)
        self.task_params: np.ndarray | None = None

    def _is_descendant(self, body: int, ancestor: int) -> bool:
        while body > 0:
            body = int(self.model.body_parentid[body])
            if body == ancestor:
                return True
        return False

    # --- public helpers ------------------------------------------------------------------------------
    @property
    def task_description(self) -> str:
        return "pick up the box and place it on the green target beyond the wall"

    @property
    def task(self) -> str:
        """LeRobot's rollout looks this attribute up in every sub-env (async vector envs fail without it)."""
        return self.task_description

    @property
    def object_height(self) -> float:
        """Object height in metres."""
        return float(self.task_params[0]) / 100.0

    @property
    def wall_height(self) -> float:
        """Wall height in metres."""
        return float(self.task_params[1]) / 100.0

    @property
    def object_pos(self) -> np.ndarray:
        return self.data.qpos[self._object_qadr : self._object_qadr + 3].copy()

    def gripper_state(self) -> float:
        """Measured gripper closure in [0, 1] (0 fully open, 1 at the closed command)."""
        s = float(np.mean(self.data.qpos[self._finger_qadr]))
        return float(np.clip((FINGER_OPEN - s) / (FINGER_OPEN - FINGER_CLOSED), 0.0, 1.0))

    # --- gym API -------------------------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        options = dict(options or {})
        # Keys LeRobot's rollout adds itself (e.g. "lerobot_new_rollout") are not ours to check.
        unknown = {k for k in options if not str(k).startswith("lerobot_")} - {"task_params"}
        if unknown:
            raise ValueError(f"unknown reset options {sorted(map(str, unknown))}; known: ['task_params']")
        if options.get("task_params") is not None:
            gamma = check_task_params(options["task_params"])
        elif self.fixed_task_params is not None:
            gamma = self.fixed_task_params.copy()
        else:
            gamma = np.array(
                [self.np_random.uniform(*TRAIN_OBJECT_RANGE), self.np_random.uniform(*TRAIN_OBSTACLE_RANGE)]
            )
        self.task_params = gamma
        self._apply_geometry()

        m, d = self.model, self.data
        mujoco.mj_resetData(m, d)
        home = home_configuration()
        d.qpos[self._arm_qadr] = home
        d.qpos[self._finger_qadr] = FINGER_OPEN
        d.qpos[self._object_qadr : self._object_qadr + 7] = [*PICK_XY, TABLE_TOP + self.object_height / 2, 1, 0, 0, 0]
        d.ctrl[ARM_POS_CTRL] = home
        d.ctrl[ARM_VEL_CTRL] = 0.0
        d.ctrl[FINGER_CTRL] = FINGER_OPEN
        self._last_command = np.array(home, dtype=np.float64)
        mujoco.mj_forward(m, d)
        self._step = 0
        self._wall_contact = False
        self._lifted = False
        self._over_wall = False
        self._update_progress()
        return self._obs(), self._info()

    def step(self, action):
        if self.task_params is None:
            raise RuntimeError("call reset() before step()")
        action = np.asarray(action, dtype=np.float64).reshape(7)
        action = np.clip(action, self.action_space.low, self.action_space.high)
        self.data.ctrl[FINGER_CTRL] = FINGER_OPEN + action[6] * (FINGER_CLOSED - FINGER_OPEN)
        self._last_command = servo_control_step(
            self.model, self.data, self._last_command, action[:6], self._update_progress
        )
        self._step += 1
        return self._step_result()

    # --- internals -----------------------------------------------------------------------------------
    def _apply_geometry(self):
        """Object and wall sizes of this episode's gamma (the model fields depend only on gamma)."""
        m = self.model
        w, h2 = OBJECT_HALF_WIDTH, self.object_height / 2
        g = self._object_gid
        m.geom_size[g] = [w, w, h2]
        m.geom_rbound[g] = np.sqrt(2 * w * w + h2 * h2)
        m.geom_aabb[g] = [0.0, 0.0, 0.0, w, w, h2]
        b = self._object_bid
        m.body_inertia[b] = OBJECT_MASS / 3.0 * np.array([w * w + h2 * h2, w * w + h2 * h2, 2 * w * w])
        g = self._wall_gid
        wh2 = self.wall_height / 2
        m.geom_size[g] = [WALL_HALF_LENGTH, WALL_HALF_THICKNESS, wh2]
        m.geom_pos[g] = [*WALL_XY, TABLE_TOP + wh2]
        m.geom_rbound[g] = np.sqrt(WALL_HALF_LENGTH**2 + WALL_HALF_THICKNESS**2 + wh2 * wh2)
        m.geom_aabb[g] = [0.0, 0.0, 0.0, WALL_HALF_LENGTH, WALL_HALF_THICKNESS, wh2]
        mujoco.mj_setConst(m, self.data)

    def _contacts_with(self, gid: int) -> np.ndarray:
        """Geom ids in contact with geom ``gid`` now."""
        return contacts_with(self.data, gid)

    def _object_bottom(self) -> float:
        return float(self.data.qpos[self._object_qadr + 2]) - self.object_height / 2 - TABLE_TOP

    def _update_progress(self):
        if not self._wall_contact and len(self._contacts_with(self._wall_gid)):
            self._wall_contact = True
        bottom = self._object_bottom()
        if not self._lifted and bottom > LIFT_THRESHOLD and self._table_gid not in self._contacts_with(
            self._object_gid
        ):
            self._lifted = True
        if not self._over_wall:
            x, y = self.data.qpos[self._object_qadr : self._object_qadr + 2]
            over_x = abs(x - WALL_XY[0]) <= WALL_HALF_LENGTH + OBJECT_HALF_WIDTH
            over_y = abs(y - WALL_XY[1]) <= WALL_HALF_THICKNESS + OBJECT_HALF_WIDTH
            if over_x and over_y and bottom > self.wall_height:
                self._over_wall = True

    def _object_on_target(self) -> bool:
        d = self.data
        pos = d.qpos[self._object_qadr : self._object_qadr + 3]
        in_xy = bool(np.all(np.abs(pos[:2] - TARGET_XY) <= TARGET_HALF))
        resting = abs(self._object_bottom()) <= REST_HEIGHT_TOL
        z_axis = d.xmat[self._object_bid].reshape(3, 3)[:, 2]
        upright = z_axis[2] >= UPRIGHT_COS
        still = float(np.linalg.norm(d.qvel[self._object_vadr : self._object_vadr + 3])) <= REST_SPEED_TOL
        return in_xy and resting and upright and still

    def _released(self) -> bool:
        touching = self._contacts_with(self._object_gid)
        return self.gripper_state() < RELEASED_GRIPPER and not bool(np.any(self._robot_geom_mask[touching]))

    def _obs(self) -> dict:
        q = np.concatenate([self.data.qpos[self._arm_qadr], [self.gripper_state()]])
        gamma = self.task_params.astype(np.float32)
        return {"agent_pos": q.astype(np.float32), "environment_state": gamma}

    def _info(self) -> dict:
        on_target = self._object_on_target()
        released = self._released()
        success = self._lifted and self._over_wall and not self._wall_contact and released and on_target
        return {
            "is_success": bool(success),
            "wall_contact": bool(self._wall_contact),
            "object_on_target": bool(on_target),
            "lifted": bool(self._lifted),
            "over_wall": bool(self._over_wall),
            "released": bool(released),
        }

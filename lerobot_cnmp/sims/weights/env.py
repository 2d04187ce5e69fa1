"""MuJoCo sensorimotor-classification sim: pick a container, place it by shape x weight (CNMP paper, Sec. IV-D).

The UR10-like arm, two-finger gripper, joint servos and IK of :mod:`lerobot_cnmp.sims.pickplace` (imported,
not copied), with a wrist force/torque sensor between the last link (wrist3) and the gripper, pick a
container from the middle of the table and place it on one of four target zones depending on its shape
and weight category, as in Seker et al. (RSS 2019, Fig. 9-11). Nothing in the observation names the class:
a policy has to infer the shape from the finger joint positions once the fingers close on the container and
the weight from the F/T readings once it is lifted.

Layout (metres, world frame, table top at z = 0, arm base at the origin): pick spot ``PICK_XY`` =
(0.70, -0.20); four 12 x 12 cm zones on a 2 x 2 grid beyond it, ``ZONE_XY[zone]`` with
``zone = 2 * shape + weight_category``: the shape selects the row (x = 0.55 narrow, 0.85 wide), the weight
the column (y = 0.15 light, 0.40 heavy).

Containers (:data:`SHAPES`): shape 0 is a 4 x 4 x 6 cm box, shape 1 a 6 x 6 x 6 cm cube; the fingers close
along x, so a grasped container holds each finger joint at 0.020 m (shape 0) or 0.030 m (shape 1).
Weight categories: light 0.15-0.35 kg, heavy 0.65-0.95 kg (threshold :data:`HEAVY_THRESHOLD` = 0.5 kg);
:data:`DEMO_MASSES` (5 per category, for demonstrations) and :data:`TEST_MASSES` (4 others per category
inside the same ranges). The grasp is physical (friction of the pads, as in pickplace).

SM layout (:data:`SM_NAMES`, 11 floats), used both for the action and for ``agent_pos``:
``[x, y, z, finger_left, finger_right, fx, fy, fz, tx, ty, tz]``:

* ``x, y, z``: the gripper's tool point (the centre between the pads), metres, world frame. Action: the
  target; each control step the env solves pickplace's damped-least-squares IK for it with the tool
  pointing down (``TOOL_ROT``), warm-started from the measured joints, and servos the joints there
  (pickplace's rate-limited servo step). Targets are clipped to the workspace box :data:`WORKSPACE`.
* ``finger_left, finger_right``: finger joint positions, metres from the tool axis to each pad's face
  (0.045 open). The fingers are coupled (a joint equality, as in a parallel gripper), so they move
  together and centre the container between the pads. Action: the opening to go to. The gripper closes
  until contact, like an adaptive gripper: for commands below ``SQUEEZE_FULL_BELOW`` (0.035 m) the finger
  servos' target is the fully closed position (blended smoothly to the command itself at the open
  command), so any closing command holds the container with the servos' force limit (25 N per pad)
  whatever its width, and the fingers then read that width, and commanding the open position opens fully.
* ``fx, fy, fz, tx, ty, tz``: the wrist F/T sensor (MuJoCo ``force`` / ``torque`` sensors on the site
  ``ft`` at the flange, i.e. the load the gripper puts on wrist3), in N and N m, in the sensor frame (z
  along the tool axis: pointing down while working), tared at reset (the gripper's own weight at the home
  pose is removed) and low-pass filtered (first order, time constant :data:`FT_TAU` = 100 ms, updated at
  every 2 ms physics step). A held container of mass m reads ``fz ~ -m g`` once the lift's acceleration
  has died out. **These entries cannot be commanded: the env ignores them in the action.** They are in
  the action so that the action is the full SM (what a CNMP predicts); the expert fills them with the
  reading it observed before the step.

Control at 50 Hz (10 physics steps of 2 ms), nominal demonstrations of 200 steps (4 s),
``DEFAULT_MAX_EPISODE_STEPS`` = 260.

Perturbation ``"weight_switch"`` (the paper's Fig. 11, marbles poured into the carried box): at a step drawn
uniformly from :data:`SWITCH_WINDOW` at reset (during the nominal transport: after the lift, before the
descent) :data:`SWITCH_ADDED_MASS` (0.5 kg) is added to the container, so a light container (0.15-0.35 kg)
becomes a heavy one (0.65-0.85 kg). Rule: only light containers switch (adding mass cannot make a heavy
one light); with ``weight_switch`` a reset that does not give the mass draws a light mass from
:data:`TEST_MASSES`, and an explicitly heavy container never switches. The switch is applied once, at the
first step at or after the drawn one where the container is carried: held (lifted, touching both pads,
not the table) with its bottom at least :data:`SWITCH_MIN_HEIGHT` (8 cm; 10 cm while carried) above the
table, i.e. not during the lift's start or the descent (a policy slower than the demos gets it later; one
that is already descending or has released the container by the drawn step gets none, and
``weight_switched`` stays False). ``info["weight_switched"]`` then turns True and ``info["switch_step"]``
gives the index of the first step executed with the new mass (-1 before/without). The target zone,
``info["target_zone"]``, follows the final mass.

Success (``info["is_success"]``, every step): the container was lifted off the table, released (fingers
open, touching no part of the robot) and rests upright, still, with its centre on the zone of its current
shape x weight category.
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco  # noqa: E402
import numpy as np  # noqa: E402
from gymnasium import spaces  # noqa: E402

from lerobot_cnmp.sims.base import MujocoSimEnv, contacts_with  # noqa: E402
from lerobot_cnmp.sims.pickplace.control import servo_control_step  # noqa: E402
from lerobot_cnmp.sims.pickplace.kinematics import home_configuration, ik, kinematic_model  # noqa: E402
from lerobot_cnmp.sims.pickplace.model import (  # noqa: E402
    ARM_POS_CTRL,
    ARM_VEL_CTRL,
    FINGER_CTRL,
    FINGER_OPEN,
    JOINT_LIMITS,
    JOINT_NAMES,
    TABLE_TOP,
)
from lerobot_cnmp.sims.pickplace.planner import TOOL_ROT  # noqa: E402
from lerobot_cnmp.sims.time_law import minimum_jerk  # noqa: E402
from lerobot_cnmp.sims.weights.model import build_model  # noqa: E402
from lerobot_cnmp.sims.weights.task import (  # noqa: E402
    CONTROL_FPS,
    FINGER_SM,
    PERTURBATION_CHOICES,
    PICK_XY,
    POS_SM,
    SHAPES,
    SM_DIM,
    SWITCH_ADDED_MASS,
    SWITCH_MIN_HEIGHT,
    SWITCH_WINDOW,
    TEST_MASSES,
    WEIGHT_CATEGORIES,
    ZONE_HALF,
    ZONE_XY,
    check_mass,
    check_shape,
    target_zone,
    weight_category,
)

WORKSPACE = np.array([[0.25, 1.05], [-0.60, 0.70], [0.01, 0.60]])  # tool-point target box (x, y, z)

# Gripper controller (see the module docstring).
SQUEEZE_FULL_BELOW = 0.035  # m: commands below it close fully (until contact)
FINGER_CMD_RANGE = (0.004, FINGER_OPEN + 0.005)

# Wrist F/T sensor.
FT_TAU = 0.1  # s, first-order low-pass: the static load (the weight) over the arm's inertial transients
FT_BOUND = 1.0e3  # the action space's bound for the (ignored) F/T entries

# Success thresholds.
LIFT_THRESHOLD = 0.015
REST_HEIGHT_TOL = 0.005
REST_SPEED_TOL = 0.05
UPRIGHT_COS = np.cos(np.deg2rad(15.0))
RELEASED_OPENING = 0.5 * (SQUEEZE_FULL_BELOW + FINGER_OPEN)  # both fingers beyond this: open


def finger_servo_target(command):
    """The finger servos' target for a finger opening command (m): fully closed (the joint's lower limit, so
    the pads stop on the container and squeeze it with the force limit) below ``SQUEEZE_FULL_BELOW``, the
    command itself at the open position, blended smoothly in between."""
    c = np.asarray(command, dtype=np.float64)
    w = 1.0 - minimum_jerk((c - SQUEEZE_FULL_BELOW) / (FINGER_OPEN - SQUEEZE_FULL_BELOW))
    return c - w * (c - FINGER_CMD_RANGE[0])


class WeightsEnv(MujocoSimEnv):
    """UR10-like arm placing a container by its shape and weight; see the module docstring.

    Args:
        perturbation: ``"none"`` or ``"weight_switch"`` (0.5 kg added to a light container during transport).
        render_mode: ``"rgb_array"`` or None.
        render_size: side of the square rendered image, pixels.
        terminate_on_success: end the episode (``terminated=True``) as soon as it is successful.
        max_episode_steps: if given, the env truncates itself at this many steps.

    ``reset(options=...)`` accepts ``{"shape": 0 | 1, "mass": kg}`` (either or both); what is not given is
    drawn: the shape uniformly, the mass from :data:`TEST_MASSES` (both categories; light only with
    ``weight_switch``).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": CONTROL_FPS}
    camera = "scene"

    def __init__(
        self,
        perturbation: str = "none",
        render_mode: str | None = "rgb_array",
        render_size: int = 256,
        terminate_on_success: bool = True,
        max_episode_steps: int | None = None,
    ):
        if perturbation not in PERTURBATION_CHOICES:
            raise ValueError(f"unknown perturbation {perturbation!r}; choose one of {PERTURBATION_CHOICES}")
        self.perturbation = perturbation
        self._init_options(render_mode, render_size, terminate_on_success, max_episode_steps)
        self.model = build_model()
        self.data = mujoco.MjData(self.model)
        self._scratch = mujoco.MjData(self.model)  # mj_setConst's workspace when the mass changes mid-episode
        m = self.model

        def oid(kind, name):
            return mujoco.mj_name2id(m, kind, name)

        G, B, J = mujoco.mjtObj.mjOBJ_GEOM, mujoco.mjtObj.mjOBJ_BODY, mujoco.mjtObj.mjOBJ_JOINT
        self._table_gid = oid(G, "table")
        self._object_gid = oid(G, "object")
        self._pad_gids = (oid(G, "pad_left"), oid(G, "pad_right"))
        self._object_bid = oid(B, "object")
        base_bid = oid(B, "base_link")
        robot = [b for b in range(m.nbody) if self._descends(b, base_bid)]
        self._robot_geom_mask = np.isin(m.geom_bodyid, robot)
        self._object_qadr = m.jnt_qposadr[oid(J, "object")]
        self._object_vadr = m.jnt_dofadr[oid(J, "object")]
        self._arm_qadr = np.array([m.jnt_qposadr[oid(J, n)] for n in JOINT_NAMES])
        self._finger_qadr = np.array([m.jnt_qposadr[oid(J, f"finger_{s}")] for s in ("left", "right")])
        self._tcp_sid = oid(mujoco.mjtObj.mjOBJ_SITE, "tcp")
        self._ft_adr = np.concatenate(
            [m.sensor_adr[oid(mujoco.mjtObj.mjOBJ_SENSOR, n)] + np.arange(3) for n in ("ft_force", "ft_torque")]
        )
        # IK on pickplace's kinematic model (same arm, same tool point)
        self._ik_model = kinematic_model()
        self._ik_data = mujoco.MjData(self._ik_model)
        self._ik_sid = mujoco.mj_name2id(self._ik_model, mujoco.mjtObj.mjOBJ_SITE, "tcp")

        self.observation_space = spaces.Dict(
            {"agent_pos": spaces.Box(-np.inf, np.inf, shape=(SM_DIM,), dtype=np.float32)}
        )
        low = np.concatenate([WORKSPACE[:, 0], [FINGER_CMD_RANGE[0]] * 2, [-FT_BOUND] * 6]).astype(np.float32)
        high = np.concatenate([WORKSPACE[:, 1], [FINGER_CMD_RANGE[1]] * 2, [FT_BOUND] * 6]).astype(np.float32)
        self.action_space = spaces.Box(low, high, dtype=np.float32)
        self.shape: int | None = None
        self.mass: float | None = None

    def _descends(self, body: int, ancestor: int) -> bool:
        while body > 0:
            if body == ancestor:
                return True
            body = int(self.model.body_parentid[body])
        return False

    # --- public helpers ------------------------------------------------------------------------------
    @property
    def task_description(self) -> str:
        return "pick up the container and place it on the zone of its shape and weight"

    @property
    def task(self) -> str:
        """LeRobot's rollout looks this attribute up in every sub-env (async vector envs fail without it)."""
        return self.task_description

    @property
    def weight_category(self) -> int:
        return weight_category(self.mass)

    @property
    def target_zone(self) -> int:
        """The zone of the container's current class (changes when the weight switches)."""
        return target_zone(self.shape, self.mass)

    @property
    def object_pos(self) -> np.ndarray:
        return self.data.qpos[self._object_qadr : self._object_qadr + 3].copy()

    def ft_reading(self) -> np.ndarray:
        """The current filtered, tared F/T reading ``[fx, fy, fz, tx, ty, tz]`` (N, N m, sensor frame)."""
        return self._ft.copy()

    def sm(self) -> np.ndarray:
        """The measured SM (float64), the layout of :data:`SM_NAMES`."""
        d = self.data
        return np.concatenate([d.site_xpos[self._tcp_sid], d.qpos[self._finger_qadr], self._ft])

    # --- gym API -------------------------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        options = dict(options or {})
        # Keys LeRobot's rollout adds itself (e.g. "lerobot_new_rollout") are not ours to check.
        known = {"shape", "mass"}
        for key in options:
            if not str(key).startswith("lerobot_") and key not in known:
                raise ValueError(f"unknown reset option {key!r}; known: {sorted(known)}")
        rng = self.np_random
        shape = check_shape(options["shape"]) if options.get("shape") is not None else int(rng.integers(2))
        if options.get("mass") is not None:
            mass = check_mass(options["mass"])
        else:
            cats = ("light",) if self.perturbation == "weight_switch" else WEIGHT_CATEGORIES
            pool = [m for c in cats for m in TEST_MASSES[c]]
            mass = float(pool[int(rng.integers(len(pool)))])
        self.shape, self.mass = shape, mass
        self.initial_mass = mass
        self._apply_container()

        m, d = self.model, self.data
        mujoco.mj_resetData(m, d)
        home = home_configuration()
        d.qpos[self._arm_qadr] = home
        d.qpos[self._finger_qadr] = FINGER_OPEN
        half_h = SHAPES[shape][2]
        d.qpos[self._object_qadr : self._object_qadr + 7] = [*PICK_XY, TABLE_TOP + half_h, 1, 0, 0, 0]
        d.ctrl[ARM_POS_CTRL] = home
        d.ctrl[ARM_VEL_CTRL] = 0.0
        d.ctrl[FINGER_CTRL] = FINGER_OPEN
        self._last_command = np.array(home, dtype=np.float64)
        mujoco.mj_forward(m, d)
        self._tare = d.sensordata[self._ft_adr].copy()  # the gripper's own load at the home pose
        self._ft = np.zeros(6)
        self._step = 0
        self._lifted = False
        self.weight_switched = False
        self.switch_step = -1
        self._switch_at = (
            int(rng.integers(SWITCH_WINDOW[0], SWITCH_WINDOW[1] + 1))
            if self.perturbation == "weight_switch"
            else None
        )
        self._update_progress()
        return self._obs(), self._info()

    def step(self, action):
        if self.shape is None:
            raise RuntimeError("call reset() before step()")
        action = np.asarray(action, dtype=np.float64).reshape(SM_DIM)
        action = np.clip(action, self.action_space.low, self.action_space.high)  # the F/T entries are ignored
        self._maybe_switch_weight()
        d = self.data
        q = d.qpos[self._arm_qadr].copy()
        q_target, _ = ik(self._ik_model, self._ik_data, self._ik_sid, action[POS_SM], TOOL_ROT, q,
                             tol=1e-9, max_iter=50)
        q_target = np.clip(q_target, JOINT_LIMITS[:, 0], JOINT_LIMITS[:, 1])
        d.ctrl[FINGER_CTRL] = finger_servo_target(action[FINGER_SM])
        self._last_command = servo_control_step(self.model, d, self._last_command, q_target, self._substep)
        self._step += 1
        return self._step_result()

    # --- internals -----------------------------------------------------------------------------------
    def _set_object_mass(self, mass: float, data) -> None:
        m = self.model
        w, h = SHAPES[self.shape][1], SHAPES[self.shape][2]
        b = self._object_bid
        m.body_mass[b] = mass
        m.body_inertia[b] = mass / 3.0 * np.array([w * w + h * h, w * w + h * h, 2 * w * w])
        mujoco.mj_setConst(m, data)

    def _apply_container(self) -> None:
        """Size and mass of this episode's container (the model fields depend only on them)."""
        m = self.model
        _, w, h = SHAPES[self.shape]
        g = self._object_gid
        m.geom_size[g] = [w, w, h]
        m.geom_rbound[g] = np.sqrt(2 * w * w + h * h)
        m.geom_aabb[g] = [0.0, 0.0, 0.0, w, w, h]
        self._set_object_mass(self.mass, self.data)

    def _held(self) -> bool:
        touching = set(contacts_with(self.data, self._object_gid).tolist())
        return self._lifted and all(p in touching for p in self._pad_gids) and self._table_gid not in touching

    def _maybe_switch_weight(self) -> None:
        if (
            self._switch_at is None
            or self.weight_switched
            or self._step < self._switch_at
            or self.weight_category != 0
            or self._object_bottom() < SWITCH_MIN_HEIGHT
            or not self._held()
        ):
            return
        self.mass = self.mass + SWITCH_ADDED_MASS
        self._set_object_mass(self.mass, self._scratch)  # not self.data: mj_setConst overwrites its state
        self.weight_switched = True
        self.switch_step = self._step

    def _substep(self) -> None:
        raw = self.data.sensordata[self._ft_adr] - self._tare
        dt = self.model.opt.timestep
        self._ft += (dt / (FT_TAU + dt)) * (raw - self._ft)
        self._update_progress()

    def _object_bottom(self) -> float:
        return float(self.data.qpos[self._object_qadr + 2]) - SHAPES[self.shape][2] - TABLE_TOP

    def _update_progress(self) -> None:
        if not self._lifted and self._object_bottom() > LIFT_THRESHOLD and self._table_gid not in contacts_with(
            self.data, self._object_gid
        ):
            self._lifted = True

    def _zone_of_object(self) -> int:
        """The zone the container's centre is on (-1 if none)."""
        xy = self.data.qpos[self._object_qadr : self._object_qadr + 2]
        inside = np.all(np.abs(ZONE_XY - xy) <= ZONE_HALF, axis=1)
        return int(np.argmax(inside)) if inside.any() else -1

    def _at_rest(self) -> bool:
        d = self.data
        resting = abs(self._object_bottom()) <= REST_HEIGHT_TOL
        upright = d.xmat[self._object_bid].reshape(3, 3)[2, 2] >= UPRIGHT_COS
        still = float(np.linalg.norm(d.qvel[self._object_vadr : self._object_vadr + 3])) <= REST_SPEED_TOL
        return bool(resting and upright and still)

    def _released(self) -> bool:
        touching = contacts_with(self.data, self._object_gid)
        opened = bool(np.all(self.data.qpos[self._finger_qadr] >= RELEASED_OPENING))
        return opened and not bool(np.any(self._robot_geom_mask[touching]))

    def _obs(self) -> dict:
        return {"agent_pos": self.sm().astype(np.float32)}

    def _info(self) -> dict:
        zone = self._zone_of_object()
        released = self._released()
        at_rest = self._at_rest()
        success = self._lifted and released and at_rest and zone == self.target_zone
        return {
            "is_success": bool(success),
            "shape": int(self.shape),
            "mass": float(self.mass),
            "weight_category": int(self.weight_category),
            "target_zone": int(self.target_zone),
            "weight_switched": bool(self.weight_switched),
            "switch_step": int(self.switch_step),
            "object_zone": zone,
            "lifted": bool(self._lifted),
            "released": bool(released),
        }

"""MuJoCo pick-and-place sim with a UR10-like arm (CNMP paper, Sec. IV-C).

A 6-DoF arm with the UR10's published DH kinematics and a parallel two-finger gripper picks a box whose
height varies and places it on a target area beyond a thin wall whose height varies, carrying it along an
arc over the wall, as in the pick-and-place experiment of Seker et al. (RSS 2019, Fig. 7-8, Table I). The
task parameters are ``gamma = (object height, obstacle height)`` in **centimetres**; the paper trains on
``gamma_object in {2, 6}`` x ``gamma_obstacle in {2, 4, 6, 8}`` (:data:`PAPER_TRAIN_GRID`) and tests inside
(:data:`PAPER_INTERPOLATION`) and outside (:data:`PAPER_EXTRAPOLATION`) that range.

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

:func:`reference_trajectory` computes the scripted expert's joint trajectory for any gamma without stepping
the sim: a Cartesian plan of the gripper's tool point converted to joints by damped-least-squares IK on
MuJoCo site Jacobians, warm-started along the path from the fixed home configuration.
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")

import functools  # noqa: E402

import mujoco  # noqa: E402
import numpy as np  # noqa: E402
from gymnasium import spaces  # noqa: E402

from lerobot_cnmp.sims.base import MujocoSimEnv, contacts_with, minimum_jerk  # noqa: E402

# --- constants of the sim ------------------------------------------------------------------------------
CONTROL_FPS = 50
N_SUBSTEPS = 10  # physics steps (dt = 0.002) per control step -> 50 Hz control
DEFAULT_MAX_EPISODE_STEPS = 250
DEMO_LENGTH = 200

# UR10 DH parameters (metres): rows (d, a, alpha) of joints base, shoulder, elbow, wrist1, wrist2, wrist3.
UR10_DH = (
    (0.1273, 0.0, np.pi / 2),
    (0.0, -0.612, 0.0),
    (0.0, -0.5723, 0.0),
    (0.163941, 0.0, np.pi / 2),
    (0.1157, 0.0, -np.pi / 2),
    (0.0922, 0.0, 0.0),
)
JOINT_NAMES = ("base", "shoulder", "elbow", "wrist1", "wrist2", "wrist3")
LINK_MASSES = (7.1, 12.7, 4.27, 2.0, 2.0, 0.365)  # UR10 link masses, kg
JOINT_LIMITS = np.array([[-2 * np.pi, 2 * np.pi]] * 2 + [[-np.pi, np.pi]] + [[-2 * np.pi, 2 * np.pi]] * 3)
JOINT_SPEED_LIMITS = np.deg2rad([120.0, 120.0, 180.0, 180.0, 180.0, 180.0])  # UR10 maximum joint speeds
ARMATURE = (1.0, 1.0, 0.5, 0.1, 0.1, 0.1)  # reflected rotor inertia, kg m^2
# Servo gains: kp = w^2 I, kv = 2 w I with the joint's largest inertia I (armature included) along the
# task's motions, w = 100 rad/s. The targets ramp over each control step with the ramp's velocity fed
# forward, so the servo only has to reject the inertial and contact loads (tracking error < 0.1 deg).
ARM_KP = (3.0e4, 6.6e4, 3.0e4, 1.5e3, 1.2e3, 1.0e3)
ARM_KV = (600.0, 1320.0, 600.0, 30.0, 24.0, 20.0)

ARM_POS_CTRL = slice(0, 6)  # actuator (ctrl) layout
ARM_VEL_CTRL = slice(6, 12)
FINGER_CTRL = slice(12, 14)

# Gripper: two fingers on slide joints; the joint value is the gap from the tool axis to the pad's face.
FINGER_OPEN = 0.045  # pad face 4.5 cm from the axis -> 9 cm gap
FINGER_CLOSED = 0.010  # commanded when closed: 2 cm gap, the 4 cm box stops the pads at 0.02
FINGER_KP = 1500.0  # N/m -> ~15 N squeeze on the 4 cm box
FINGER_KV = 20.0
FINGER_FORCE = 25.0
PAD_HALF = (0.003, 0.0125, 0.008)  # pad half sizes (x thickness, y width, z height)
TCP_OFFSET = 0.14  # flange -> tool centre point (pad centres), along the tool axis
PALM_BOTTOM = 0.07  # flange -> palm bottom (finger roots)

# Scene.
TABLE_TOP = 0.0
PICK_XY = np.array([0.70, -0.25])
TARGET_XY = np.array([0.70, 0.25])
TARGET_HALF = 0.05
WALL_XY = np.array([0.70, 0.0])
WALL_HALF_LENGTH = 0.20  # along x
WALL_HALF_THICKNESS = 0.01  # along y
OBJECT_HALF_WIDTH = 0.02
OBJECT_MASS = 0.15

CAMERA_EYE = (1.55, -1.0, 0.8)
CAMERA_TARGET = (0.45, 0.0, 0.22)

# Task parameters (cm): training range and what the sim accepts.
TRAIN_OBJECT_RANGE = (2.0, 6.0)
TRAIN_OBSTACLE_RANGE = (2.0, 8.0)
OBJECT_HEIGHT_LIMITS = (1.0, 12.0)
OBSTACLE_HEIGHT_LIMITS = (1.0, 15.0)
PAPER_TRAIN_GRID = tuple((o, h) for o in (2.0, 6.0) for h in (2.0, 4.0, 6.0, 8.0))
PAPER_INTERPOLATION = ((3.0, 3.0), (3.0, 6.0), (4.0, 7.0))
PAPER_EXTRAPOLATION = ((7.0, 9.0), (8.0, 10.0), (9.0, 11.0))

# Expert plan (metres). The tool point (TCP) is the centre between the finger pads.
HOME_TCP = np.array([0.45, 0.0, 0.40])
_HOME_SEED = np.array([np.pi, -np.pi / 2, np.pi / 2, -np.pi / 2, -np.pi / 2, 0.0])
GRASP_SLOPE = 0.5  # the grasp height moves with half the object height (linear over the trained range) ...
GRASP_KNEE_CM = 1.6  # ... above this object height; below it (extrapolation only) it is smoothly clamped
GRASP_MIN_Z = 0.0095  # to keep the pads (half height 0.8 cm) above the table
GRASP_CLAMP_SOFTNESS = 0.001
APPROACH_HEIGHT = 0.08  # pre-grasp: this far above the grasp point
CARRY_LIFT = 0.05  # vertical lift before and descent after the arc
WALL_CLEARANCE = 0.05  # arc apex: object bottom this far above the wall top
PLACE_DROP = 0.003  # release with the object bottom this high above the table
RETREAT = 0.08
# Phase knots, in control steps of a 200-step demonstration (scaled for other lengths).
PHASE_STEPS = {
    "start_approach": 8,
    "pregrasp": 50,
    "grasp": 72,
    "closed": 82,
    "start_lift": 86,
    "lifted": 102,
    "arc_end": 150,
    "placed": 166,
    "opened": 176,
    "start_retreat": 180,
    "end": 196,
}
# Tool orientation while working: tool z down, fingers closing along world x.
TOOL_ROT = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])

# Success thresholds.
LIFT_THRESHOLD = 0.015  # object bottom above the table to count as lifted
REST_HEIGHT_TOL = 0.005
REST_SPEED_TOL = 0.05
UPRIGHT_COS = np.cos(np.deg2rad(15.0))
RELEASED_GRIPPER = 0.5  # measured closure below this counts as open


def _lookat_xyaxes(eye, target, up=(0.0, 0.0, 1.0)) -> str:
    eye, target, up = (np.asarray(v, dtype=float) for v in (eye, target, up))
    fwd = target - eye
    fwd /= np.linalg.norm(fwd)
    x = np.cross(fwd, up)
    x /= np.linalg.norm(x)
    y = np.cross(x, fwd)
    return " ".join(f"{v:.5f}" for v in (*x, *y))


def _fmt(*v) -> str:
    return " ".join(f"{float(x):.6g}" for x in v)


def _arm_xml() -> str:
    """Nested link bodies from the DH table: body i+1 sits at Tz(d_i) Tx(a_i) Rx(alpha_i) in body i."""
    (d1, _, _), (_, a2, _), (_, a3, _), (d4, _, _), (d5, _, _), (d6, _, _) = UR10_DH
    geoms = {
        # link1 (shoulder link): base column up to the shoulder axis
        "base": [
            f'<geom name="link1" type="cylinder" fromto="{_fmt(0, 0, 0.045, 0, 0, d1)}" size="0.075" '
            f'mass="{LINK_MASSES[0]}" material="arm"/>'
        ],
        # link2 (upper arm): shoulder housing on the joint axis, beam along x to the elbow
        "shoulder": [
            f'<geom name="shoulder_housing" type="cylinder" fromto="{_fmt(0, 0, -0.085, 0, 0, 0.085)}" '
            'size="0.078" mass="0.5" material="joint"/>',
            f'<geom name="upper_arm" type="capsule" fromto="{_fmt(-0.07, 0, 0, a2 + 0.07, 0, 0)}" '
            f'size="0.056" mass="{LINK_MASSES[1]}" material="arm"/>',
            f'<geom name="elbow_housing" type="cylinder" fromto="{_fmt(a2, 0, -0.07, a2, 0, 0.07)}" '
            'size="0.062" mass="0.3" material="joint"/>',
        ],
        # link3 (forearm): beam to the wrist1 axis, then the wrist offset d4 along it
        "elbow": [
            f'<geom name="forearm" type="capsule" fromto="{_fmt(-0.06, 0, 0, a3 + 0.05, 0, 0)}" '
            f'size="0.045" mass="{LINK_MASSES[2]}" material="arm"/>',
        ],
        "wrist1": [
            f'<geom name="wrist1_housing" type="cylinder" fromto="{_fmt(0, 0, -0.05, 0, 0, d4 + 0.045)}" '
            f'size="0.046" mass="{LINK_MASSES[3]}" material="joint"/>',
        ],
        "wrist2": [
            f'<geom name="wrist2_housing" type="cylinder" fromto="{_fmt(0, 0, -0.045, 0, 0, d5)}" '
            f'size="0.046" mass="{LINK_MASSES[4]}" material="joint"/>',
        ],
        "wrist3": [
            f'<geom name="wrist3_housing" type="cylinder" fromto="{_fmt(0, 0, -0.045, 0, 0, d6)}" '
            f'size="0.046" mass="{LINK_MASSES[5]}" material="arm"/>',
        ],
    }
    rng_attr = [f"{lo:.6g} {hi:.6g}" for lo, hi in JOINT_LIMITS]
    xml = ""
    close = ""
    parent_row = None
    for i, name in enumerate(JOINT_NAMES):
        if parent_row is None:
            pos, quat = (0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0)
        else:
            d, a, alpha = parent_row
            pos, quat = (a, 0.0, d), (np.cos(alpha / 2), np.sin(alpha / 2), 0.0, 0.0)
        xml += (
            f'<body name="{name}_link" pos="{_fmt(*pos)}" quat="{_fmt(*quat)}" gravcomp="1">\n'
            f'  <joint name="{name}" type="hinge" axis="0 0 1" range="{rng_attr[i]}" '
            f'armature="{ARMATURE[i]}" damping="0"/>\n' + "\n".join(geoms[name]) + "\n"
        )
        close += "</body>\n"
        parent_row = UR10_DH[i]
    xml += _gripper_xml(d6=UR10_DH[5][0])
    return xml + close


def _gripper_xml(d6: float) -> str:
    px, py, pz = PAD_HALF
    fz = PALM_BOTTOM
    pad_z = TCP_OFFSET - fz  # pad centre below the finger root
    finger_len = pad_z + pz  # finger root -> pad bottom
    fx = 0.005  # finger beam half thickness
    fingers = ""
    for side, sign in (("left", 1.0), ("right", -1.0)):
        fingers += f"""
      <body name="finger_{side}" pos="0 0 {fz}" gravcomp="1">
        <joint name="finger_{side}" type="slide" axis="{sign:g} 0 0" range="0.004 {FINGER_OPEN + 0.005}"
               damping="2"/>
        <geom name="finger_{side}" type="box" pos="{_fmt(sign * (2 * px + fx), 0, finger_len / 2)}"
              size="{_fmt(fx, 0.01, finger_len / 2)}" mass="0.04" material="finger"/>
        <geom name="pad_{side}" type="box" pos="{_fmt(sign * px, 0, pad_z)}" size="{_fmt(px, py, pz)}"
              mass="0.01" material="pad" class="pad"/>
      </body>"""
    return f"""
    <body name="gripper" pos="0 0 {d6}" gravcomp="1">
      <geom name="coupling" type="cylinder" fromto="0 0 0 0 0 0.02" size="0.04" mass="0.2" material="finger"/>
      <geom name="palm" type="box" pos="0 0 0.045" size="0.065 0.03 0.025" mass="0.6" material="finger"/>
      <site name="tcp" pos="0 0 {TCP_OFFSET}" size="0.006" rgba="1 0.5 0 0.6"/>{fingers}
    </body>
"""


def build_mjcf() -> str:
    """MJCF of the scene. The object and wall sizes are set per episode (:meth:`PickPlaceEnv.reset`)."""
    cam = _lookat_xyaxes(CAMERA_EYE, CAMERA_TARGET)
    # Per arm joint a position servo (stiffness) and a velocity servo (damping towards the commanded
    # velocity): together a PD servo with velocity feed-forward, which tracks a ramp without lag.
    actuators = "\n".join(
        f'    <position name="{n}" joint="{n}" kp="{kp:g}" ctrlrange="{lo:.6g} {hi:.6g}"/>'
        for n, kp, (lo, hi) in zip(JOINT_NAMES, ARM_KP, JOINT_LIMITS, strict=True)
    )
    actuators += "\n" + "\n".join(
        f'    <velocity name="{n}_vel" joint="{n}" kv="{kv:g}"/>' for n, kv in zip(JOINT_NAMES, ARM_KV, strict=True)
    )
    for side in ("left", "right"):
        actuators += (
            f'\n    <position name="finger_{side}" joint="finger_{side}" kp="{FINGER_KP:g}" kv="{FINGER_KV:g}" '
            f'ctrlrange="0 {FINGER_OPEN + 0.005}" forcerange="-{FINGER_FORCE:g} {FINGER_FORCE:g}"/>'
        )
    wx, wy = WALL_XY
    return f"""
<mujoco model="cnmp_pickplace_ur10">
  <compiler angle="radian" autolimits="true"/>
  <option timestep="0.002" integrator="Euler" cone="elliptic" impratio="10"/>
  <visual>
    <global offwidth="1024" offheight="1024"/>
    <headlight ambient="0.45 0.45 0.45" diffuse="0.5 0.5 0.5"/>
  </visual>
  <default>
    <geom contype="2" conaffinity="1" friction="1 0.005 0.0001" condim="3"/>
    <default class="pad">
      <geom condim="4" friction="1.5 0.02 0.0001" solref="0.004 1" solimp="0.95 0.99 0.001"/>
    </default>
    <default class="env">
      <geom contype="1" conaffinity="1"/>
    </default>
  </default>
  <asset>
    <texture name="sky" type="skybox" builtin="gradient" rgb1="0.75 0.82 0.9" rgb2="0.35 0.4 0.45"
             width="64" height="64"/>
    <texture name="grid" type="2d" builtin="checker" rgb1="0.82 0.78 0.72" rgb2="0.78 0.74 0.68"
             width="256" height="256"/>
    <material name="table" texture="grid" texrepeat="6 6"/>
    <material name="arm" rgba="0.62 0.75 0.85 1"/>
    <material name="joint" rgba="0.25 0.3 0.35 1"/>
    <material name="finger" rgba="0.2 0.2 0.22 1"/>
    <material name="pad" rgba="0.75 0.3 0.15 1"/>
  </asset>
  <worldbody>
    <light pos="0.5 -0.5 2.0" dir="0 0.2 -1" diffuse="0.6 0.6 0.6"/>
    <camera name="scene" pos="{_fmt(*CAMERA_EYE)}" xyaxes="{cam}" fovy="45"/>
    <geom name="table" class="env" type="box" pos="0.4 0 -0.02" size="0.8 0.8 0.02" material="table"/>
    <geom name="wall" class="env" type="box" pos="{_fmt(wx, wy, 0.04)}"
          size="{_fmt(WALL_HALF_LENGTH, WALL_HALF_THICKNESS, 0.04)}" rgba="0.75 0.25 0.2 1"/>
    <site name="target" type="box" pos="{_fmt(*TARGET_XY, 0.0005)}" size="{_fmt(TARGET_HALF, TARGET_HALF, 0.0005)}"
          rgba="0.15 0.7 0.25 0.8"/>
    <site name="pick" type="box" pos="{_fmt(*PICK_XY, 0.0004)}" size="0.03 0.03 0.0004" rgba="0.3 0.3 0.9 0.4"/>
    <geom name="pedestal" class="env" type="cylinder" pos="0 0 0.0225" size="0.09 0.0225" material="joint"/>
{_arm_xml()}
    <body name="object" pos="{_fmt(*PICK_XY, 0.03)}">
      <freejoint name="object"/>
      <geom name="object" class="env" type="box" size="{_fmt(OBJECT_HALF_WIDTH, OBJECT_HALF_WIDTH, 0.03)}"
            mass="{OBJECT_MASS}" condim="4" friction="1 0.02 0.0001" rgba="0.95 0.75 0.1 1"/>
    </body>
  </worldbody>
  <actuator>
{actuators}
  </actuator>
</mujoco>
"""


MJCF = build_mjcf()


@functools.lru_cache(maxsize=1)
def _kinematic_model() -> mujoco.MjModel:
    """The scene's model, used for IK only (the arm's kinematics do not depend on gamma)."""
    model = mujoco.MjModel.from_xml_string(MJCF)
    # the IK addresses the arm as qpos[:6] / dofs [:6]
    for i, name in enumerate(JOINT_NAMES):
        j = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)
        assert model.jnt_qposadr[j] == i and model.jnt_dofadr[j] == i, "arm joints must come first"
    return model


# --- task parameters ------------------------------------------------------------------------------------
def check_task_params(task_params) -> np.ndarray:
    """``(object_cm, obstacle_cm)`` -> float64 array [2], validated against the sim's limits."""
    try:
        gamma = np.asarray(task_params, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as err:
        raise ValueError(f"task_params must be two numbers (object_cm, obstacle_cm), got {task_params!r}") from err
    if gamma.shape != (2,) or not np.all(np.isfinite(gamma)):
        raise ValueError(f"task_params must be two finite numbers (object_cm, obstacle_cm), got {task_params!r}")
    for val, (lo, hi), name in (
        (gamma[0], OBJECT_HEIGHT_LIMITS, "object"),
        (gamma[1], OBSTACLE_HEIGHT_LIMITS, "obstacle"),
    ):
        if not lo <= val <= hi:
            raise ValueError(f"{name} height {val:g} cm outside the sim's range [{lo:g}, {hi:g}] cm")
    return gamma


def is_extrapolation(task_params) -> bool:
    """True if gamma lies outside the training range (object 2-6 cm, obstacle 2-8 cm). The sim and the
    policy accept it (up to the sim's limits); reports flag it."""
    obj, obs = (float(v) for v in task_params)
    return not (TRAIN_OBJECT_RANGE[0] <= obj <= TRAIN_OBJECT_RANGE[1]
                and TRAIN_OBSTACLE_RANGE[0] <= obs <= TRAIN_OBSTACLE_RANGE[1])


def grasp_height(object_cm: float) -> float:
    """Tool-point height (m) of the grasp: linear in the object height (GRASP_SLOPE) from GRASP_MIN_Z at
    GRASP_KNEE_CM, smoothly clamped below the knee to keep the pads off the table. The relation has no kink
    inside the trained range (2-6 cm), so a model can interpolate it from the demos."""
    z = GRASP_MIN_Z + GRASP_SLOPE * (object_cm - GRASP_KNEE_CM) / 100.0
    k = GRASP_CLAMP_SOFTNESS
    return float(GRASP_MIN_Z + k * np.logaddexp(0.0, (z - GRASP_MIN_Z) / k))


def tcp_plan(task_params, demo_length: int = DEMO_LENGTH, clearance: float = WALL_CLEARANCE):
    """Cartesian plan of the expert: ``(tcp positions [T, 3], gripper command [T])`` for gamma (cm).

    ``clearance`` is the height of the object's bottom over the wall top at the arc's apex (metres).
    """
    gamma = check_task_params(task_params)
    T = int(demo_length)
    if T < 2:
        raise ValueError(f"demo_length must be >= 2, got {demo_length}")
    k = np.arange(T) * (199.0 / (T - 1))  # time in steps of a 200-step demonstration
    P = {n: float(v) for n, v in PHASE_STEPS.items()}
    z_g = grasp_height(gamma[0])
    wall_top = gamma[1] / 100.0
    pick = np.array([*PICK_XY, z_g])
    place = np.array([*TARGET_XY, z_g + PLACE_DROP])
    pre = pick + [0.0, 0.0, APPROACH_HEIGHT]
    lift = pick + [0.0, 0.0, CARRY_LIFT]
    above_place = place + [0.0, 0.0, CARRY_LIFT]
    retreat = place + [0.0, 0.0, RETREAT]
    z_apex = z_g + wall_top + clearance  # object bottom = tcp z - z_g

    def seg(k0, k1):
        return minimum_jerk((k - k0) / (k1 - k0))[:, None]

    pos = np.tile(HOME_TCP, (T, 1))
    s = seg(P["start_approach"], P["pregrasp"])
    pos = np.where(k[:, None] >= P["start_approach"], HOME_TCP + s * (pre - HOME_TCP), pos)
    s = seg(P["pregrasp"], P["grasp"])
    pos = np.where(k[:, None] >= P["pregrasp"], pre + s * (pick - pre), pos)
    s = seg(P["start_lift"], P["lifted"])
    pos = np.where(k[:, None] >= P["start_lift"], pick + s * (lift - pick), pos)
    s = seg(P["lifted"], P["arc_end"])
    arc = lift + s * (above_place - lift)
    arc[:, 2] = lift[2] + (z_apex - lift[2]) * np.sin(np.pi * s[:, 0])
    pos = np.where(k[:, None] >= P["lifted"], arc, pos)
    s = seg(P["arc_end"], P["placed"])
    pos = np.where(k[:, None] >= P["arc_end"], above_place + s * (place - above_place), pos)
    s = seg(P["start_retreat"], P["end"])
    pos = np.where(k[:, None] >= P["start_retreat"], place + s * (retreat - place), pos)

    grip = minimum_jerk((k - P["grasp"]) / (P["closed"] - P["grasp"])) - minimum_jerk(
        (k - P["placed"]) / (P["opened"] - P["placed"])
    )
    return pos, grip


# --- inverse kinematics ---------------------------------------------------------------------------------
def _ik(model, data, site_id, target_pos, target_rot, q0, tol=1e-10, max_iter=100, damping=1e-4):
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
    model = _kinematic_model()
    data = mujoco.MjData(model)
    sid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, "tcp")
    q, err = _ik(model, data, sid, HOME_TCP, TOOL_ROT, _HOME_SEED, max_iter=500, damping=1e-3)
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
    model = _kinematic_model()
    data = mujoco.MjData(model)
    sid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, "tcp")
    q = home_configuration().copy()
    out = np.zeros((len(pos), 7))
    for t, p in enumerate(pos):
        q, err = _ik(model, data, sid, p, TOOL_ROT, q)
        if err > 1e-6:
            raise RuntimeError(f"IK failed at step {t} for task_params {task_params} (residual {err:.3g})")
        out[t, :6] = q
    if np.any(out[:, :6] < JOINT_LIMITS[:, 0]) or np.any(out[:, :6] > JOINT_LIMITS[:, 1]):
        raise RuntimeError(f"reference for task_params {task_params} leaves the joint limits")
    out[:, 6] = grip
    return out


# --- control and contacts (shared with the other arm sims) ---------------------------------------------
def servo_control_step(model, data, prev_command, joint_command, on_substep=None) -> np.ndarray:
    """One 50 Hz control step of the arm's joint servos; returns the joint target reached (the new command).

    First-order hold: the joint targets ramp from ``prev_command`` to ``joint_command`` over the control
    step, with the ramp's velocity fed forward (like a robot controller interpolating servo targets). The
    controller limits the joint speed to the UR10's. The finger ``ctrl`` entries are left as they are.
    ``on_substep()`` is called after each of the ``N_SUBSTEPS`` physics steps.
    """
    d = data
    prev = np.asarray(prev_command, dtype=np.float64)
    max_delta = JOINT_SPEED_LIMITS * (N_SUBSTEPS * model.opt.timestep)
    target = prev + np.clip(np.asarray(joint_command, dtype=np.float64) - prev, -max_delta, max_delta)
    d.ctrl[ARM_VEL_CTRL] = (target - prev) / (N_SUBSTEPS * model.opt.timestep)
    for i in range(N_SUBSTEPS):
        # semi-implicit Euler moves the joint with the updated velocity, so substep i servos to the
        # ramp at its start; the joints reach ``target`` at the end of the control step
        d.ctrl[ARM_POS_CTRL] = prev + (target - prev) * (i / N_SUBSTEPS)
        mujoco.mj_step(model, d)
        if on_substep is not None:
            on_substep()
    d.ctrl[ARM_POS_CTRL] = target
    return target


# --- the env --------------------------------------------------------------------------------------------
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

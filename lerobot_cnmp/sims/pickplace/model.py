"""The pick-and-place scene's model: a 6-DoF arm built from the UR10's published DH table (link masses,
armature, joint limits and speeds, gravity compensated, per joint a position and a velocity servo), a parallel
two-finger gripper, the table, the wall, the target area and the box, as MJCF (numpy only: MuJoCo compiles it
in the env). The box and wall sizes are set per episode by the env."""

from __future__ import annotations

import numpy as np

CONTROL_FPS = 50
N_SUBSTEPS = 10  # physics steps (dt = 0.002) per control step -> 50 Hz control
DEFAULT_MAX_EPISODE_STEPS = 250

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


def lookat_xyaxes(eye, target, up=(0.0, 0.0, 1.0)) -> str:
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
    cam = lookat_xyaxes(CAMERA_EYE, CAMERA_TARGET)
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

"""The room sim's physics: a point mass (radius 0.02, mass 1) on the shared point-mass MJCF
(:mod:`lerobot_cnmp.sims.point_mass`) in a walled room ``[0, 1]^2`` with two box obstacles (placed and sized per
episode), the cameras of its mask image and of its videos, and the observation's sizes."""

from __future__ import annotations

import numpy as np

from lerobot_cnmp.sims.point_mass import point_mass_mjcf

SM_DIM = 2
MAX_CONDITIONS = 3
ENV_STATE_DIM = MAX_CONDITIONS * (2 + 2 * SM_DIM)  # 18
AGENT_RADIUS = 0.02
WALL_THICKNESS = 0.05  # walls lie outside the room square [0, 1]^2
OBSTACLE_HALF_HEIGHT = 0.05  # z half-extent of walls and obstacles
N_SUBSTEPS = 10  # physics steps (dt = 0.002) per control step -> 50 Hz control
CONTROL_FPS = 50
DEFAULT_IMAGE_SIZE = 64
MAX_IMAGE_SIZE = 1024  # the offscreen buffer's side
ACTION_LOW = np.array([0.0, 0.0], dtype=np.float32)
ACTION_HIGH = np.array([1.0, 1.0], dtype=np.float32)

# Position servos, critically damped for mass 1. Stiffer than obstacle2d's (kp 2500): the demos are
# faster (100 steps for paths up to ~2.4 m long, peak ~2.2 m/s), and the lag of a critically damped
# servo, 2 v / omega, would otherwise reach ~9 cm along the path.
KP = 10000.0

WALL_GEOMS = ("wall_left", "wall_right", "wall_bottom", "wall_top")
OBSTACLE_GEOMS = ("obstacle0", "obstacle1")
_H, _L, _Z = WALL_THICKNESS / 2, 0.5 + WALL_THICKNESS, OBSTACLE_HALF_HEIGHT  # wall box half-sizes

SCENE = f"""    <!-- "top": the image observation, exactly the room square (orthographic: fovy is the height in m) -->
    <camera name="top" pos="0.5 0.5 1.0" xyaxes="1 0 0 0 1 0" projection="orthographic" fovy="1.0"/>
    <!-- "view": the colour render for videos, walls included -->
    <camera name="view" pos="0.5 0.5 1.0" xyaxes="1 0 0 0 1 0" projection="orthographic" fovy="1.16"/>
    <geom name="floor" type="plane" pos="0.5 0.5 -0.06" size="0.6 0.6 0.01" material="grid"
          contype="0" conaffinity="0" group="1"/>
    <geom name="wall_left" type="box" pos="{-_H} 0.5 0" size="{_H} {_L} {_Z}" rgba="0.3 0.3 0.3 1"/>
    <geom name="wall_right" type="box" pos="{1 + _H} 0.5 0" size="{_H} {_L} {_Z}" rgba="0.3 0.3 0.3 1"/>
    <geom name="wall_bottom" type="box" pos="0.5 {-_H} 0" size="{_L} {_H} {_Z}" rgba="0.3 0.3 0.3 1"/>
    <geom name="wall_top" type="box" pos="0.5 {1 + _H} 0" size="{_L} {_H} {_Z}" rgba="0.3 0.3 0.3 1"/>
    <!-- placed and sized per episode (RoomEnv._place_obstacles); each in a static body of its own, so
         that its collision bounding volumes are its own geom's and can follow its size -->
    <body name="obstacle0" pos="0.35 0.25 0">
      <geom name="obstacle0" type="box" size="0.05 0.25 {_Z}" rgba="0.8 0.25 0.2 1"/>
    </body>
    <body name="obstacle1" pos="0.65 0.75 0">
      <geom name="obstacle1" type="box" size="0.05 0.25 {_Z}" rgba="0.8 0.25 0.2 1"/>
    </body>
    <site name="end" type="sphere" pos="1 0.5 0.06" size="0.03" rgba="0.1 0.75 0.2 0.6"/>"""

MJCF = point_mass_mjcf(
    "cnmp_room",
    scene=SCENE,
    agent_radius=AGENT_RADIUS,
    agent_attrs='rgba="0.15 0.35 0.9 1" group="2"',
    kp=KP,
    ctrl_low=ACTION_LOW,
    ctrl_high=ACTION_HIGH,
    n_condition_sites=MAX_CONDITIONS,
    condition_site_half=0.02,
    offscreen_size=MAX_IMAGE_SIZE,
    headlight='ambient="0.5 0.5 0.5" diffuse="0.5 0.5 0.5" specular="0 0 0"',
)

"""The obstacle2d sim's physics: a point mass (radius 0.03, mass 1) on the shared point-mass MJCF
(:mod:`lerobot_cnmp.sims.point_mass`) around a round obstacle centred at (0.5, 0), its actuators and its
perturbations."""

from __future__ import annotations

import numpy as np

from lerobot_cnmp.sims.obstacle2d.task import MAX_CONDITIONS
from lerobot_cnmp.sims.point_mass import point_mass_mjcf

OBSTACLE_CENTER = np.array([0.5, 0.0])
OBSTACLE_RADIUS = 0.2
AGENT_RADIUS = 0.03
N_SUBSTEPS = 10  # physics steps (dt = 0.002) per control step -> 50 Hz control
CONTROL_FPS = 50
ACTION_LOW = np.array([-0.3, -0.8], dtype=np.float32)
ACTION_HIGH = np.array([1.3, 0.8], dtype=np.float32)
DEFAULT_MAX_EPISODE_STEPS = 300
KP = 2500.0  # the position servos' gain (critically damped for mass 1)

# Actuators: ``servo`` (the stiff position servo of the demos) or ``rate_limited`` (that servo behind a set
# point that moves toward the command at most RATE_LIMIT m/s).
ACTUATOR_CHOICES = ("servo", "rate_limited")
RATE_LIMIT = 0.08  # m/s, the rate_limited actuator's top speed (the demos move at up to ~0.5 m/s)

# Perturbations, at a random step in PERTURB_STEP_RANGE.
PERTURBATION_CHOICES = ("none", "push", "push_toward", "push_random", "hold")
PUSH_DISTANCE = 0.12
PUSH_MIN_CLEARANCE = 0.02  # a push toward the obstacle stops this far from it
HOLD_STEPS = 30
PERTURB_STEP_RANGE = (50, 120)  # inclusive

SCENE = f"""    <camera name="top" pos="0.5 0 2.0" xyaxes="1 0 0 0 1 0" fovy="45"/>
    <geom name="floor" type="plane" pos="0.5 0 -0.06" size="1.5 1.5 0.01" material="grid"
          contype="0" conaffinity="0"/>
    <geom name="obstacle" type="cylinder" pos="{OBSTACLE_CENTER[0]} {OBSTACLE_CENTER[1]} 0"
          size="{OBSTACLE_RADIUS} 0.05" rgba="0.8 0.25 0.2 1" contype="1" conaffinity="1"/>
    <site name="goal" type="sphere" pos="1 0 0.06" size="0.035" rgba="0.1 0.75 0.2 0.7"/>"""

MJCF = point_mass_mjcf(
    "cnmp_obstacle2d",
    scene=SCENE,
    agent_radius=AGENT_RADIUS,
    agent_attrs='rgba="0.15 0.35 0.9 1" contype="1" conaffinity="1"',
    kp=KP,
    ctrl_low=ACTION_LOW,
    ctrl_high=ACTION_HIGH,
    n_condition_sites=MAX_CONDITIONS,
    condition_site_half=0.025,
)

"""The weights task (CNMP paper, Sec. IV-D): the SM layout, the containers (shape x weight category), their
masses, the pick spot and the four zones, the weight switch, and the class -> zone rule."""

from __future__ import annotations

import numpy as np

from lerobot_cnmp.sims.pickplace.model import CONTROL_FPS  # noqa: F401  (the arm's control rate is the sim's)

DEMO_LENGTH = 200
DEFAULT_MAX_EPISODE_STEPS = 260
SM_NAMES = ("x", "y", "z", "finger_left", "finger_right", "fx", "fy", "fz", "tx", "ty", "tz")
SM_DIM = len(SM_NAMES)
POS_SM = slice(0, 3)
FINGER_SM = slice(3, 5)
FT_SM = slice(5, 11)

# Containers: (name, half width along x and y, half height), metres.
SHAPES = (("box_4cm", 0.02, 0.03), ("cube_6cm", 0.03, 0.03))
LIGHT_RANGE = (0.15, 0.35)
HEAVY_RANGE = (0.65, 0.95)
HEAVY_THRESHOLD = 0.5  # kg: masses above it are "heavy"
MASS_LIMITS = (0.05, 1.5)  # what reset accepts, kg
WEIGHT_CATEGORIES = ("light", "heavy")
DEMO_MASSES = {"light": (0.15, 0.20, 0.25, 0.30, 0.35), "heavy": (0.65, 0.725, 0.80, 0.875, 0.95)}
TEST_MASSES = {"light": (0.175, 0.225, 0.275, 0.325), "heavy": (0.6875, 0.7625, 0.8375, 0.9125)}

# Scene (metres).
PICK_XY = np.array([0.70, -0.20])
ZONE_ROWS_X = (0.55, 0.85)  # by shape
ZONE_COLS_Y = (0.15, 0.40)  # by weight category
ZONE_XY = np.array([[x, y] for x in ZONE_ROWS_X for y in ZONE_COLS_Y])  # zone = 2 * shape + heavy
ZONE_HALF = 0.06
ZONE_RGBA = ((0.3, 0.75, 0.35, 0.8), (0.1, 0.45, 0.15, 0.8), (0.35, 0.55, 0.9, 0.8), (0.1, 0.25, 0.65, 0.8))

# Weight switch.
PERTURBATION_CHOICES = ("none", "weight_switch")
SWITCH_WINDOW = (108, 120)  # steps (inclusive): the nominal transport runs from step 104 to 150
SWITCH_ADDED_MASS = 0.5  # kg
SWITCH_MIN_HEIGHT = 0.08  # m: the container's bottom above the table when the mass is added


def weight_category(mass: float) -> int:
    """0 light, 1 heavy."""
    return int(float(mass) > HEAVY_THRESHOLD)


def target_zone(shape: int, mass: float) -> int:
    """Index into :data:`ZONE_XY` of the container's class: ``2 * shape + weight_category(mass)``."""
    return 2 * int(shape) + weight_category(mass)


def finger_contact_opening(shape: int) -> float:
    """Finger joint position (m) at which both pads touch a container of ``shape``."""
    return float(SHAPES[int(shape)][1])


def check_shape(shape) -> int:
    if isinstance(shape, bool) or not isinstance(shape, (int, np.integer)) or int(shape) not in (0, 1):
        raise ValueError(f"shape must be 0 ({SHAPES[0][0]}) or 1 ({SHAPES[1][0]}), got {shape!r}")
    return int(shape)


def check_mass(mass) -> float:
    try:
        m = float(mass)
    except (TypeError, ValueError) as err:
        raise ValueError(f"mass must be a number of kg, got {mass!r}") from err
    if not (np.isfinite(m) and MASS_LIMITS[0] <= m <= MASS_LIMITS[1]):
        raise ValueError(f"mass {mass!r} kg outside the sim's range [{MASS_LIMITS[0]}, {MASS_LIMITS[1]}] kg")
    return m

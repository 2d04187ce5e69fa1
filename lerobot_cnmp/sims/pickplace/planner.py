"""The task parameters γ = (object height, obstacle height) in cm, their ranges and checks, and the expert's
Cartesian plan of the tool point (grasp height linear in the object height, arc apex with the object a set
clearance above the wall top, fixed phase timing, minimum-jerk segments)."""

from __future__ import annotations

import numpy as np

from lerobot_cnmp.sims.pickplace.model import PICK_XY, TARGET_XY
from lerobot_cnmp.sims.time_law import minimum_jerk

DEMO_LENGTH = 200

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

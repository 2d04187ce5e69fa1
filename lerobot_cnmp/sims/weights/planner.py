"""The weights expert's Cartesian plan: home -> above the container -> descend -> close -> lift -> carry to above
the zone -> descend -> open -> retreat, fixed phase timing, minimum-jerk segments."""

from __future__ import annotations

import numpy as np

from lerobot_cnmp.sims.pickplace.model import FINGER_OPEN
from lerobot_cnmp.sims.pickplace.planner import HOME_TCP
from lerobot_cnmp.sims.time_law import minimum_jerk
from lerobot_cnmp.sims.weights.task import DEMO_LENGTH, PICK_XY, ZONE_XY, finger_contact_opening

# Expert plan (metres); the tool point is at GRASP_Z when grasping (container mid-height).
GRASP_Z = 0.03
APPROACH_HEIGHT = 0.10  # pre-grasp: this far above the grasp point
LIFT_HEIGHT = 0.10  # carry with the tool point this far above the grasp height
PLACE_DROP = 0.01  # release with the container's bottom this high above the table (slip and tracking margin)
RETREAT = 0.10
# Phase knots, in control steps of a 200-step demonstration (scaled for other lengths).
PHASE_STEPS = {
    "start_approach": 8,
    "pregrasp": 50,
    "grasp": 70,
    "closed": 80,
    "start_lift": 86,
    "lifted": 104,
    "carry_end": 150,
    "placed": 166,
    "opened": 176,
    "start_retreat": 180,
    "end": 196,
}
MIN_REPLAN_STEPS = 25  # shortest move to the new zone after a weight switch (200-step scale)


def tcp_plan(shape: int, zone: int, steps, demo_length: int = DEMO_LENGTH):
    """The demonstrator's Cartesian plan at (possibly fractional) control steps ``steps``: ``(tool-point
    positions [n, 3], finger opening command [n])`` for a container of ``shape`` going to ``zone``.

    Home -> above the container -> descend -> close the fingers to the container's width -> lift -> carry
    straight to above the zone -> descend -> open -> retreat up, fixed phase timing (:data:`PHASE_STEPS`,
    scaled to ``demo_length``), minimum-jerk segments.
    """
    T = int(demo_length)
    if T < 2:
        raise ValueError(f"demo_length must be >= 2, got {demo_length}")
    k = np.atleast_1d(np.asarray(steps, dtype=np.float64)) * (199.0 / (T - 1))  # 200-step time
    P = {n: float(v) for n, v in PHASE_STEPS.items()}
    pick = np.array([*PICK_XY, GRASP_Z])
    pre = pick + [0.0, 0.0, APPROACH_HEIGHT]
    lift = pick + [0.0, 0.0, LIFT_HEIGHT]
    place = np.array([*ZONE_XY[int(zone)], GRASP_Z + PLACE_DROP])
    above_place = place + [0.0, 0.0, LIFT_HEIGHT]
    retreat = place + [0.0, 0.0, RETREAT]
    home = np.asarray(HOME_TCP, dtype=np.float64)
    # (start knot, end knot, from, to) in order; each segment holds its end afterwards
    segments = (
        ("start_approach", "pregrasp", home, pre),
        ("pregrasp", "grasp", pre, pick),
        ("start_lift", "lifted", pick, lift),
        ("lifted", "carry_end", lift, above_place),
        ("carry_end", "placed", above_place, place),
        ("start_retreat", "end", place, retreat),
    )
    pos = np.tile(home, (len(k), 1))
    for k0, k1, a, b in segments:
        s = minimum_jerk((k - P[k0]) / (P[k1] - P[k0]))[:, None]
        pos = np.where(k[:, None] >= P[k0], a + s * (b - a), pos)
    closed = finger_contact_opening(shape)
    grip = minimum_jerk((k - P["grasp"]) / (P["closed"] - P["grasp"])) - minimum_jerk(
        (k - P["placed"]) / (P["opened"] - P["placed"])
    )
    fingers = FINGER_OPEN + grip * (closed - FINGER_OPEN)
    return pos, fingers

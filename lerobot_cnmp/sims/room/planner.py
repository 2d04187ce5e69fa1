"""The room expert's plan (the paper's "simple heuristic"), a pure function of the room: waypoints through the
middle of each obstacle's gap, the monotone PCHIP cubic ``y(x)`` through them, traversed by arc length with a
minimum-jerk time law; and the clearance checks that make a drawn room valid. Works on any room with
``obstacles`` (each with ``rect`` and ``gap_center``), ``start`` and ``end``
(:class:`lerobot_cnmp.sims.room.task.RoomTask`)."""

from __future__ import annotations

import functools

import numpy as np
from scipy.interpolate import PchipInterpolator

from lerobot_cnmp.sims.room.model import AGENT_RADIUS
from lerobot_cnmp.sims.time_law import minimum_jerk

MARGIN = 0.05  # x offset of the gap waypoints from the obstacle's faces
MIN_TRANSITION_DX = 0.02  # the least x distance between consecutive waypoints of a valid plan
MIN_CLEARANCE = AGENT_RADIUS + 0.03  # least distance of the planned path to obstacles and walls
PATH_SAMPLES = 4001  # dense samples of y(x) for the arc length and the clearance check


def waypoints(task) -> tuple[np.ndarray, np.ndarray]:
    """The planner's waypoints ``(x [6], y [6])``: start, each obstacle's gap centre ``MARGIN`` before and
    after it, end."""
    xs, ys = [task.start[0]], [task.start[1]]
    for ob in task.obstacles:
        x_min, x_max, _, _ = ob.rect
        xs += [x_min - MARGIN, x_max + MARGIN]
        ys += [ob.gap_center, ob.gap_center]
    xs.append(task.end[0])
    ys.append(task.end[1])
    return np.array(xs), np.array(ys)


@functools.lru_cache(maxsize=64)
def _path_table(task) -> tuple[np.ndarray, np.ndarray]:
    """Dense samples of the planned curve, ``(points [N, 2], cumulative arc length [N])``."""
    xs, ys = waypoints(task)
    if np.any(np.diff(xs) <= 0):
        raise ValueError(f"the planner's waypoints are not increasing in x for {task}")
    x = np.linspace(xs[0], xs[-1], PATH_SAMPLES)
    pts = np.stack([x, PchipInterpolator(xs, ys)(x)], axis=-1)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=-1))])
    pts.setflags(write=False)
    s.setflags(write=False)
    return pts, s


def plan_path(task, phases) -> np.ndarray:
    """The planned position at ``phases`` (scalar or array in [0, 1], clipped) -> ``[..., 2]``: the PCHIP
    curve through :func:`waypoints`, at arc length ``L * minimum_jerk(phase)``."""
    pts, s = _path_table(task)
    target = s[-1] * minimum_jerk(np.asarray(phases, dtype=np.float64))
    return np.stack([np.interp(target, s, pts[:, 0]), np.interp(target, s, pts[:, 1])], axis=-1)


def distance_to_obstacles(task, points) -> np.ndarray:
    """Distance of ``points [..., 2]`` to the nearest obstacle or wall (0 inside one)."""
    p = np.asarray(points, dtype=np.float64)
    d = np.min(np.stack([p[..., 0], 1.0 - p[..., 0], p[..., 1], 1.0 - p[..., 1]]), axis=0)
    d = np.maximum(d, 0.0)
    for ob in task.obstacles:
        x0, x1, y0, y1 = ob.rect
        dx = np.maximum(np.maximum(x0 - p[..., 0], p[..., 0] - x1), 0.0)
        dy = np.maximum(np.maximum(y0 - p[..., 1], p[..., 1] - y1), 0.0)
        d = np.minimum(d, np.hypot(dx, dy))
    return d


def path_clearance(task) -> float:
    """Least distance of the planned path (the agent's centre) to an obstacle or a wall."""
    return float(distance_to_obstacles(task, _path_table(task)[0]).min())


def plan_is_valid(task) -> bool:
    """Waypoints at least :data:`MIN_TRANSITION_DX` apart in x and a path clearance of at least
    :data:`MIN_CLEARANCE`."""
    xs, _ = waypoints(task)
    if np.diff(xs).min() < MIN_TRANSITION_DX:
        return False
    return path_clearance(task) >= MIN_CLEARANCE

"""The obstacle2d task family (CNMP paper, Sec. IV-A, Fig. 4) and how an episode's conditions are drawn.

A member of the family is a hidden reference trajectory::

    x(tau) = tau,    y(tau) = y0 + (h - y0) * sin(pi * tau) ** p,    tau in [0, 1]

passing over (``mode=+1``) or under (``mode=-1``) the obstacle. Family ``mirrored``: ``y0 in s*[0.1, 0.3]``,
``h in s*[0.45, 0.65]``, ``p in [0.9, 1.6]`` for mode ``s`` (a start or goal alone names the mode). Family
``shared`` (the paper's setting): both modes start at (0, y0) and end at (1, y0) with the same
``y0 in [-0.1, 0.1]``, ``h in s*[0.45, 0.65]`` (a method that averages the modes goes through the obstacle).
The conditions of an episode are points of its reference, in the layout of
:mod:`lerobot_cnmp.execution.conditions` with SM dimension :data:`SM_DIM` and :data:`MAX_CONDITIONS` slots.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lerobot_cnmp.execution.conditions import Condition

SM_DIM = 2
MAX_CONDITIONS = 4
ENV_STATE_DIM = MAX_CONDITIONS * (2 + 2 * SM_DIM)  # 24

# Task family bounds (for mode +1; mode -1 mirrors y0 and h).
Y0_RANGE = (0.1, 0.3)
SHARED_Y0_RANGE = (-0.1, 0.1)  # family 'shared': the start height of both modes
H_RANGE = (0.45, 0.65)
P_RANGE = (0.9, 1.6)

CONDITION_CHOICES = ("mixed", "paper_via", "paper_early", "paper_end", "random", "start_goal", "start_goal_early")
PAPER_CONDITION_CHOICES = ("mixed", "paper_via", "paper_early", "paper_end")  # the mirrored family only
FAMILY_CHOICES = ("mirrored", "shared")
RANDOM_VARIANTS = ("via", "early", "end", "via+end", "via_y")  # condition sets of ``random``
MODE_NAMES = {1: "over", -1: "under"}


@dataclass(frozen=True)
class Obstacle2DTask:
    """One member of the task family: the hidden reference trajectory of an episode."""

    mode: int  # +1 over the obstacle, -1 under
    y0: float
    h: float
    p: float

    def position(self, tau):
        """Reference position at phase ``tau`` (scalar or array, clipped to [0, 1]) -> ``[..., 2]``."""
        tau = np.clip(np.asarray(tau, dtype=np.float64), 0.0, 1.0)
        y = self.y0 + (self.h - self.y0) * np.sin(np.pi * tau) ** self.p
        return np.stack([tau, y], axis=-1)

    @property
    def start(self) -> np.ndarray:
        return np.array([0.0, self.y0])

    @property
    def goal(self) -> np.ndarray:
        return np.array([1.0, self.y0])

    @property
    def mode_name(self) -> str:
        return MODE_NAMES[self.mode]

    @classmethod
    def sample(cls, rng: np.random.Generator, mode: int | None = None, family: str = "mirrored") -> Obstacle2DTask:
        if family not in FAMILY_CHOICES:
            raise ValueError(f"unknown family {family!r}; choose one of {list(FAMILY_CHOICES)}")
        if mode is None:
            mode = int(rng.choice([1, -1]))
        y0 = rng.uniform(*Y0_RANGE)
        h = rng.uniform(*H_RANGE)
        p = rng.uniform(*P_RANGE)
        if family == "shared":  # the same start (and goal) height range for both modes
            return cls(mode=mode, y0=float(SHARED_Y0_RANGE[0] + (SHARED_Y0_RANGE[1] - SHARED_Y0_RANGE[0])
                                           * (y0 - Y0_RANGE[0]) / (Y0_RANGE[1] - Y0_RANGE[0])),
                       h=float(mode * h), p=float(p))
        return cls(mode=mode, y0=float(mode * y0), h=float(mode * h), p=float(p))


def check_mode(mode) -> int | None:
    if mode is None:
        return None
    if mode in ("over", "under"):
        return 1 if mode == "over" else -1
    if mode not in (1, -1):
        raise ValueError(f"mode must be +1 ('over'), -1 ('under') or None, got {mode!r}")
    return int(mode)


def check_family(family: str, conditions: str) -> None:
    if family not in FAMILY_CHOICES:
        raise ValueError(f"unknown family {family!r}; choose one of {list(FAMILY_CHOICES)}")
    if family == "shared" and conditions in PAPER_CONDITION_CHOICES:
        raise ValueError(f"conditions {conditions!r} are the paper's sets of the 'mirrored' family; with family "
                         f"'shared' choose one of {[c for c in CONDITION_CHOICES if c not in PAPER_CONDITION_CHOICES]}")


PAPER_CONDITIONS: dict[str, list[Condition]] = {
    # Sec. IV-A / Fig. 4: a via-point that selects the mode, an early point, an end point.
    "paper_via": [Condition(0.5, (0.5, 0.55))],
    "paper_early": [Condition(0.2, (0.2, -0.37))],
    "paper_end": [Condition(1.0, (1.0, 0.13))],
}


def _point(task: Obstacle2DTask, t: float, dims=None) -> Condition:
    xy = task.position(t)
    return Condition(float(t), (float(xy[0]), float(xy[1])), dims)


def sample_episode(
    rng: np.random.Generator, conditions: str, mode: int | None = None, family: str = "mirrored"
) -> tuple[Obstacle2DTask, list[Condition], str]:
    """Draw ``(task, conditions, kind)`` for one episode.

    ``kind`` names the concrete condition set: ``paper_via``, ``paper_early``, ``paper_end`` or
    ``random/<variant>`` with variant in :data:`RANDOM_VARIANTS`. ``mode`` (+1 / -1) forces the avoidance
    mode (for ``mixed``, only the compatible condition sets are drawn). ``start_goal``: the start (phase 0)
    and the goal (phase 1); ``start_goal_early``: those and the reference point at a phase drawn in
    [0.15, 0.3], which names the mode in either family. ``family``: see :class:`Obstacle2DEnv`; the
    paper's condition sets (and ``mixed``) exist for the ``mirrored`` family only.
    """
    if conditions not in CONDITION_CHOICES:
        raise ValueError(f"unknown conditions {conditions!r}; choose one of {list(CONDITION_CHOICES)}")
    check_family(family, conditions)
    mode = check_mode(mode)
    if conditions in ("start_goal", "start_goal_early"):
        task = Obstacle2DTask.sample(rng, mode, family)
        conds = [_point(task, 0.0), _point(task, 1.0)]
        if conditions == "start_goal_early":
            conds.append(_point(task, rng.uniform(0.15, 0.3)))
        return task, conds, conditions
    kind = conditions
    if kind == "mixed":
        kinds = ["paper_via", "paper_early", "paper_end", "random"]
        if mode is not None:  # keep only the kinds compatible with the requested mode
            kinds = [k for k in kinds if k == "random" or (k == "paper_early") == (mode == -1)]
        kind = str(kinds[int(rng.integers(len(kinds)))])
    fixed_mode = {"paper_via": 1, "paper_end": 1, "paper_early": -1}.get(kind)
    if fixed_mode is not None and mode is not None and mode != fixed_mode:
        raise ValueError(f"conditions {kind!r} are only defined for mode {fixed_mode:+d}, got mode {mode:+d}")

    if kind == "paper_via":
        base = Obstacle2DTask.sample(rng, 1)
        task = Obstacle2DTask(1, base.y0, PAPER_CONDITIONS[kind][0].values[1], base.p)
        return task, PAPER_CONDITIONS[kind], kind
    if kind == "paper_end":
        base = Obstacle2DTask.sample(rng, 1)
        task = Obstacle2DTask(1, 0.13, base.h, base.p)
        return task, PAPER_CONDITIONS[kind], kind
    if kind == "paper_early":
        s = np.sin(np.pi * 0.2)
        for _ in range(100_000):
            base = Obstacle2DTask.sample(rng, -1)
            r = (-0.37 - base.y0) / (base.h - base.y0)
            if not 0.0 < r < 1.0:
                continue
            p = float(np.log(r) / np.log(s))
            if P_RANGE[0] <= p <= P_RANGE[1]:
                task = Obstacle2DTask(-1, base.y0, base.h, p)
                return task, PAPER_CONDITIONS[kind], kind
        raise RuntimeError("could not sample a task through the paper_early condition")  # pragma: no cover
    # random
    task = Obstacle2DTask.sample(rng, mode, family)
    variant = RANDOM_VARIANTS[int(rng.integers(len(RANDOM_VARIANTS)))]
    if variant == "via":
        conds = [_point(task, rng.uniform(0.35, 0.65))]
    elif variant == "early":
        conds = [_point(task, rng.uniform(0.1, 0.3))]
    elif variant == "end":
        conds = [_point(task, 1.0)]
    elif variant == "via+end":
        conds = [_point(task, rng.uniform(0.35, 0.65)), _point(task, 1.0)]
    else:  # via_y: a via point constraining y only
        conds = [_point(task, rng.uniform(0.4, 0.6), dims=(1,))]
    kind = f"random/{variant}"
    return task, conds, kind

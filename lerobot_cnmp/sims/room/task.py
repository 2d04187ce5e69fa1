"""The room family (CNMP paper, Sec. IV-B): two rectangular obstacles on opposite walls, a start on the left
and an end on the right, drawn until the plan (:mod:`lerobot_cnmp.sims.room.planner`) is valid; and the
conditions an episode gets, points of that plan."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lerobot_cnmp.execution.conditions import Condition
from lerobot_cnmp.sims.room.planner import plan_is_valid, plan_path

DEMO_LENGTH = 100
DEFAULT_MAX_EPISODE_STEPS = 150

# Room family (see the env's module docstring).
LEFT_X_RANGE = (0.25, 0.45)
RIGHT_X_RANGE = (0.55, 0.75)
WIDTH_RANGE = (0.06, 0.14)
LENGTH_RANGE = (0.35, 0.6)
START_X_RANGE = (0.05, 0.12)
END_X_RANGE = (0.88, 0.95)
Y_RANGE = (0.1, 0.9)  # of the start and the end
WALLS = ("bottom", "top")
MAX_SAMPLE_TRIES = 1000

CONDITION_CHOICES = ("start_end", "via_end", "via")
VIA_PHASE_RANGE = (0.3, 0.7)


@dataclass(frozen=True)
class Obstacle:
    """A rectangle attached to the bottom or the top wall, reaching ``length`` into the room."""

    x: float  # centre
    width: float
    length: float
    wall: str  # "bottom" or "top"

    @property
    def rect(self) -> tuple[float, float, float, float]:
        """``(x_min, x_max, y_min, y_max)``."""
        if self.wall == "bottom":
            y0, y1 = 0.0, self.length
        else:
            y0, y1 = 1.0 - self.length, 1.0
        return (self.x - self.width / 2, self.x + self.width / 2, y0, y1)

    @property
    def gap_center(self) -> float:
        """y of the middle of the gap the obstacle leaves open."""
        return (1.0 + self.length) / 2 if self.wall == "bottom" else (1.0 - self.length) / 2


@dataclass(frozen=True)
class RoomTask:
    """One room of the family: the two obstacles (left, right), the start and the end."""

    obstacles: tuple[Obstacle, Obstacle]
    start: tuple[float, float]
    end: tuple[float, float]

    @property
    def layout(self) -> str:
        """``"bottom-first"`` when the left obstacle hangs from the bottom wall, else ``"top-first"``."""
        return f"{self.obstacles[0].wall}-first"

    def position(self, tau):
        """Planned position at phase ``tau`` (scalar or array, clipped to [0, 1]) -> ``[..., 2]``."""
        return plan_path(self, tau)

    @classmethod
    def draw(cls, rng: np.random.Generator) -> RoomTask:
        """One draw of the family's ranges, valid plan or not (:meth:`sample` keeps only valid ones)."""
        left_wall = WALLS[int(rng.integers(2))]
        right_wall = "top" if left_wall == "bottom" else "bottom"
        obstacles = (
            Obstacle(float(rng.uniform(*LEFT_X_RANGE)), float(rng.uniform(*WIDTH_RANGE)),
                     float(rng.uniform(*LENGTH_RANGE)), left_wall),
            Obstacle(float(rng.uniform(*RIGHT_X_RANGE)), float(rng.uniform(*WIDTH_RANGE)),
                     float(rng.uniform(*LENGTH_RANGE)), right_wall),
        )
        start = (float(rng.uniform(*START_X_RANGE)), float(rng.uniform(*Y_RANGE)))
        end = (float(rng.uniform(*END_X_RANGE)), float(rng.uniform(*Y_RANGE)))
        return cls(obstacles, start, end)

    @classmethod
    def sample(cls, rng: np.random.Generator) -> RoomTask:
        """Draw rooms from ``rng`` until one has a valid plan (:func:`plan_is_valid`)."""
        for _ in range(MAX_SAMPLE_TRIES):
            task = cls.draw(rng)
            if plan_is_valid(task):
                return task
        raise RuntimeError(f"no valid room in {MAX_SAMPLE_TRIES} draws")  # pragma: no cover


def episode_conditions(task: RoomTask, condition: str, via_phase: float) -> list[Condition]:
    """The conditions of an episode, points of the room's plan (see ``CONDITION_CHOICES``)."""
    if condition not in CONDITION_CHOICES:
        raise ValueError(f"unknown condition {condition!r}; choose one of {list(CONDITION_CHOICES)}")
    phases = {"start_end": [0.0, 1.0], "via_end": [via_phase, 1.0], "via": [via_phase]}[condition]
    return [Condition(float(t), tuple(float(v) for v in plan_path(task, t))) for t in phases]

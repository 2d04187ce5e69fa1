"""``--env.type=cnmp_obstacle2d``: the LeRobot ``EnvConfig`` of the obstacle2d sim and its gymnasium id
``cnmp/Obstacle2D-v0`` (imports no MuJoCo)."""

from __future__ import annotations

from dataclasses import dataclass, field

from lerobot.configs import PolicyFeature
from lerobot.envs.configs import EnvConfig

from lerobot_cnmp.sims.config import CNMPSimConfig, point_mass_features, point_mass_features_map, register_gym_id
from lerobot_cnmp.sims.obstacle2d.model import (
    ACTUATOR_CHOICES,
    CONTROL_FPS,
    DEFAULT_MAX_EPISODE_STEPS,
    PERTURBATION_CHOICES,
    RATE_LIMIT,
)
from lerobot_cnmp.sims.obstacle2d.task import CONDITION_CHOICES, ENV_STATE_DIM, FAMILY_CHOICES, check_family

OBSTACLE2D_GYM_ID = "cnmp/Obstacle2D-v0"
register_gym_id(OBSTACLE2D_GYM_ID, "lerobot_cnmp.sims.obstacle2d.env:Obstacle2DEnv", DEFAULT_MAX_EPISODE_STEPS)


@EnvConfig.register_subclass("cnmp_obstacle2d")
@dataclass
class CNMPObstacle2DEnv(CNMPSimConfig):
    """2D point mass avoiding a round obstacle, over or under it (CNMP paper, Sec. IV-A).

    Fields:
        task: gymnasium task name (the id is ``cnmp/<task>``).
        fps: control frequency, Hz (10 physics steps of 2 ms per control step).
        episode_length: steps before truncation (the nominal demonstrated motion takes 200).
        conditions: how each episode's conditions are chosen: ``mixed`` (default; one of the next four per
            episode), ``paper_via``, ``paper_early``, ``paper_end`` (the paper's Fig. 4 conditions) or
            ``random`` (random family member and condition set), ``start_goal`` (start and goal) or
            ``start_goal_early`` (those and an early point, which names the mode). With family ``shared``
            only the last three exist.
        perturbation: ``none``, ``push`` (0.12 displacement away from the obstacle at a random step in
            [50, 120]), ``push_toward`` (toward the obstacle, stopping 0.02 short of it), ``push_random`` (a
            random direction, same stop) or ``hold`` (held still for 30 steps from a random step in [50, 120]).
        family: ``mirrored`` (the modes start and end at mirrored heights) or ``shared`` (both modes share the
            start and the goal, the paper's setting).
        actuator: ``servo`` (the stiff position servo of the demos) or ``rate_limited`` (its set point moves at
            most ``rate_limit`` m/s toward the command: the body lags behind the demos' schedule).
        rate_limit: the ``rate_limited`` actuator's top speed, m/s (default 0.08; the demos move at up to ~0.5).
        render_mode, render_size, terminate_on_success: see :class:`CNMPSimConfig`.
    """

    task: str | None = "Obstacle2D-v0"
    fps: int = CONTROL_FPS
    episode_length: int = DEFAULT_MAX_EPISODE_STEPS
    conditions: str = "mixed"
    perturbation: str = "none"
    family: str = "mirrored"
    actuator: str = "servo"
    rate_limit: float = RATE_LIMIT
    features: dict[str, PolicyFeature] = field(default_factory=lambda: point_mass_features(ENV_STATE_DIM))
    features_map: dict[str, str] = field(default_factory=point_mass_features_map)

    def __post_init__(self):
        self._check_choice("task", ("Obstacle2D-v0",))
        self._check_choice("conditions", CONDITION_CHOICES)
        self._check_choice("perturbation", PERTURBATION_CHOICES)
        self._check_choice("family", FAMILY_CHOICES)
        self._check_choice("actuator", ACTUATOR_CHOICES)
        check_family(self.family, self.conditions)
        self._check_common()

    @property
    def gym_kwargs(self) -> dict:
        return {
            "conditions": self.conditions,
            "perturbation": self.perturbation,
            "family": self.family,
            "actuator": self.actuator,
            "rate_limit": self.rate_limit,
            **self._common_gym_kwargs(),
        }

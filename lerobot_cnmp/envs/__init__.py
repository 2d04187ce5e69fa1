"""CNMP sims: gymnasium registration, LeRobot env configs and the recorder's sim registry."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import gymnasium as gym

from lerobot_cnmp.envs.configs import OBSTACLE2D_GYM_ID, CNMPObstacle2DEnv
from lerobot_cnmp.envs.obstacle2d import DEFAULT_MAX_EPISODE_STEPS, ENV_STATE_DIM, MAX_CONDITIONS

if OBSTACLE2D_GYM_ID not in gym.registry:
    gym.register(
        id=OBSTACLE2D_GYM_ID,
        entry_point="lerobot_cnmp.envs.obstacle2d:Obstacle2DEnv",
        max_episode_steps=DEFAULT_MAX_EPISODE_STEPS,
    )


def _condition_names(max_conditions: int, sm_names: list[str]) -> list[str]:
    names = []
    for k in range(max_conditions):
        names += [f"c{k}_present", f"c{k}_phase"]
        names += [f"c{k}_{n}" for n in sm_names]
        names += [f"c{k}_mask_{n}" for n in sm_names]
    return names


@dataclass(frozen=True)
class SimSpec:
    """What the generic recorder (``lerobot_cnmp.record``) needs to know about a sim.

    Attributes:
        env_config_cls: the LeRobot ``EnvConfig`` subclass that builds the env.
        expert_cls: scripted demonstrator, ``expert_cls(env.unwrapped)`` with ``reset()`` and ``act(step)``.
        demo_length: frames per demonstration.
        default_episodes: episodes recorded when none are asked for.
        default_conditions: the config's ``conditions`` used when recording.
        feature_names: per env-observation key (and ``action``), the names of the vector's entries.
        reset_options: ``(i, conditions) -> options`` passed to ``reset`` for episode ``i`` recorded with
            the config's ``conditions`` (e.g. to balance modes).
        episode_label: ``env.unwrapped -> str`` label of the recorded episode for the dataset card.
        description: markdown paragraph about the sim for the dataset card.
    """

    env_config_cls: type
    expert_cls: type
    demo_length: int
    default_episodes: int
    default_conditions: str
    feature_names: dict[str, list[str]] = field(default_factory=dict)
    reset_options: Callable[[int, str], dict[str, Any] | None] = lambda i, conditions: None
    episode_label: Callable[[Any], str] = lambda env: ""
    description: str = ""


def _obstacle2d_reset_options(i: int, conditions: str) -> dict[str, Any] | None:
    # even episodes pass over the obstacle, odd ones under it: the demos are balanced between modes
    # (the paper_* condition sets fix the mode themselves)
    if conditions in ("random", "mixed"):
        return {"mode": 1 if i % 2 == 0 else -1}
    return None


def _obstacle2d_spec() -> SimSpec:
    from lerobot_cnmp.experts.obstacle2d import Obstacle2DExpert

    return SimSpec(
        env_config_cls=CNMPObstacle2DEnv,
        expert_cls=Obstacle2DExpert,
        demo_length=200,
        default_episodes=64,
        default_conditions="random",
        feature_names={
            "action": ["x", "y"],
            "agent_pos": ["x", "y"],
            "environment_state": _condition_names(MAX_CONDITIONS, ["x", "y"]),
        },
        reset_options=_obstacle2d_reset_options,
        episode_label=lambda env: env.task.mode_name,
        description=(
            "A MuJoCo point mass (sphere, radius 0.03, mass 1) moves in the plane under position control "
            "(two slide joints, critically damped position servos, 2 ms physics step, 10 physics steps "
            "per 50 Hz control step) from the left (x=0) to the right (x=1) of a round obstacle (centre "
            "(0.5, 0), radius 0.2), passing either over it (mode +1) or under it (mode -1), as in the 2D "
            "obstacle-avoidance experiment of Seker et al. (RSS 2019, Sec. IV-A). Each episode follows a "
            "hidden reference of the family x(tau) = tau, y(tau) = y0 + (h - y0) sin(pi tau)^p, "
            "tau in [0, 1], with y0 in s[0.1, 0.3], h in s[0.45, 0.65], p in [0.9, 1.6] for mode s; the "
            "start is (0, y0) and the goal (1, y0). A scripted expert commands the reference position at "
            "each step's phase (tau_k = k/199); the recorded positions are those the simulated "
            "servo reached, not the formula."
        ),
    )


SIMS: dict[str, SimSpec] = {"cnmp_obstacle2d": _obstacle2d_spec()}

__all__ = ["CNMPObstacle2DEnv", "SIMS", "SimSpec", "OBSTACLE2D_GYM_ID", "ENV_STATE_DIM"]

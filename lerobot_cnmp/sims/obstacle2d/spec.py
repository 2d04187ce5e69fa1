"""The recorder's :class:`~lerobot_cnmp.sims.registry.SimSpec`s of the obstacle2d sim: ``cnmp_obstacle2d`` (64
demos balanced between the modes, conditions drawn at random) and ``cnmp_obstacle2d_shared`` (the same with the
``shared`` family: both modes share the start and the goal), with the dataset card's prose."""

from __future__ import annotations

import dataclasses
from typing import Any

from lerobot_cnmp.sims.obstacle2d.config import CNMPObstacle2DEnv
from lerobot_cnmp.sims.obstacle2d.expert import Obstacle2DExpert
from lerobot_cnmp.sims.obstacle2d.task import MAX_CONDITIONS
from lerobot_cnmp.sims.registry import SimSpec, point_mass_feature_names


def _obstacle2d_reset_options(i: int, conditions: str) -> dict[str, Any] | None:
    # even episodes pass over the obstacle, odd ones under it: the demos are balanced between modes
    # (the paper_* condition sets fix the mode themselves)
    if conditions in ("random", "mixed"):
        return {"mode": 1 if i % 2 == 0 else -1}
    return None


SPEC = SimSpec(
    env_config_cls=CNMPObstacle2DEnv,
    expert_cls=Obstacle2DExpert,
    demo_length=200,
    default_episodes=64,
    default_conditions="random",
    feature_names=point_mass_feature_names(MAX_CONDITIONS),
    reset_options=_obstacle2d_reset_options,
    episode_label=lambda env: env.task.mode_name,
    features_note=(
        "`observation.environment_state` holds the episode's conditions, constant within an episode, in "
        "the layout of `lerobot_cnmp.execution.conditions` with SM dimension 2 and 4 slots: slot k is "
        "`[present, phase, x, y, mask_x, mask_y]` (unused slots all zeros; `mask` marks the constrained dims)."
    ),
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

# the obstacle sim's ``shared`` family: same expert, features and balanced modes; the env config gets
# ``family="shared"``
SHARED_SPEC = dataclasses.replace(
    SPEC,
    config_kwargs=lambda conditions: {"conditions": conditions, "family": "shared"},
    description=SPEC.description.replace(
        "with y0 in s[0.1, 0.3], h in s[0.45, 0.65], p in [0.9, 1.6] for mode s; the start is (0, y0) and "
        "the goal (1, y0).",
        "with y0 in [-0.1, 0.1] for both modes (family `shared`: the two modes share the start (0, y0) and "
        "the goal (1, y0), the paper's setting), h in s[0.45, 0.65], p in [0.9, 1.6] for mode s.")
    + " Record and evaluate with `--env.family=shared`.",
)

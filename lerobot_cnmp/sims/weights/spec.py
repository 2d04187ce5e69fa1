"""The recorder's :class:`~lerobot_cnmp.sims.registry.SimSpec` of ``cnmp_weights``: the paper's 20 demos (2
shapes x 2 weight categories x 5 masses) and the dataset card's prose."""

from __future__ import annotations

from typing import Any

from lerobot_cnmp.sims.registry import SimSpec, records_only
from lerobot_cnmp.sims.weights.config import CNMPWeightsEnv
from lerobot_cnmp.sims.weights.expert import WeightsExpert
from lerobot_cnmp.sims.weights.task import DEMO_LENGTH, DEMO_MASSES, SHAPES, SM_NAMES, WEIGHT_CATEGORIES


def _weights_demos() -> list[tuple[int, float]]:
    # the paper's 20 demos: 2 shapes x 2 weight categories x 5 masses
    return [(shape, m) for shape in range(len(SHAPES)) for cat in WEIGHT_CATEGORIES
            for m in DEMO_MASSES[cat]]


def _weights_reset_options(i: int, conditions: str) -> dict[str, Any]:
    shape, mass = _weights_demos()[i % len(_weights_demos())]
    return {"shape": shape, "mass": mass}


SPEC = SimSpec(
    env_config_cls=CNMPWeightsEnv,
    expert_cls=WeightsExpert,
    demo_length=DEMO_LENGTH,
    default_episodes=len(_weights_demos()),
    default_conditions="demo_masses",
    feature_names={"action": list(SM_NAMES), "agent_pos": list(SM_NAMES)},
    reset_options=_weights_reset_options,
    episode_label=lambda env: f"{SHAPES[env.shape][0]}, {env.mass:g} kg",
    config_kwargs=records_only("cnmp_weights", "demo_masses", "its demo masses"),
    features_note=(
        "`observation.state` and `action` are the SM in task space: the tool point (x, y, z, m), the two "
        "finger joint positions (m) and the wrist force/torque reading (N, N·m, zeroed at reset, 100 ms "
        "low-pass). The env ignores the F/T entries of an action (forces cannot be commanded); the "
        "expert fills them with the previous reading. The container's class (shape, weight category) "
        "is in the episode labels above only, never in a feature."
    ),
    description=(
        "The UR10-like arm of cnmp_pickplace with a wrist force/torque sensor picks a container from the "
        "middle of the table, (0.70, -0.20), and places it on one of four 12 x 12 cm zones chosen by its "
        "shape (a 4 cm box or a 6 cm cube, which close the fingers to different widths) and its weight "
        "category (light 0.15-0.35 kg, heavy 0.65-0.95 kg), as in the sensorimotor classification "
        "experiment of Seker et al. (RSS 2019, Sec. IV-D). The arm is driven in task space: each step the "
        "tool-point target is converted to joints by IK. A scripted expert, who knows the class, plans "
        "approach, grasp, lift, carry, place and release with minimum-jerk segments; 5 masses per "
        "category and shape give the paper's 20 demonstrations."
    ),
)

"""The recorder's :class:`~lerobot_cnmp.sims.registry.SimSpec` of ``cnmp_pickplace``: the paper's 8 training
demos (the γ grid) and the dataset card's prose."""

from __future__ import annotations

from typing import Any

from lerobot_cnmp.sims.pickplace.config import CNMPPickPlaceEnv
from lerobot_cnmp.sims.pickplace.expert import PickPlaceExpert
from lerobot_cnmp.sims.pickplace.model import JOINT_NAMES
from lerobot_cnmp.sims.pickplace.planner import DEMO_LENGTH, PAPER_TRAIN_GRID
from lerobot_cnmp.sims.registry import SimSpec, records_only

JOINTS = [*JOINT_NAMES, "gripper"]


def _pickplace_reset_options(i: int, conditions: str) -> dict[str, Any]:
    # the paper's 8 training demos: object {2, 6} cm x obstacle {2, 4, 6, 8} cm, in turn
    grid = PAPER_TRAIN_GRID
    return {"task_params": grid[i % len(grid)]}


SPEC = SimSpec(
    env_config_cls=CNMPPickPlaceEnv,
    expert_cls=PickPlaceExpert,
    demo_length=DEMO_LENGTH,
    default_episodes=len(PAPER_TRAIN_GRID),
    default_conditions="grid",
    feature_names={"action": JOINTS, "agent_pos": JOINTS, "environment_state": ["object_cm", "obstacle_cm"]},
    reset_options=_pickplace_reset_options,
    episode_label=lambda env: "gamma=({:g}, {:g})".format(*env.task_params),
    features_note=(
        "`observation.task_params` holds gamma = (object height, obstacle height) in cm, constant within "
        "an episode; `observation.state` the measured joint angles (rad) and gripper closure in [0, 1]; "
        "`action` the commanded joint angles and gripper command."
    ),
    config_kwargs=records_only("cnmp_pickplace", "grid", "the paper's gamma grid"),
    description=(
        "A MuJoCo arm with the UR10's published DH kinematics (6 position-servoed joints, gravity "
        "compensated, 50 Hz control) and a parallel two-finger gripper picks a 4 x 4 cm box of height "
        "gamma_object cm from (0.70, -0.25) and places it on a 10 x 10 cm target area at (0.70, 0.25), "
        "carrying it along an arc over a 2 cm thick wall of height gamma_obstacle cm standing between "
        "them, as in the pick-and-place experiment of Seker et al. (RSS 2019, Sec. IV-C). The grasp is "
        "physical (friction of the finger pads only). A scripted expert plans the tool point in "
        "Cartesian space (grasp height linear in the object height, arc apex with the object 5 cm "
        "above the wall top, fixed phase timing, minimum-jerk segments) and converts it to joint angles by damped-least-squares IK "
        "on MuJoCo Jacobians; the SM is the 6 joint angles (radians) plus the gripper command in [0, 1], "
        "and gamma is stored as observation.task_params (cm)."
    ),
)

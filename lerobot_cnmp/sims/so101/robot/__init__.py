"""A MuJoCo SO-101 follower (``--robot.type=cnmp_so101_mujoco``) with the features of LeRobot's real
``so101_follower``, and a scripted leader (``--teleop.type=cnmp_so101_scripted``), so that the stock
``lerobot-record`` -> ``lerobot-train`` -> ``lerobot-rollout`` loop runs headless.

Registration: LeRobot's CLIs call ``register_third_party_plugins``, which imports every installed distribution
whose name starts with ``lerobot_policy_`` / ``lerobot_robot_`` / ``lerobot_teleoperator_``; ours is
``lerobot_policy_cnmp``, whose import imports :mod:`lerobot_cnmp` and so this package, registering the robot
and teleoperator configs as well (no separate distribution is needed). ``make_robot_from_config`` finds the
classes here by name (``SO101MujocoConfig`` -> ``SO101Mujoco`` in this package).
"""

from lerobot_cnmp.sims.so101.robot.config_so101_mujoco import JOINTS, SO101MujocoConfig, SO101ScriptedTeleopConfig
from lerobot_cnmp.sims.so101.robot.so101_mujoco import SO101Mujoco, SO101ScriptedTeleop, mjcf_path

__all__ = ["JOINTS", "SO101Mujoco", "SO101MujocoConfig", "SO101ScriptedTeleop", "SO101ScriptedTeleopConfig",
           "mjcf_path"]

"""lerobot-cnmp: Conditional Neural Movement Primitives for LeRobot.

Importing this package registers, with LeRobot and gymnasium:
- the policy type ``cnmp`` (``--policy.type=cnmp``),
- the baseline policy type ``promp`` (an open-loop ProMP fitted by ``lerobot-cnmp-fit-promp``, evaluated by
  ``lerobot-eval`` like any policy),
- the sims ``cnmp_obstacle2d`` (``--env.type=cnmp_obstacle2d``) and their gymnasium ids,
- the MuJoCo SO-101 robot ``cnmp_so101_mujoco`` (``--robot.type``) and its scripted leader
  ``cnmp_so101_scripted`` (``--teleop.type``).
"""

from lerobot_cnmp.policy.configuration_cnmp import CNMPConfig
from lerobot_cnmp.promp.configuration_promp import ProMPConfig  # --policy.type=promp: the open-loop baseline, evaluated by lerobot-eval
from lerobot_cnmp import sims  # noqa: F401  (registers env configs and gymnasium ids)
from lerobot_cnmp.sims.so101 import robot  # noqa: F401  (registers --robot.type=cnmp_so101_mujoco, --teleop.type=cnmp_so101_scripted)

__all__ = ["CNMPConfig", "ProMPConfig"]
__version__ = "0.1.0"

"""lerobot-cnmp: Conditional Neural Movement Primitives for LeRobot.

Importing this package registers, with LeRobot and gymnasium, without importing MuJoCo or any sim:
- the policy type ``cnmp`` (``--policy.type=cnmp``),
- the baseline policy type ``promp`` (an open-loop ProMP fitted by ``lerobot-cnmp-fit-promp``, evaluated by
  ``lerobot-eval`` like any policy),
- the sims' env types ``cnmp_obstacle2d``, ``cnmp_pickplace``, ``cnmp_weights``, ``cnmp_room``, ``cnmp_so101``
  and ``cnmp_metaworld`` (``--env.type``) and their gymnasium ids ``cnmp/*``,
- the MuJoCo SO-101 robot ``cnmp_so101_mujoco`` (``--robot.type``) and its scripted leader
  ``cnmp_so101_scripted`` (``--teleop.type``).
"""

from lerobot_cnmp import sims  # noqa: F401  (registers the env configs and gymnasium ids)
from lerobot_cnmp.policy.configuration_cnmp import CNMPConfig
from lerobot_cnmp.promp.configuration_promp import ProMPConfig
from lerobot_cnmp.sims.so101 import robot  # noqa: F401  (registers --robot.type and --teleop.type)

__all__ = ["CNMPConfig", "ProMPConfig"]
__version__ = "0.1.0"

"""lerobot-cnmp: Conditional Neural Movement Primitives for LeRobot.

Importing this package registers, with LeRobot and gymnasium:
- the policy type ``cnmp`` (``--policy.type=cnmp``),
- the sims ``cnmp_obstacle2d`` (``--env.type=cnmp_obstacle2d``) and their gymnasium ids.
"""

from lerobot_cnmp.configuration_cnmp import CNMPConfig
from lerobot_cnmp import envs  # noqa: F401  (registers env configs and gymnasium ids)

__all__ = ["CNMPConfig"]
__version__ = "0.1.0"

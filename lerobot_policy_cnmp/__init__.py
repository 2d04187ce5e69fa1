"""Plugin entry point: LeRobot imports `lerobot_policy_cnmp` by its distribution name.

Importing it registers the `cnmp` policy type and the CNMP sims (`--env.type=cnmp_obstacle2d`, ...).
"""

import lerobot_cnmp  # noqa: F401  (registration side effects)
from lerobot_cnmp import *  # noqa: F401,F403

"""Plugin entry point: LeRobot imports `lerobot_policy_cnmp` by its distribution name.

Importing it registers the `cnmp` and `promp` policy types, the CNMP sims (`--env.type=cnmp_obstacle2d`, ...,
gymnasium ids `cnmp/*`) and the MuJoCo SO-101 robot and teleoperator, without importing MuJoCo or any sim's
env module (see :mod:`lerobot_cnmp`).
"""

import lerobot_cnmp  # noqa: F401  (registration side effects)
from lerobot_cnmp import *  # noqa: F401,F403

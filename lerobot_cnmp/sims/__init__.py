"""The CNMP sims, one folder per sim (``config.py`` its LeRobot ``EnvConfig`` and gymnasium id, ``env.py`` the
gym env, ``expert.py`` its scripted demonstrator, ``spec.py`` the recorder's entry, and the model, task and
planner modules the env is built from), plus what they share (``base.py``, ``config.py``, ``point_mass.py``,
``path.py``, ``time_law.py``) and the recorder's registry (``registry.py``).

Importing this package registers every sim's ``--env.type=cnmp_*`` config and gymnasium id without importing
MuJoCo, MetaWorld or the SO-101 plugin: gymnasium imports an env module only when ``gym.make`` builds it, and
:data:`SIMS` imports a sim's spec (and expert) only when the recorder asks for it.
"""

from lerobot_cnmp.sims.metaworld.config import METAWORLD_GYM_ID, CNMPMetaWorldEnv
from lerobot_cnmp.sims.obstacle2d.config import OBSTACLE2D_GYM_ID, CNMPObstacle2DEnv
from lerobot_cnmp.sims.pickplace.config import PICKPLACE_GYM_ID, CNMPPickPlaceEnv
from lerobot_cnmp.sims.registry import SIMS, SimSpec
from lerobot_cnmp.sims.room.config import ROOM_GYM_ID, CNMPRoomEnv
from lerobot_cnmp.sims.so101.config import CNMPSO101Env
from lerobot_cnmp.sims.so101.task import SO101_GYM_ID
from lerobot_cnmp.sims.weights.config import WEIGHTS_GYM_ID, CNMPWeightsEnv

__all__ = [
    "SIMS", "SimSpec",
    "CNMPObstacle2DEnv", "CNMPPickPlaceEnv", "CNMPWeightsEnv", "CNMPRoomEnv", "CNMPSO101Env", "CNMPMetaWorldEnv",
    "OBSTACLE2D_GYM_ID", "PICKPLACE_GYM_ID", "WEIGHTS_GYM_ID", "ROOM_GYM_ID", "SO101_GYM_ID", "METAWORLD_GYM_ID",
]

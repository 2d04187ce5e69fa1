"""Scripted demonstrator for ``cnmp/Room-v0``: drives the sim along the planned path of the episode's room."""

from __future__ import annotations

from lerobot_cnmp.sims.room.task import DEMO_LENGTH
from lerobot_cnmp.sims.path import PathExpert


class RoomExpert(PathExpert):
    """Commands the room's planned path (:func:`lerobot_cnmp.sims.room.planner.plan_path`) at each step's own phase,
    over :data:`~lerobot_cnmp.sims.room.task.DEMO_LENGTH` steps by default; see :class:`PathExpert`."""

    default_demo_length = DEMO_LENGTH

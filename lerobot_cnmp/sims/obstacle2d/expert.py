"""Scripted demonstrator for ``cnmp/Obstacle2D-v0``: drives the sim along the episode's hidden reference."""

from __future__ import annotations

from lerobot_cnmp.sims.path import PathExpert


class Obstacle2DExpert(PathExpert):
    """Commands the episode's reference (:class:`~lerobot_cnmp.sims.obstacle2d.task.Obstacle2DTask`) at each
    step's own phase, over 200 steps by default; see :class:`PathExpert`."""

    default_demo_length = 200

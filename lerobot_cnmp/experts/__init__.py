"""Scripted demonstrators for the CNMP sims."""

from lerobot_cnmp.experts.obstacle2d import Obstacle2DExpert

__all__ = ["Obstacle2DExpert"]

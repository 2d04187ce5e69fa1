"""Scripted demonstrator for ``cnmp/Room-v0``: drives the sim along the planned path of the episode's room."""

from __future__ import annotations

import numpy as np

from lerobot_cnmp.envs.room import DEMO_LENGTH


class RoomExpert:
    """Commands the room's planned path (:func:`lerobot_cnmp.envs.room.plan_path`) at each step's own phase.

    At step ``k`` the action is ``task.position(tau_k)`` with ``tau_k = min(k/(T-1), 1)``, the convention of
    the obstacle2d expert: the recorded SM trajectory (the actions) starts at the start state, and the state
    sensed at step ``k`` is where step ``k - 1`` sent the servo.

    Args:
        env: the unwrapped :class:`~lerobot_cnmp.envs.room.RoomEnv` (after ``reset``).
        demo_length: ``T``, the number of control steps of a demonstration.
    """

    def __init__(self, env, demo_length: int = DEMO_LENGTH):
        if demo_length < 2:
            raise ValueError(f"demo_length must be >= 2, got {demo_length}")
        self.env = env
        self.demo_length = int(demo_length)

    def reset(self) -> None:
        if getattr(self.env, "task", None) is None:
            raise RuntimeError("reset the env before the expert")

    def act(self, step: int) -> np.ndarray:
        tau = min(step / (self.demo_length - 1), 1.0)
        return self.env.task.position(tau).astype(np.float32)

"""Scripted demonstrator for ``cnmp/Obstacle2D-v0``: drives the sim along the episode's hidden reference."""

from __future__ import annotations

import numpy as np


class Obstacle2DExpert:
    """Commands the reference position at each step's own phase.

    At step ``k`` the action is ``task.position(tau_k)`` with ``tau_k = min(k/(T-1), 1)``: the recorded SM
    trajectory (the actions) starts at the start state, and the state sensed at step ``k`` is where step
    ``k - 1`` sent the servo (the convention ``CNMPPolicy`` executes with). The recorded states are what the
    simulated point mass did under this controller.

    Args:
        env: the unwrapped :class:`~lerobot_cnmp.envs.obstacle2d.Obstacle2DEnv` (after ``reset``).
        demo_length: ``T``, the number of control steps of a demonstration.
    """

    def __init__(self, env, demo_length: int = 200):
        if demo_length < 2:
            raise ValueError(f"demo_length must be >= 2, got {demo_length}")
        self.env = env
        self.demo_length = int(demo_length)

    def reset(self) -> None:
        if getattr(self.env, "task", None) is None:
            raise RuntimeError("reset the env before the expert")

    def act(self, step: int) -> np.ndarray:
        # Command the reference at this step's own phase: the SM trajectory (the recorded actions) then
        # starts at the start state, and the state sensed at step k is what step k - 1 commanded.
        tau = min(step / (self.demo_length - 1), 1.0)
        return self.env.task.position(tau).astype(np.float32)

"""The scripted demonstrator of the point-mass sims: command the episode's planned path at each step's phase."""

from __future__ import annotations

import numpy as np


class PathExpert:
    """Commands ``env.task.position(tau_k)`` at step ``k``, with ``tau_k = min(k/(T-1), 1)``.

    The recorded SM trajectory (the actions) then starts at the start state, and the state sensed at step
    ``k`` is where step ``k - 1`` sent the servo (the convention ``CNMPPolicy`` executes with). The recorded
    states are what the simulated point mass did under this controller.

    Args:
        env: the unwrapped sim (after ``reset``), whose ``task`` has ``position(tau) -> (x, y)``.
        demo_length: ``T``, the number of control steps of a demonstration.
    """

    default_demo_length = 200

    def __init__(self, env, demo_length: int | None = None):
        demo_length = self.default_demo_length if demo_length is None else demo_length
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

"""Scripted demonstrator for the UR10 pick-and-place sim: replays the joint reference of the episode's gamma."""

from __future__ import annotations

import numpy as np

from lerobot_cnmp.sims.pickplace.kinematics import reference_trajectory


class PickPlaceExpert:
    """Commands :func:`~lerobot_cnmp.sims.pickplace.kinematics.reference_trajectory` of the episode's task parameters.

    At step ``k`` the action is the reference's row ``min(k, T - 1)``: six joint targets (rad) and the
    gripper command in [0, 1]. The reference is planned in Cartesian space (home -> above the object ->
    grasp at a height linear in the object's (``grasp_height``) -> close -> lift -> arc with the object
    5 cm above the wall top -> lower onto the target -> open -> retreat) with fixed phase timing and
    converted to joints by IK, so it is a smooth function of gamma. The recorded states are what the simulated arm did under this controller.

    Args:
        env: the unwrapped :class:`~lerobot_cnmp.sims.pickplace.env.PickPlaceEnv` (after ``reset``).
        demo_length: ``T``, the number of control steps of a demonstration.
    """

    def __init__(self, env, demo_length: int = 200):
        if demo_length < 2:
            raise ValueError(f"demo_length must be >= 2, got {demo_length}")
        self.env = env
        self.demo_length = int(demo_length)
        self._reference: np.ndarray | None = None

    def reset(self) -> None:
        task_params = getattr(self.env, "task_params", None)
        if task_params is None:
            raise RuntimeError("reset the env before the expert")
        self._reference = reference_trajectory(task_params, demo_length=self.demo_length).astype(np.float32)

    @property
    def reference(self) -> np.ndarray:
        """The ``[T, 7]`` joint reference of the current episode."""
        if self._reference is None:
            raise RuntimeError("call reset() before using the expert")
        return self._reference

    def act(self, step: int) -> np.ndarray:
        k = min(max(int(step), 0), self.demo_length - 1)
        return self.reference[k].copy()

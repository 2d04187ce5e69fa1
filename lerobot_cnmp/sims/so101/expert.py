"""Scripted demonstrator for the SO-101 pick-and-place sim (``cnmp_so101``): the plugin's own
``lerobot_env_so101.scripted.PickPlaceController`` behind the experts' interface."""

from __future__ import annotations

import numpy as np


class SO101PickPlaceExpert:
    """Drives :class:`lerobot_env_so101.scripted.PickPlaceController` from the unwrapped plugin env.

    The controller moves through hover, descend, close (10 steps), lift, traverse, lower, open (8 steps),
    retreat, done: each moving phase steers the grasp point toward its target with deltas
    ``error / action_scale`` clipped to 1 (0.4 near the block) until within 4 mm (or 60 steps), and it
    returns zero deltas with the jaw open once done. It reads what the observation does not hold: the grasp
    point between the jaws (``env.ik_point_pos``; ``agent_pos`` has the ``gripperframe`` site), the block
    sensor and the goal. It keeps the phase between calls, so :meth:`act` must be called once per env step,
    in order, after :meth:`reset` (``step`` is only checked against that order).

    Args:
        env: the unwrapped ``SO101PickPlaceGymEnv`` (``env.unwrapped`` of ``cnmp/SO101PickPlace-v0``).
        demo_length: unused (the controller's timing is its own); accepted for the recorder's interface.
    """

    def __init__(self, env, demo_length: int | None = None):
        from lerobot_env_so101.scripted import PickPlaceController

        if not hasattr(env, "ik_point_pos") or not hasattr(env, "goal_pos"):
            raise TypeError(f"expected the unwrapped SO101PickPlaceGymEnv, got {type(env).__name__}")
        self.env = env
        self.demo_length = demo_length
        # the controller converts metres to action units with the env's scale (a private attribute of the
        # plugin's SO101GymEnv: there is no public accessor)
        self.action_scale = float(env._action_scale)
        self.controller = PickPlaceController(action_scale=self.action_scale)
        self._next_step = 0

    def reset(self) -> None:
        self.controller.reset()
        self._next_step = 0

    @property
    def phase(self) -> str:
        return self.controller.phase.name

    def act(self, step: int) -> np.ndarray:
        if int(step) != self._next_step:
            raise ValueError(f"the SO-101 expert is stateful: expected step {self._next_step}, got {step}")
        self._next_step += 1
        block_pos = np.array(self.env.data.sensor("block_pos").data, dtype=np.float64)
        return self.controller.act(self.env.ik_point_pos, block_pos, self.env.goal_pos)

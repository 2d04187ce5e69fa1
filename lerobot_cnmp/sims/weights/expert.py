"""Scripted demonstrator for the shape x weight sim: carries the container to its class's zone."""

from __future__ import annotations

import numpy as np

from lerobot_cnmp.sims.time_law import minimum_jerk
from lerobot_cnmp.sims.weights.planner import MIN_REPLAN_STEPS, PHASE_STEPS, tcp_plan
from lerobot_cnmp.sims.weights.task import DEMO_LENGTH, FINGER_SM, FT_SM, POS_SM, SM_DIM, ZONE_XY


class WeightsExpert:
    """Commands :func:`~lerobot_cnmp.sims.weights.planner.tcp_plan` of the episode's true class (it is the
    demonstrator: it reads ``env.shape`` and ``env.target_zone``).

    The action at step ``k`` is the full SM: the planned tool-point position, the planned finger opening
    for both fingers (closing to the container's width, which the fingers then read) and, in the F/T entries
    (which the env ignores), the reading the env reported before the step, so the recorded action is the
    SM trajectory the sensors followed.

    After a weight switch (``env.weight_switched``) the expert re-plans at the step ``s`` it first sees it:
    from ``s`` on the remaining plan is shifted towards the new zone by an offset that ramps up with a
    minimum-jerk profile over ``D = max(carry_end - s, MIN_REPLAN_STEPS)`` steps; if the ramp would end
    after the nominal end of the carry, the plan holds at ``max(carry_end, s)`` for the difference,
    delaying the descent (the position stays continuous). Switches inside the env's window
    (steps 108-120) need no delay: the expert places on the new zone within the 200 steps.

    Args:
        env: the unwrapped :class:`~lerobot_cnmp.sims.weights.env.WeightsEnv` (after ``reset``).
        demo_length: ``T``, the number of control steps of a demonstration.
    """

    def __init__(self, env, demo_length: int = DEMO_LENGTH):
        if demo_length < 2:
            raise ValueError(f"demo_length must be >= 2, got {demo_length}")
        self.env = env
        self.demo_length = int(demo_length)
        self._zone: int | None = None
        self._replan: tuple[int, int, int, np.ndarray] | None = None  # (start step, ramp steps, delay, offset)

    def reset(self) -> None:
        if getattr(self.env, "shape", None) is None:
            raise RuntimeError("reset the env before the expert")
        self._zone = int(self.env.target_zone)
        self._replan = None

    def _scale(self, k200: float) -> float:
        """A 200-step-scale time in steps of this demonstration."""
        return k200 * (self.demo_length - 1) / 199.0

    def plan(self, step: int) -> tuple[np.ndarray, np.ndarray]:
        """``(tool-point position [3], finger opening)`` planned for ``step`` (after any re-plan)."""
        if self._zone is None:
            raise RuntimeError("call reset() before using the expert")
        k = float(step)
        offset = np.zeros(3)
        if self._replan is not None:
            s, ramp, delay, delta = self._replan
            carry_end = self._scale(PHASE_STEPS["carry_end"])
            if k >= s:
                offset = minimum_jerk((k - s) / ramp) * delta
                hold = max(carry_end, s)
                if delay > 0 and k >= hold:  # hold where the plan is, then go on
                    k = hold if k < hold + delay else k - delay
        pos, fingers = tcp_plan(self.env.shape, self._zone, [k], self.demo_length)
        return pos[0] + offset, float(fingers[0])

    def act(self, step: int) -> np.ndarray:
        step = max(int(step), 0)
        env = self.env
        if self._zone is None:
            raise RuntimeError("call reset() before using the expert")
        if self._replan is None and int(env.target_zone) != self._zone:
            carry_end = self._scale(PHASE_STEPS["carry_end"])
            ramp = max(carry_end - step, self._scale(MIN_REPLAN_STEPS))
            delay = int(np.ceil(max(0.0, step + ramp - carry_end)))
            delta = np.zeros(3)
            delta[:2] = ZONE_XY[int(env.target_zone)] - ZONE_XY[self._zone]
            self._replan = (step, ramp, delay, delta)
        pos, finger = self.plan(step)
        action = np.zeros(SM_DIM, dtype=np.float32)
        action[POS_SM] = pos
        action[FINGER_SM] = finger
        action[FT_SM] = env.ft_reading()
        return action

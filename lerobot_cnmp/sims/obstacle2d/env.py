"""MuJoCo 2D obstacle-avoidance sim (CNMP paper, Sec. IV-A).

A point mass moves in the plane, position-controlled in x and y, around a round obstacle centred at
(0.5, 0). Demonstrations pass either over (``mode=+1``) or under (``mode=-1``) the obstacle, which is the
multi-modal task family of Seker et al. (RSS 2019, Fig. 4)::

    x(tau) = tau,    y(tau) = y0 + (h - y0) * sin(pi * tau) ** p,    tau in [0, 1]

with ``y0 in s*[0.1, 0.3]``, ``h in s*[0.45, 0.65]``, ``p in [0.9, 1.6]`` for mode ``s``. Each episode draws
a hidden reference trajectory of the family (its start is the reset state, its end the goal) and a set of
conditions taken from it; the conditions are the only task information in the observation
(``environment_state``, encoded with :func:`lerobot_cnmp.execution.conditions.encode_conditions`).

Task families (``family``, :mod:`lerobot_cnmp.sims.obstacle2d.task`): ``mirrored`` (the above; the modes start and end at mirrored heights, so a start or
goal alone names the mode) or ``shared`` (the paper's setting: both modes start at (0, y0) and end at (1, y0)
with the same ``y0 in [-0.1, 0.1]``, ``h in s*[0.45, 0.65]``; a method that averages the modes goes through
the obstacle).

Success (``info["is_success"]``, every step): goal reached (within 0.05), every condition passed (the
closest visited position is within 0.05 on the constrained dims) and no contact with the obstacle so far.

Actuators (``actuator``): ``servo`` (the stiff, critically damped position servo the demos were recorded
with) or ``rate_limited`` (the same servo behind a set point that moves toward the commanded position at
most ``rate_limit`` m/s (default ``RATE_LIMIT``), slower than the demonstrated motion: a body commanded on the demos' schedule
falls behind and cuts corners).
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from lerobot_cnmp.execution.conditions import Condition  # noqa: E402
from lerobot_cnmp.sims.obstacle2d.model import (  # noqa: E402
    ACTION_HIGH,
    ACTION_LOW,
    ACTUATOR_CHOICES,
    AGENT_RADIUS,
    CONTROL_FPS,
    HOLD_STEPS,
    MJCF,
    N_SUBSTEPS,
    OBSTACLE_CENTER,
    OBSTACLE_RADIUS,
    PERTURB_STEP_RANGE,
    PERTURBATION_CHOICES,
    PUSH_DISTANCE,
    PUSH_MIN_CLEARANCE,
    RATE_LIMIT,
)
from lerobot_cnmp.sims.obstacle2d.task import (  # noqa: E402
    CONDITION_CHOICES,
    MAX_CONDITIONS,
    SM_DIM,
    Obstacle2DTask,
    check_family,
    sample_episode,
)
from lerobot_cnmp.sims.point_mass_env import SUCCESS_TOL, PointMassEnv  # noqa: E402


class Obstacle2DEnv(PointMassEnv):
    """Point mass around a round obstacle; see the module docstring.

    Args:
        conditions: how each episode's conditions are chosen, one of ``CONDITION_CHOICES``.
        perturbation: ``"none"``, ``"push"`` (instant 0.12 displacement away from the obstacle, normal to
            the motion, at a random step in [50, 120]), ``"push_toward"`` (the same, toward the obstacle's
            centre), ``"push_random"`` (the same, in a uniformly random direction) or ``"hold"`` (agent held
            still for 30 steps from a random step in [50, 120]).
        family: ``"mirrored"`` or ``"shared"`` (both modes share start and goal), see the module docstring.
        actuator: ``"servo"`` or ``"rate_limited"`` (set point slewed at ``rate_limit`` m/s), see the module
            docstring.
        rate_limit: the ``rate_limited`` actuator's top speed, m/s (default ``RATE_LIMIT``).
        render_mode: ``"rgb_array"`` or None.
        render_size: side of the square rendered image, pixels.
        terminate_on_success: end the episode (``terminated=True``) as soon as it is successful.
        max_episode_steps: if given, the env truncates itself at this many steps (``gym.make`` normally
            handles this through its ``TimeLimit`` wrapper instead).

    ``reset(options=...)`` accepts ``{"mode": +1 | -1 | "over" | "under"}`` to force the avoidance mode, or
    ``{"task": Obstacle2DTask, "conditions": [Condition, ...]}`` to set the episode explicitly.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": CONTROL_FPS}
    camera = "top"
    action_low, action_high = ACTION_LOW, ACTION_HIGH
    n_substeps = N_SUBSTEPS
    sm_dim, max_conditions = SM_DIM, MAX_CONDITIONS
    reset_option_keys = frozenset({"mode", "task", "conditions"})

    def __init__(
        self,
        conditions: str = "mixed",
        perturbation: str = "none",
        render_mode: str | None = "rgb_array",
        render_size: int = 256,
        terminate_on_success: bool = True,
        max_episode_steps: int | None = None,
        family: str = "mirrored",
        actuator: str = "servo",
        rate_limit: float = RATE_LIMIT,
    ):
        if conditions not in CONDITION_CHOICES:
            raise ValueError(f"unknown conditions {conditions!r}; choose one of {list(CONDITION_CHOICES)}")
        if perturbation not in PERTURBATION_CHOICES:
            raise ValueError(
                f"unknown perturbation {perturbation!r}; choose one of {list(PERTURBATION_CHOICES)}"
            )
        check_family(family, conditions)
        if actuator not in ACTUATOR_CHOICES:
            raise ValueError(f"unknown actuator {actuator!r}; choose one of {list(ACTUATOR_CHOICES)}")
        self.conditions_mode = conditions
        self.perturbation = perturbation
        self.family = family
        self.actuator = actuator
        if not rate_limit > 0:
            raise ValueError(f"rate_limit must be > 0 (m/s), got {rate_limit}")
        self.rate_limit = float(rate_limit)
        self._init_options(render_mode, render_size, terminate_on_success, max_episode_steps)

        self._init_point_mass(MJCF, goal_site="goal", blocking_geoms=("obstacle",))
        self.condition_kind: str = ""

    # --- public helpers ------------------------------------------------------------------------------
    @property
    def task_description(self) -> str:
        return "reach the goal around the obstacle"

    @property
    def goal(self) -> np.ndarray:
        return self.task.goal

    # --- episode -----------------------------------------------------------------------------------
    def _new_episode(self, options: dict) -> None:
        if "task" in options:
            task = self._task_option(options, Obstacle2DTask)
            conds = list(options.get("conditions", []))
            kind = "custom"
        else:
            if "conditions" in options:
                raise ValueError("options['conditions'] needs options['task'] too")
            task, conds, kind = sample_episode(self.np_random, self.conditions_mode, options.get("mode"), self.family)
        self._set_episode(task, conds)
        self.condition_kind = kind

        # perturbation schedule, drawn after the task so a seed gives the same task with or without it
        self._perturb_step = (
            int(self.np_random.integers(PERTURB_STEP_RANGE[0], PERTURB_STEP_RANGE[1] + 1))
            if self.perturbation != "none"
            else -1
        )
        # push_random: its direction, drawn after the step (the other perturbations draw the same sequence)
        self._push_angle = float(self.np_random.uniform(0.0, 2 * np.pi)) if self.perturbation == "push_random" else 0.0
        self._perturbed = False
        self._hold_pos: np.ndarray | None = None
        self._hold_left = 0
        self._setpoint = np.array(task.start, dtype=np.float64)  # the rate_limited actuator's set point

    def _goal_marker(self) -> np.ndarray:
        return self.task.goal

    def _place_condition_marker(self, sid: int, c: Condition) -> None:
        m = self.model
        if c.dims is None or len(c.dims) == SM_DIM:
            m.site_pos[sid, :2] = c.values
            m.site_size[sid] = [0.025, 0.025, 0.002]
        else:  # one-dimensional condition: a bar across the scene at that coordinate
            m.site_pos[sid, :2] = [0.5 if 0 not in c.dims else c.values[0], c.values[1]]
            m.site_size[sid] = [0.6, 0.006, 0.002] if 0 not in c.dims else [0.006, 0.6, 0.002]

    # --- step ----------------------------------------------------------------------------------------
    def _actuate(self, action: np.ndarray) -> None:
        if self._hold_left > 0:
            self._hold_left -= 1
            self.data.qpos[:2] = self._hold_pos
            self.data.qvel[:] = 0.0
            self.data.ctrl[:] = self._hold_pos
            self._setpoint = self._hold_pos.copy()
            self.data.time += N_SUBSTEPS * self.model.opt.timestep
            mujoco.mj_forward(self.model, self.data)
            return
        if self.actuator == "rate_limited":
            delta = action - self._setpoint
            most = self.rate_limit * N_SUBSTEPS * self.model.opt.timestep
            dist = float(np.linalg.norm(delta))
            self._setpoint = self._setpoint + (delta if dist <= most else delta * (most / dist))
            action = self._setpoint
        self._run_servos(action)

    def _after_step(self) -> None:
        if self._step == self._perturb_step:  # push: displaced now; hold: held for the next HOLD_STEPS
            self._start_perturbation()

    def _info(self) -> dict:
        goal_error = self._distance_to(self.task.goal)
        n_passed = self._conditions_passed()
        success = goal_error <= SUCCESS_TOL and n_passed == len(self.conditions) and not self._contact
        return {
            "is_success": bool(success),
            "contact": bool(self._contact),
            "goal_error": goal_error,
            "conditions_passed": n_passed,
            "perturbed": bool(self._perturbed),
        }

    def _start_perturbation(self):
        self._perturbed = True
        pos = self.data.qpos[:2].copy()
        if self.perturbation in ("push_toward", "push_random"):
            if self.perturbation == "push_toward":
                n = OBSTACLE_CENTER - pos
                n = n / max(np.linalg.norm(n), 1e-9)
            else:
                n = np.array([np.cos(self._push_angle), np.sin(self._push_angle)])
            # never into the obstacle: shortened to keep PUSH_MIN_CLEARANCE between the agent and it
            lengths = np.linspace(PUSH_DISTANCE, 0.0, 121)
            clear = np.linalg.norm(pos + lengths[:, None] * n - OBSTACLE_CENTER, axis=1) - OBSTACLE_RADIUS - AGENT_RADIUS
            length = float(lengths[np.argmax(clear >= PUSH_MIN_CLEARANCE)]) if (clear >= PUSH_MIN_CLEARANCE).any() else 0.0
            self.data.qpos[:2] = pos + length * n
            self.data.qvel[:] = 0.0
            mujoco.mj_forward(self.model, self.data)
        elif self.perturbation == "push":
            away = pos - OBSTACLE_CENTER
            away = away / max(np.linalg.norm(away), 1e-9)
            vel = self.data.qvel[:2].copy()
            speed = np.linalg.norm(vel)
            if speed > 1e-6:
                n = np.array([-vel[1], vel[0]]) / speed
                if np.dot(n, away) < 0:
                    n = -n
            else:
                n = away
            self.data.qpos[:2] = pos + PUSH_DISTANCE * n
            self.data.qvel[:] = 0.0
            mujoco.mj_forward(self.model, self.data)
        elif self.perturbation == "hold":
            self._hold_pos = pos
            self._hold_left = HOLD_STEPS

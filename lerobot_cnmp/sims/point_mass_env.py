"""What the point-mass sims (obstacle2d, room) share as gymnasium envs, on the MJCF of
:mod:`lerobot_cnmp.sims.point_mass`: the episode's conditions in the observation, the reset of the mass to the
task's start, the step (clip, servo substeps, contact flag), the closest approach to each condition, and the
goal and condition markers.

Kept apart from :mod:`lerobot_cnmp.sims.point_mass` (numpy only) so that the sims' configs, which import their
models, stay free of MuJoCo."""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco  # noqa: E402
import numpy as np  # noqa: E402
from gymnasium import spaces  # noqa: E402

from lerobot_cnmp.execution.conditions import Condition, encode_conditions  # noqa: E402
from lerobot_cnmp.sims.base import MujocoSimEnv, contacts_with  # noqa: E402

SUCCESS_TOL = 0.05  # a condition is passed, a goal reached, within this distance
MARKER_SHOWN = [0.05, 0.05, 0.05, 0.9]  # rgba of a condition's marker
MARKER_HIDDEN = [0, 0, 0, 0]


class PointMassEnv(MujocoSimEnv):
    """Base of the point-mass sims: a mass on two slide joints driven by (x, y) position servos.

    A subclass sets ``action_low`` / ``action_high`` (the servos' range, the action space), ``n_substeps``
    (physics steps per control step), ``sm_dim`` and ``max_conditions`` (the layout of
    ``environment_state``), calls :meth:`_init_point_mass` in its constructor, and provides
    ``_new_episode(options)`` (draws or sets the task and calls :meth:`_set_episode`), ``_goal_marker()``
    (where the goal site goes) and ``_info()``. ``self._contact`` records whether the agent has touched one of
    ``self._blocking_gids`` during the episode; ``self._cond_min_err[k]`` is the closest approach so far to
    condition ``k``, on its constrained dimensions.
    """

    action_low: np.ndarray
    action_high: np.ndarray
    n_substeps: int = 10
    sm_dim: int = 2
    max_conditions: int = 3
    reset_option_keys: frozenset = frozenset({"task"})

    def _init_point_mass(self, mjcf: str, goal_site: str, blocking_geoms, extra_observations=None) -> None:
        """Build the model, the ids of the agent, the blocking geoms and the markers, and the spaces
        (``agent_pos``, ``environment_state`` and ``extra_observations``)."""
        self.model = mujoco.MjModel.from_xml_string(mjcf)
        self.data = mujoco.MjData(self.model)
        self._agent_gid = self._geom_id("agent")
        self._blocking_gids = frozenset(self._geom_id(n) for n in blocking_geoms)
        self._goal_sid = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_SITE, goal_site)
        self._cond_sids = [
            mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_SITE, f"cond{k}") for k in range(self.max_conditions)
        ]
        env_state_dim = self.max_conditions * (2 + 2 * self.sm_dim)
        self.observation_space = spaces.Dict(
            {
                "agent_pos": spaces.Box(-np.inf, np.inf, shape=(2,), dtype=np.float32),
                "environment_state": spaces.Box(-np.inf, np.inf, shape=(env_state_dim,), dtype=np.float32),
                **(extra_observations or {}),
            }
        )
        self.action_space = spaces.Box(self.action_low, self.action_high, dtype=np.float32)
        self.task = None
        self.conditions: list[Condition] = []
        self._env_state = np.zeros(env_state_dim, dtype=np.float32)

    def _geom_id(self, name: str) -> int:
        return mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_GEOM, name)

    @property
    def agent_pos(self) -> np.ndarray:
        return self.data.qpos[:2].copy()

    # --- gym API -------------------------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self._new_episode(self._checked_options(options))
        self._reset_physics()
        self._step = 0
        self._contact = False
        self._cond_min_err = np.full(len(self.conditions), np.inf)
        self._update_progress()
        return self._obs(), self._info()

    def step(self, action):
        if self.task is None:
            raise RuntimeError("call reset() before step()")
        action = np.clip(np.asarray(action, dtype=np.float64).reshape(2), self.action_low, self.action_high)
        self._actuate(action)
        self._step += 1
        self._after_step()
        self._update_progress()
        return self._step_result()

    # --- episode -------------------------------------------------------------------------------------
    def _checked_options(self, options: dict | None) -> dict:
        """``options`` as a dict, refusing keys other than ``reset_option_keys`` (keys LeRobot's rollout
        adds itself, such as ``"lerobot_new_rollout"``, are not ours to check)."""
        options = dict(options or {})
        unknown = {k for k in options if not str(k).startswith("lerobot_")} - self.reset_option_keys
        if unknown:
            raise ValueError(f"unknown reset options {sorted(unknown)}; known: {sorted(self.reset_option_keys)}")
        return options

    @staticmethod
    def _task_option(options: dict, task_type: type):
        """``options["task"]``, checked to be a ``task_type``."""
        task = options["task"]
        if not isinstance(task, task_type):
            name = task_type.__name__
            article = "an" if name[0] in "AEIOU" else "a"
            raise ValueError(f"options['task'] must be {article} {name}, got {type(task).__name__}")
        return task

    def _set_episode(self, task, conditions: list[Condition]) -> None:
        """The episode's task and conditions, and the conditions encoded as ``environment_state``."""
        self.task, self.conditions = task, conditions
        self._env_state = encode_conditions(conditions, sm_dim=self.sm_dim, max_conditions=self.max_conditions)

    def _reset_physics(self) -> None:
        """Fresh physics with the agent at rest at ``task.start`` (its servos holding it there), the scene
        placed (:meth:`_place_scene`) and the markers set."""
        mujoco.mj_resetData(self.model, self.data)
        self._place_scene()
        self._set_markers()
        start = self.task.start
        self.data.qpos[:2] = start
        self.data.qvel[:] = 0.0
        self.data.ctrl[:] = start
        mujoco.mj_forward(self.model, self.data)  # after the scene and markers: rendering reads their poses

    def _place_scene(self) -> None:
        """Place the episode's own geoms (none by default)."""

    # --- step ----------------------------------------------------------------------------------------
    def _actuate(self, action: np.ndarray) -> None:
        """One control step with the servos commanded to ``action`` (already clipped)."""
        self._run_servos(action)

    def _run_servos(self, target: np.ndarray) -> None:
        """Command the servos to ``target`` and run ``n_substeps`` physics steps, recording contact."""
        self.data.ctrl[:] = target
        for _ in range(self.n_substeps):
            mujoco.mj_step(self.model, self.data)
            if not self._contact and self._in_contact():
                self._contact = True

    def _after_step(self) -> None:
        """What happens after the physics of a step, before progress is tracked (nothing by default)."""

    def _in_contact(self) -> bool:
        """Whether the agent touches a blocking geom now."""
        return not self._blocking_gids.isdisjoint(contacts_with(self.data, self._agent_gid).tolist())

    # --- progress, observation -----------------------------------------------------------------------
    def _update_progress(self) -> None:
        """The closest approach to each condition so far, on its constrained dimensions."""
        pos = self.data.qpos[:2]
        for k, c in enumerate(self.conditions):
            dims = list(range(self.sm_dim)) if c.dims is None else list(c.dims)
            err = float(np.linalg.norm(pos[dims] - np.asarray(c.values)[dims]))
            self._cond_min_err[k] = min(self._cond_min_err[k], err)

    def _conditions_passed(self) -> int:
        """How many conditions the agent has passed within :data:`SUCCESS_TOL`."""
        return int(np.sum(self._cond_min_err <= SUCCESS_TOL))

    def _distance_to(self, point) -> float:
        return float(np.linalg.norm(self.data.qpos[:2] - np.asarray(point)))

    def _obs(self) -> dict:
        return {"agent_pos": self.data.qpos[:2].astype(np.float32), "environment_state": self._env_state.copy()}

    # --- markers -------------------------------------------------------------------------------------
    def _set_markers(self) -> None:
        """The goal site at :meth:`_goal_marker`, one shown marker per condition, the other markers hidden."""
        m = self.model
        m.site_pos[self._goal_sid, :2] = self._goal_marker()
        for k, sid in enumerate(self._cond_sids):
            if k < len(self.conditions):
                self._place_condition_marker(sid, self.conditions[k])
                m.site_rgba[sid] = MARKER_SHOWN
            else:
                m.site_rgba[sid] = MARKER_HIDDEN

    def _place_condition_marker(self, sid: int, condition: Condition) -> None:
        """Put the marker site ``sid`` at ``condition``'s point."""
        self.model.site_pos[sid, :2] = condition.values

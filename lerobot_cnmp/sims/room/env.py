"""MuJoCo room sim with image observations (CNMP paper, Sec. IV-B).

A point mass moves from the left to the right side of a walled 2D room, ``x, y in [0, 1]``, around two
rectangular obstacles attached to opposite walls, as in the top-down image experiment of Seker et al.
(RSS 2019, Fig. 5-6). Each episode draws a room (:class:`RoomTask`): one obstacle with its centre
``x in [0.25, 0.45]`` and one with ``x in [0.55, 0.75]``, one of them attached to the bottom wall (it
reaches from ``y = 0`` up to its length) and the other to the top wall (from ``y = 1`` down), which one
at random; widths in ``[0.06, 0.14]``, lengths in ``[0.35, 0.6]``; a start with ``x in [0.05, 0.12]`` and
an end with ``x in [0.88, 0.95]``, both with ``y in [0.1, 0.9]``.

The planner (:func:`plan_path`, the paper's "simple heuristic", a pure function of the room) passes each
obstacle through the middle of the gap it leaves open: waypoints start, ``(left edge - MARGIN, gap
centre)`` and ``(right edge + MARGIN, gap centre)`` of the left obstacle, the same for the right one, end;
``y(x)`` is the shape-preserving monotone cubic (PCHIP, scipy's ``PchipInterpolator``) through them, so it never
overshoots a waypoint (flat over each obstacle, monotone in between) and keeps at least ``MARGIN`` from
the obstacles. The path is traversed by arc length with a minimum-jerk time law,
``s(tau) = L * (10 tau^3 - 15 tau^4 + 6 tau^5)``: zero velocity at both ends and a peak speed along the
path of ``1.875 L`` per unit phase however steep the path is (a minimum-jerk law on ``x`` alone would need
several m/s in y where the path switches gaps within a narrow space). Rooms whose plan
is not valid (waypoints closer than :data:`MIN_TRANSITION_DX` in x, e.g. obstacles that overlap in x, or
a planned path closer than :data:`MIN_CLEARANCE` = agent radius + 0.03 to an obstacle or wall) are
redrawn from the same generator inside :meth:`RoomTask.sample`, so every sampled room is passable by
its plan (about 1 in 5 draws is redrawn; the recorder's seeds stay deterministic).

Observations:

* ``agent_pos`` (2,): the point mass's position.
* ``environment_state`` (18,): the episode's conditions in the :mod:`lerobot_cnmp.execution.conditions` layout, SM
  dimension 2, :data:`MAX_CONDITIONS` = 3 slots. Option ``condition``: ``start_end`` (the planned start
  at phase 0 and end at phase 1), ``via_end`` (the planned point at a phase drawn in [0.3, 0.7], and the
  end) or ``via`` (that planned point only). The agent always starts at the room's start.
* ``pixels["top"]`` (image_size, image_size, 3) uint8: a binary mask of the room seen from above by an
  orthographic MuJoCo camera framing exactly the room square: obstacles 255 (white), free floor 0; the
  agent, the floor texture and the markers are hidden. Image row 0 is the top of the room (y = 1),
  column 0 its left side (x = 0): pixel ``(r, c)`` covers ``x = (c + 0.5) / W``, ``y = 1 - (r + 0.5) / H``
  at its centre, and is white iff that centre lies on an obstacle (rendered with one sample per pixel,
  then thresholded). The walls lie just outside the room square, so they are not in the image. The mask
  is static: rendered once per reset.

Success (``info["is_success"]``, judged every step): no contact of the agent with an obstacle or a wall
so far; every condition passed (the closest visited position within :data:`SUCCESS_TOL` = 0.05 of it,
as obstacle2d judges via points); the agent on the right side of the room (within 0.05 of the end
condition when there is one, ``x >= 0.85`` otherwise) and at rest (speed below :data:`REST_SPEED`). A
collision terminates the episode as a failure.
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco  # noqa: E402
import numpy as np  # noqa: E402
from gymnasium import spaces  # noqa: E402

from lerobot_cnmp.execution.conditions import Condition  # noqa: E402
from lerobot_cnmp.sims.room.model import (  # noqa: E402
    ACTION_HIGH,
    ACTION_LOW,
    AGENT_RADIUS,
    CONTROL_FPS,
    DEFAULT_IMAGE_SIZE,
    MAX_CONDITIONS,
    MAX_IMAGE_SIZE,
    MJCF,
    N_SUBSTEPS,
    OBSTACLE_GEOMS,
    OBSTACLE_HALF_HEIGHT,
    SM_DIM,
    WALL_GEOMS,
)
from lerobot_cnmp.sims.point_mass_env import SUCCESS_TOL, PointMassEnv  # noqa: E402
from lerobot_cnmp.sims.room.planner import distance_to_obstacles  # noqa: E402
from lerobot_cnmp.sims.room.task import (  # noqa: E402
    CONDITION_CHOICES,
    VIA_PHASE_RANGE,
    RoomTask,
    episode_conditions,
)

RIGHT_SIDE_X = 0.85  # "on the right side" without an end condition
REST_SPEED = 0.05  # m/s: at rest below this speed


class RoomEnv(PointMassEnv):
    """Point mass crossing a room with two obstacles, seen as a top-down mask; see the module docstring.

    Args:
        condition: which conditions each episode gets, one of ``CONDITION_CHOICES``.
        image_size: side of the square mask image ``pixels["top"]``, pixels (16 to 1024).
        render_mode: ``"rgb_array"`` or None.
        render_size: side of the square colour image of :meth:`render`, pixels.
        terminate_on_success: end the episode (``terminated=True``) as soon as it is successful.
        max_episode_steps: if given, the env truncates itself at this many steps (``gym.make`` normally
            handles this through its ``TimeLimit`` wrapper instead).

    ``reset(options=...)`` accepts ``{"task": RoomTask}`` to set the room and ``{"via_phase": t}`` (t in
    [0, 1]) to set the via point's phase; otherwise both are drawn from the reset seed (the room first,
    then the via phase, also when the condition has no via point, so a seed gives the same room and phase
    under every ``condition``).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": CONTROL_FPS}
    camera = "view"
    action_low, action_high = ACTION_LOW, ACTION_HIGH
    n_substeps = N_SUBSTEPS
    sm_dim, max_conditions = SM_DIM, MAX_CONDITIONS
    reset_option_keys = frozenset({"task", "via_phase"})

    def __init__(
        self,
        condition: str = "start_end",
        image_size: int = DEFAULT_IMAGE_SIZE,
        render_mode: str | None = "rgb_array",
        render_size: int = 256,
        terminate_on_success: bool = True,
        max_episode_steps: int | None = None,
    ):
        if condition not in CONDITION_CHOICES:
            raise ValueError(f"unknown condition {condition!r}; choose one of {list(CONDITION_CHOICES)}")
        if not 16 <= int(image_size) <= MAX_IMAGE_SIZE:
            raise ValueError(f"image_size must be in [16, {MAX_IMAGE_SIZE}] pixels, got {image_size}")
        self.condition = condition
        self.image_size = int(image_size)
        self._init_options(render_mode, render_size, terminate_on_success, max_episode_steps)

        s = self.image_size
        self._init_point_mass(
            MJCF,
            goal_site="end",
            blocking_geoms=(*WALL_GEOMS, *OBSTACLE_GEOMS),
            extra_observations={"pixels": spaces.Dict({"top": spaces.Box(0, 255, shape=(s, s, 3), dtype=np.uint8)})},
        )
        self._obstacle_gids = [self._geom_id(n) for n in OBSTACLE_GEOMS]
        self._mask_gids = sorted(self._blocking_gids)
        self._mask_renderer: mujoco.Renderer | None = None
        self._mask_option = mujoco.MjvOption()
        self._mask_option.geomgroup[:] = 0
        self._mask_option.geomgroup[0] = 1  # walls and obstacles only: no floor (1), no agent (2)
        self._mask_option.sitegroup[:] = 0  # no markers
        self.condition_kind: str = condition
        self.via_phase: float = float("nan")
        self._end_condition: Condition | None = None
        self._mask = np.zeros((s, s, 3), dtype=np.uint8)

    # --- public helpers ------------------------------------------------------------------------------
    @property
    def task_description(self) -> str:
        return "cross the room from left to right around the obstacles"

    @property
    def mask(self) -> np.ndarray:
        """The episode's top-down mask (a copy), ``(image_size, image_size, 3)`` uint8 in {0, 255}."""
        return self._mask.copy()

    # --- episode -----------------------------------------------------------------------------------
    def _new_episode(self, options: dict) -> None:
        task = self._task_option(options, RoomTask) if "task" in options else RoomTask.sample(self.np_random)
        via_phase = float(self.np_random.uniform(*VIA_PHASE_RANGE))
        if "via_phase" in options:
            via_phase = float(options["via_phase"])
            if not 0.0 <= via_phase <= 1.0:
                raise ValueError(f"options['via_phase'] must be in [0, 1], got {via_phase}")
        self.via_phase = via_phase
        self._set_episode(task, episode_conditions(task, self.condition, via_phase))
        self._end_condition = next((c for c in self.conditions if c.phase == 1.0), None)
        self._min_clearance = np.inf

    def _reset_physics(self) -> None:
        super()._reset_physics()
        self._mask = self._render_mask()  # static: rendered once per episode

    def _place_scene(self) -> None:
        m = self.model
        for gid, ob in zip(self._obstacle_gids, self.task.obstacles):
            x0, x1, y0, y1 = ob.rect
            half = [(x1 - x0) / 2, (y1 - y0) / 2, OBSTACLE_HALF_HEIGHT]
            body = m.geom_bodyid[gid]
            m.body_pos[body] = [(x0 + x1) / 2, (y0 + y1) / 2, 0.0]
            m.geom_size[gid] = half
            # collision detection prunes with bounding volumes computed at compile time (the geom's
            # bounding sphere and box, its body's one-node BVH, all in body coordinates): they follow
            m.geom_rbound[gid] = float(np.linalg.norm(half))
            m.geom_aabb[gid] = [0.0, 0.0, 0.0, *half]
            m.bvh_aabb[m.body_bvhadr[body]] = [0.0, 0.0, 0.0, *half]

    def _goal_marker(self):
        return self.task.end

    def close(self):
        if self._mask_renderer is not None:
            self._mask_renderer.close()
            self._mask_renderer = None
        super().close()

    # --- internals -----------------------------------------------------------------------------------
    def _step_result(self):
        # as the other sims, and a collision ends the episode as a failure
        obs, reward, terminated, truncated, info = super()._step_result()
        if info["collision"]:
            terminated, truncated = True, False
        return obs, reward, terminated, truncated, info

    def _obs(self) -> dict:
        return {**super()._obs(), "pixels": {"top": self._mask.copy()}}

    def _update_progress(self):
        super()._update_progress()
        clearance = float(distance_to_obstacles(self.task, self.data.qpos[:2])) - AGENT_RADIUS
        self._min_clearance = min(self._min_clearance, clearance)

    def _info(self) -> dict:
        end_error = self._distance_to(self.task.end)
        if self._end_condition is not None:
            right_side = self._distance_to(self._end_condition.values) <= SUCCESS_TOL
        else:
            right_side = float(self.data.qpos[0]) >= RIGHT_SIDE_X
        at_rest = float(np.linalg.norm(self.data.qvel[:2])) <= REST_SPEED
        n_passed = self._conditions_passed()
        errors = np.full(MAX_CONDITIONS, np.nan)
        errors[: len(self.conditions)] = self._cond_min_err
        success = not self._contact and n_passed == len(self.conditions) and right_side and at_rest
        return {
            "is_success": bool(success),
            "collision": bool(self._contact),
            "conditions_passed": n_passed,
            "condition_errors": errors,  # closest approach to each condition so far (nan: no condition)
            "end_error": end_error,  # distance to the room's end (a condition or not)
            "right_side": bool(right_side),
            "at_rest": bool(at_rest),
            "min_clearance": float(self._min_clearance),  # least gap agent surface <-> obstacle/wall so far
        }

    def _render_mask(self) -> np.ndarray:
        """Render walls and obstacles white (nothing else) from the ``top`` camera, threshold to 0/255."""
        if self._mask_renderer is None:
            # one sample per pixel (no multisampling): a pixel is white iff its centre lies on an obstacle
            samples = self.model.vis.quality.offsamples
            self.model.vis.quality.offsamples = 0
            try:
                self._mask_renderer = mujoco.Renderer(self.model, self.image_size, self.image_size)
            finally:
                self.model.vis.quality.offsamples = samples
            for flag in (mujoco.mjtRndFlag.mjRND_SHADOW, mujoco.mjtRndFlag.mjRND_REFLECTION,
                         mujoco.mjtRndFlag.mjRND_SKYBOX):
                self._mask_renderer.scene.flags[flag] = 0
        rgba = self.model.geom_rgba[self._mask_gids].copy()
        self.model.geom_rgba[self._mask_gids] = 1.0
        try:
            self._mask_renderer.update_scene(self.data, camera="top", scene_option=self._mask_option)
            img = self._mask_renderer.render()
        finally:
            self.model.geom_rgba[self._mask_gids] = rgba
        mask = np.where(img.max(axis=-1) > 127, 255, 0).astype(np.uint8)
        return np.repeat(mask[..., None], 3, axis=-1)

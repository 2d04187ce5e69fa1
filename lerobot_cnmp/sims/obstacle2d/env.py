"""MuJoCo 2D obstacle-avoidance sim (CNMP paper, Sec. IV-A).

A point mass moves in the plane, position-controlled in x and y, around a round obstacle centred at
(0.5, 0). Demonstrations pass either over (``mode=+1``) or under (``mode=-1``) the obstacle, which is the
multi-modal task family of Seker et al. (RSS 2019, Fig. 4)::

    x(tau) = tau,    y(tau) = y0 + (h - y0) * sin(pi * tau) ** p,    tau in [0, 1]

with ``y0 in s*[0.1, 0.3]``, ``h in s*[0.45, 0.65]``, ``p in [0.9, 1.6]`` for mode ``s``. Each episode draws
a hidden reference trajectory of the family (its start is the reset state, its end the goal) and a set of
conditions taken from it; the conditions are the only task information in the observation
(``environment_state``, encoded with :func:`lerobot_cnmp.execution.conditions.encode_conditions`).

Task families (``family``): ``mirrored`` (the above; the modes start and end at mirrored heights, so a start or
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

from dataclasses import dataclass  # noqa: E402

import mujoco  # noqa: E402
import numpy as np  # noqa: E402
from gymnasium import spaces  # noqa: E402

from lerobot_cnmp.sims.base import MujocoSimEnv, contacts_with  # noqa: E402

from lerobot_cnmp.execution.conditions import Condition, encode_conditions  # noqa: E402

# --- constants of the sim ------------------------------------------------------------------------------
SM_DIM = 2
MAX_CONDITIONS = 4
ENV_STATE_DIM = MAX_CONDITIONS * (2 + 2 * SM_DIM)  # 24
OBSTACLE_CENTER = np.array([0.5, 0.0])
OBSTACLE_RADIUS = 0.2
AGENT_RADIUS = 0.03
SUCCESS_TOL = 0.05
N_SUBSTEPS = 10  # physics steps (dt = 0.002) per control step -> 50 Hz control
CONTROL_FPS = 50
ACTION_LOW = np.array([-0.3, -0.8], dtype=np.float32)
ACTION_HIGH = np.array([1.3, 0.8], dtype=np.float32)
DEFAULT_MAX_EPISODE_STEPS = 300
PUSH_DISTANCE = 0.12
PUSH_MIN_CLEARANCE = 0.02  # a push toward the obstacle stops this far from it
HOLD_STEPS = 30
PERTURB_STEP_RANGE = (50, 120)  # inclusive
RATE_LIMIT = 0.08  # m/s, the rate_limited actuator's top speed (the demos move at up to ~0.5 m/s)

# Task family bounds (for mode +1; mode -1 mirrors y0 and h).
Y0_RANGE = (0.1, 0.3)
SHARED_Y0_RANGE = (-0.1, 0.1)  # family 'shared': the start height of both modes
H_RANGE = (0.45, 0.65)
P_RANGE = (0.9, 1.6)

CONDITION_CHOICES = ("mixed", "paper_via", "paper_early", "paper_end", "random", "start_goal", "start_goal_early")
PAPER_CONDITION_CHOICES = ("mixed", "paper_via", "paper_early", "paper_end")  # the mirrored family only
PERTURBATION_CHOICES = ("none", "push", "push_toward", "push_random", "hold")
FAMILY_CHOICES = ("mirrored", "shared")
ACTUATOR_CHOICES = ("servo", "rate_limited")
RANDOM_VARIANTS = ("via", "early", "end", "via+end", "via_y")  # condition sets of ``random``
MODE_NAMES = {1: "over", -1: "under"}

_KP = 2500.0
_KV = 2.0 * np.sqrt(_KP * 1.0)  # critical damping for mass 1

MJCF = f"""
<mujoco model="cnmp_obstacle2d">
  <option timestep="0.002" gravity="0 0 0" integrator="implicitfast"/>
  <visual>
    <global offwidth="1024" offheight="1024"/>
    <headlight ambient="0.5 0.5 0.5" diffuse="0.5 0.5 0.5"/>
  </visual>
  <asset>
    <texture name="grid" type="2d" builtin="checker" rgb1="0.92 0.92 0.92" rgb2="0.85 0.85 0.85"
             width="256" height="256"/>
    <material name="grid" texture="grid" texrepeat="8 8"/>
  </asset>
  <worldbody>
    <camera name="top" pos="0.5 0 2.0" xyaxes="1 0 0 0 1 0" fovy="45"/>
    <geom name="floor" type="plane" pos="0.5 0 -0.06" size="1.5 1.5 0.01" material="grid"
          contype="0" conaffinity="0"/>
    <geom name="obstacle" type="cylinder" pos="{OBSTACLE_CENTER[0]} {OBSTACLE_CENTER[1]} 0"
          size="{OBSTACLE_RADIUS} 0.05" rgba="0.8 0.25 0.2 1" contype="1" conaffinity="1"/>
    <body name="agent" pos="0 0 0">
      <joint name="x" type="slide" axis="1 0 0"/>
      <joint name="y" type="slide" axis="0 1 0"/>
      <geom name="agent" type="sphere" size="{AGENT_RADIUS}" mass="1" rgba="0.15 0.35 0.9 1"
            contype="1" conaffinity="1"/>
    </body>
    <site name="goal" type="sphere" pos="1 0 0.06" size="0.035" rgba="0.1 0.75 0.2 0.7"/>
    <site name="cond0" type="box" pos="0 0 0.07" size="0.025 0.025 0.002" rgba="0 0 0 0"/>
    <site name="cond1" type="box" pos="0 0 0.07" size="0.025 0.025 0.002" rgba="0 0 0 0"/>
    <site name="cond2" type="box" pos="0 0 0.07" size="0.025 0.025 0.002" rgba="0 0 0 0"/>
    <site name="cond3" type="box" pos="0 0 0.07" size="0.025 0.025 0.002" rgba="0 0 0 0"/>
  </worldbody>
  <actuator>
    <position name="ax" joint="x" kp="{_KP}" kv="{_KV}" ctrllimited="true"
              ctrlrange="{ACTION_LOW[0]} {ACTION_HIGH[0]}"/>
    <position name="ay" joint="y" kp="{_KP}" kv="{_KV}" ctrllimited="true"
              ctrlrange="{ACTION_LOW[1]} {ACTION_HIGH[1]}"/>
  </actuator>
</mujoco>
"""


@dataclass(frozen=True)
class Obstacle2DTask:
    """One member of the task family: the hidden reference trajectory of an episode."""

    mode: int  # +1 over the obstacle, -1 under
    y0: float
    h: float
    p: float

    def position(self, tau):
        """Reference position at phase ``tau`` (scalar or array, clipped to [0, 1]) -> ``[..., 2]``."""
        tau = np.clip(np.asarray(tau, dtype=np.float64), 0.0, 1.0)
        y = self.y0 + (self.h - self.y0) * np.sin(np.pi * tau) ** self.p
        return np.stack([tau, y], axis=-1)

    @property
    def start(self) -> np.ndarray:
        return np.array([0.0, self.y0])

    @property
    def goal(self) -> np.ndarray:
        return np.array([1.0, self.y0])

    @property
    def mode_name(self) -> str:
        return MODE_NAMES[self.mode]

    @classmethod
    def sample(cls, rng: np.random.Generator, mode: int | None = None, family: str = "mirrored") -> Obstacle2DTask:
        if family not in FAMILY_CHOICES:
            raise ValueError(f"unknown family {family!r}; choose one of {list(FAMILY_CHOICES)}")
        if mode is None:
            mode = int(rng.choice([1, -1]))
        y0 = rng.uniform(*Y0_RANGE)
        h = rng.uniform(*H_RANGE)
        p = rng.uniform(*P_RANGE)
        if family == "shared":  # the same start (and goal) height range for both modes
            return cls(mode=mode, y0=float(SHARED_Y0_RANGE[0] + (SHARED_Y0_RANGE[1] - SHARED_Y0_RANGE[0])
                                           * (y0 - Y0_RANGE[0]) / (Y0_RANGE[1] - Y0_RANGE[0])),
                       h=float(mode * h), p=float(p))
        return cls(mode=mode, y0=float(mode * y0), h=float(mode * h), p=float(p))


def _check_mode(mode) -> int | None:
    if mode is None:
        return None
    if mode in ("over", "under"):
        return 1 if mode == "over" else -1
    if mode not in (1, -1):
        raise ValueError(f"mode must be +1 ('over'), -1 ('under') or None, got {mode!r}")
    return int(mode)


def _check_family(family: str, conditions: str) -> None:
    if family not in FAMILY_CHOICES:
        raise ValueError(f"unknown family {family!r}; choose one of {list(FAMILY_CHOICES)}")
    if family == "shared" and conditions in PAPER_CONDITION_CHOICES:
        raise ValueError(f"conditions {conditions!r} are the paper's sets of the 'mirrored' family; with family "
                         f"'shared' choose one of {[c for c in CONDITION_CHOICES if c not in PAPER_CONDITION_CHOICES]}")


PAPER_CONDITIONS: dict[str, list[Condition]] = {
    # Sec. IV-A / Fig. 4: a via-point that selects the mode, an early point, an end point.
    "paper_via": [Condition(0.5, (0.5, 0.55))],
    "paper_early": [Condition(0.2, (0.2, -0.37))],
    "paper_end": [Condition(1.0, (1.0, 0.13))],
}


def _point(task: Obstacle2DTask, t: float, dims=None) -> Condition:
    xy = task.position(t)
    return Condition(float(t), (float(xy[0]), float(xy[1])), dims)


def sample_episode(
    rng: np.random.Generator, conditions: str, mode: int | None = None, family: str = "mirrored"
) -> tuple[Obstacle2DTask, list[Condition], str]:
    """Draw ``(task, conditions, kind)`` for one episode.

    ``kind`` names the concrete condition set: ``paper_via``, ``paper_early``, ``paper_end`` or
    ``random/<variant>`` with variant in :data:`RANDOM_VARIANTS`. ``mode`` (+1 / -1) forces the avoidance
    mode (for ``mixed``, only the compatible condition sets are drawn). ``start_goal``: the start (phase 0)
    and the goal (phase 1); ``start_goal_early``: those and the reference point at a phase drawn in
    [0.15, 0.3], which names the mode in either family. ``family``: see :class:`Obstacle2DEnv`; the
    paper's condition sets (and ``mixed``) exist for the ``mirrored`` family only.
    """
    if conditions not in CONDITION_CHOICES:
        raise ValueError(f"unknown conditions {conditions!r}; choose one of {list(CONDITION_CHOICES)}")
    _check_family(family, conditions)
    mode = _check_mode(mode)
    if conditions in ("start_goal", "start_goal_early"):
        task = Obstacle2DTask.sample(rng, mode, family)
        conds = [_point(task, 0.0), _point(task, 1.0)]
        if conditions == "start_goal_early":
            conds.append(_point(task, rng.uniform(0.15, 0.3)))
        return task, conds, conditions
    kind = conditions
    if kind == "mixed":
        kinds = ["paper_via", "paper_early", "paper_end", "random"]
        if mode is not None:  # keep only the kinds compatible with the requested mode
            kinds = [k for k in kinds if k == "random" or (k == "paper_early") == (mode == -1)]
        kind = str(kinds[int(rng.integers(len(kinds)))])
    fixed_mode = {"paper_via": 1, "paper_end": 1, "paper_early": -1}.get(kind)
    if fixed_mode is not None and mode is not None and mode != fixed_mode:
        raise ValueError(f"conditions {kind!r} are only defined for mode {fixed_mode:+d}, got mode {mode:+d}")

    if kind == "paper_via":
        base = Obstacle2DTask.sample(rng, 1)
        task = Obstacle2DTask(1, base.y0, PAPER_CONDITIONS[kind][0].values[1], base.p)
        return task, PAPER_CONDITIONS[kind], kind
    if kind == "paper_end":
        base = Obstacle2DTask.sample(rng, 1)
        task = Obstacle2DTask(1, 0.13, base.h, base.p)
        return task, PAPER_CONDITIONS[kind], kind
    if kind == "paper_early":
        s = np.sin(np.pi * 0.2)
        for _ in range(100_000):
            base = Obstacle2DTask.sample(rng, -1)
            r = (-0.37 - base.y0) / (base.h - base.y0)
            if not 0.0 < r < 1.0:
                continue
            p = float(np.log(r) / np.log(s))
            if P_RANGE[0] <= p <= P_RANGE[1]:
                task = Obstacle2DTask(-1, base.y0, base.h, p)
                return task, PAPER_CONDITIONS[kind], kind
        raise RuntimeError("could not sample a task through the paper_early condition")  # pragma: no cover
    # random
    task = Obstacle2DTask.sample(rng, mode, family)
    variant = RANDOM_VARIANTS[int(rng.integers(len(RANDOM_VARIANTS)))]
    if variant == "via":
        conds = [_point(task, rng.uniform(0.35, 0.65))]
    elif variant == "early":
        conds = [_point(task, rng.uniform(0.1, 0.3))]
    elif variant == "end":
        conds = [_point(task, 1.0)]
    elif variant == "via+end":
        conds = [_point(task, rng.uniform(0.35, 0.65)), _point(task, 1.0)]
    else:  # via_y: a via point constraining y only
        conds = [_point(task, rng.uniform(0.4, 0.6), dims=(1,))]
    kind = f"random/{variant}"
    return task, conds, kind


class Obstacle2DEnv(MujocoSimEnv):
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
        _check_family(family, conditions)
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

        self.model = mujoco.MjModel.from_xml_string(MJCF)
        self.data = mujoco.MjData(self.model)
        self._obstacle_gid = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_GEOM, "obstacle")
        self._agent_gid = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_GEOM, "agent")
        self._goal_sid = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_SITE, "goal")
        self._cond_sids = [
            mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_SITE, f"cond{k}") for k in range(MAX_CONDITIONS)
        ]

        self.observation_space = spaces.Dict(
            {
                "agent_pos": spaces.Box(-np.inf, np.inf, shape=(2,), dtype=np.float32),
                "environment_state": spaces.Box(-np.inf, np.inf, shape=(ENV_STATE_DIM,), dtype=np.float32),
            }
        )
        self.action_space = spaces.Box(ACTION_LOW, ACTION_HIGH, dtype=np.float32)

        self.task: Obstacle2DTask | None = None
        self.conditions: list[Condition] = []
        self.condition_kind: str = ""
        self._env_state = np.zeros(ENV_STATE_DIM, dtype=np.float32)

    # --- public helpers ------------------------------------------------------------------------------
    @property
    def task_description(self) -> str:
        return "reach the goal around the obstacle"

    @property
    def goal(self) -> np.ndarray:
        return self.task.goal

    @property
    def agent_pos(self) -> np.ndarray:
        return self.data.qpos[:2].copy()

    # --- gym API -------------------------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        options = dict(options or {})
        # Keys LeRobot's rollout adds itself (e.g. "lerobot_new_rollout") are not ours to check.
        unknown = {k for k in options if not str(k).startswith("lerobot_")} - {"mode", "task", "conditions"}
        if unknown:
            raise ValueError(f"unknown reset options {sorted(unknown)}; known: ['conditions', 'mode', 'task']")
        if "task" in options:
            task = options["task"]
            if not isinstance(task, Obstacle2DTask):
                raise ValueError(f"options['task'] must be an Obstacle2DTask, got {type(task).__name__}")
            conds = list(options.get("conditions", []))
            kind = "custom"
        else:
            if "conditions" in options:
                raise ValueError("options['conditions'] needs options['task'] too")
            task, conds, kind = sample_episode(self.np_random, self.conditions_mode, options.get("mode"), self.family)
        self.task, self.conditions, self.condition_kind = task, conds, kind
        self._env_state = encode_conditions(conds, sm_dim=SM_DIM, max_conditions=MAX_CONDITIONS)

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

        mujoco.mj_resetData(self.model, self.data)
        self.data.qpos[:2] = task.start
        self.data.qvel[:] = 0.0
        self.data.ctrl[:] = task.start
        self._setpoint = np.array(task.start, dtype=np.float64)  # the rate_limited actuator's set point
        self._set_markers()
        mujoco.mj_forward(self.model, self.data)  # after the markers: rendering reads the computed site poses
        self._step = 0
        self._contact = False
        self._cond_min_err = np.full(len(conds), np.inf)
        self._update_progress()
        return self._obs(), self._info()

    def step(self, action):
        if self.task is None:
            raise RuntimeError("call reset() before step()")
        action = np.clip(np.asarray(action, dtype=np.float64).reshape(2), ACTION_LOW, ACTION_HIGH)
        if self._hold_left > 0:
            self._hold_left -= 1
            self.data.qpos[:2] = self._hold_pos
            self.data.qvel[:] = 0.0
            self.data.ctrl[:] = self._hold_pos
            self._setpoint = self._hold_pos.copy()
            self.data.time += N_SUBSTEPS * self.model.opt.timestep
            mujoco.mj_forward(self.model, self.data)
        else:
            if self.actuator == "rate_limited":
                delta = action - self._setpoint
                most = self.rate_limit * N_SUBSTEPS * self.model.opt.timestep
                dist = float(np.linalg.norm(delta))
                self._setpoint = self._setpoint + (delta if dist <= most else delta * (most / dist))
                action = self._setpoint
            self.data.ctrl[:] = action
            for _ in range(N_SUBSTEPS):
                mujoco.mj_step(self.model, self.data)
                if not self._contact and self._in_contact():
                    self._contact = True
        self._step += 1
        if self._step == self._perturb_step:  # push: displaced now; hold: held for the next HOLD_STEPS
            self._start_perturbation()
        self._update_progress()
        return self._step_result()

    # --- internals -----------------------------------------------------------------------------------
    def _obs(self) -> dict:
        return {"agent_pos": self.data.qpos[:2].astype(np.float32), "environment_state": self._env_state.copy()}

    def _in_contact(self) -> bool:
        return self._obstacle_gid in contacts_with(self.data, self._agent_gid)

    def _update_progress(self):
        pos = self.data.qpos[:2]
        for k, c in enumerate(self.conditions):
            dims = list(range(SM_DIM)) if c.dims is None else list(c.dims)
            err = float(np.linalg.norm(pos[dims] - np.asarray(c.values)[dims]))
            self._cond_min_err[k] = min(self._cond_min_err[k], err)

    def _info(self) -> dict:
        goal_error = float(np.linalg.norm(self.data.qpos[:2] - self.task.goal))
        n_passed = int(np.sum(self._cond_min_err <= SUCCESS_TOL))
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

    def _set_markers(self):
        m = self.model
        m.site_pos[self._goal_sid, :2] = self.task.goal
        for k, sid in enumerate(self._cond_sids):
            if k < len(self.conditions):
                c = self.conditions[k]
                if c.dims is None or len(c.dims) == SM_DIM:
                    m.site_pos[sid, :2] = c.values
                    m.site_size[sid] = [0.025, 0.025, 0.002]
                else:  # y-only condition: a horizontal bar at that height
                    m.site_pos[sid, :2] = [0.5 if 0 not in c.dims else c.values[0], c.values[1]]
                    m.site_size[sid] = [0.6, 0.006, 0.002] if 0 not in c.dims else [0.006, 0.6, 0.002]
                m.site_rgba[sid] = [0.05, 0.05, 0.05, 0.9]
            else:
                m.site_rgba[sid] = [0, 0, 0, 0]

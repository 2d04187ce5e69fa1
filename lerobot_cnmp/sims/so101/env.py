"""The third-party SO-101 pick-and-place sim (``lerobot-env-so101==0.4.0``) as a CNMP sim:
``--env.type=cnmp_so101``, gymnasium id ``cnmp/SO101PickPlace-v0``.

A thin wrapper: the physics, the IK, the task, its randomization and its success rule are the plugin's
``SO101PickPlaceGymEnv`` (gym id ``lerobot_env_so101/SO101PickPlace-v0``), built here with the plugin's own
class. What this module adds:

- :class:`~lerobot_cnmp.sims.so101.config.CNMPSO101Env` (in ``config.py``), an ``EnvConfig`` with the features
  the PickPlace task really has. The plugin's own
  ``--env.type=so101`` config is the pick-only task's: it declares a 3-value ``environment_state`` (PickPlace
  gives 6: block and goal), defaults to ``random_block_position=False`` and to ``action_scale=1.0`` (1 m per
  unit action, while its scripted controllers are calibrated for 0.025).
- :class:`SO101Wrapper`, which reports the plugin's success flag ``info["succeed"]`` as LeRobot's
  ``info["is_success"]`` (stock ``lerobot-eval`` reads only the latter and would count 0 %), can keep an
  episode running past success (``terminate_on_success=False``, for recording fixed-length demos; the
  plugin always terminates on success), names the task (``task`` / ``task_description``, which
  ``lerobot-eval`` looks up in every sub-env) and can observe cameras of the plugin's model (``cameras``,
  :class:`~lerobot_cnmp.sims.cameras.FastRenderer`): then ``environment_state`` (block and goal) leaves the
  observation, as a real SO-101 dataset has none, and goes to ``info["task_params"]`` (block start and goal,
  every reset and step) for the recorder's ground truth.

The plugin (an optional extra: ``pip install -e ".[so101]"``) is imported only when an env is built, so
importing this module, and ``lerobot_cnmp.sims``, works without it.

Facts of the plugin's PickPlace task (read from its source, v0.4.0):

- control: 10 Hz (``control_dt`` 0.1 s = 50 MuJoCo steps of 2 ms); the registered episode is 300 steps.
- action ``[dx, dy, dz, grasp]`` in [-1, 1]^3 x [0, 1]: ``dx, dy, dz`` move the IK target of the grasp
  point between the jaws (``env.ik_point_pos``) by ``action_scale`` metres per unit (target clipped to the
  box x in [0.1, 0.5], y in [-0.3, 0.3], z in [0, 0.4] m); the IK keeps the gripper pointing straight down.
  An all-zero delta holds the current pose. ``grasp`` is an absolute jaw command, 0 closed, 1 open.
- ``agent_pos`` (14, float32): the 5 arm joint angles (rad) ``shoulder_pan, shoulder_lift, elbow_flex,
  wrist_flex, wrist_roll``, their velocities (rad/s), ``gripper_pose`` (the gripper *command* mapped to
  [-1, 1]: -1 closed, +1 open, not the measured jaw) and the position (m) of the ``gripperframe`` site on the
  fixed jaw (not the grasp point the action moves).
- ``environment_state`` (6, float32): the block centre (m) and the goal, where the block centre should rest
  (its z is the block's half size, 0.02 m). World frame: the arm's base at the origin, x forward, z up.
- reset: with ``random_block_position`` the block (x, y) and the goal (x, y) are drawn uniformly from
  x in [0.15, 0.30] m, y in [-0.10, 0.10] m by the env's ``np_random`` (seeded by ``reset(seed=...)``), the
  goal redrawn until it is at least 8 cm from the block; without it, block (0.25, 0) and goal (0.20, 0.08).
- success (``info["succeed"]``, every step): the block was lifted more than 3 cm above its start at some
  point of the episode, its centre is within 3 cm (in x, y) of the goal, the jaw (measured) is more than
  half open and the block moves slower than 1 cm/s. The episode terminates on success or when the block
  leaves x in [0.08, 0.40], y in [-0.20, 0.20] m; reward 1 on success, else 0.
- rendering: the ``front`` camera; the SO-101 meshes have 322k faces and the scene casts shadows, so with
  software EGL (no GPU) a 128 x 128 frame takes about 0.6 to 0.9 s; the wrapper renders with shadows,
  reflections and the skybox off (~0.1 s). Pixels are off unless asked
  (``cameras``); ``render()`` builds its renderer on first use only.
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402
from gymnasium import spaces  # noqa: E402

from lerobot_cnmp.sims.cameras import FastRenderer, FreeView, Marker, check_cameras  # noqa: E402
from lerobot_cnmp.sims.so101.task import (  # noqa: E402
    DEFAULT_ACTION_SCALE,
    DEFAULT_RENDER_SIZE,
    FREE_VIEWS,
    GOAL_MARK_RADIUS,
    GOAL_MARK_RGBA,
    TASK_DESCRIPTION,
    require_plugin,
)


class SO101Wrapper(gym.Wrapper):
    """The plugin's PickPlace env with LeRobot's success key, optional termination on success, the task's
    name, and optionally cameras instead of the block and goal positions.

    Every step's info gets ``is_success`` = the plugin's ``succeed`` (which is kept). With
    ``terminate_on_success=False`` a successful step is not terminal (the plugin's ``terminated`` on success
    is cleared; a success implies the block lies within 3 cm of a goal inside [0.15, 0.30] x [-0.1, 0.1] m,
    so it is never also out of the workspace, the plugin's other reason to terminate). With ``cameras`` (the
    plugin model's ``front`` and our ``table`` view, ``FREE_VIEWS``; the goal drawn as a disc) the observation holds ``agent_pos`` and ``pixels[<name>]`` (uint8,
    ``camera_size`` square) and no ``environment_state``; every info holds ``task_params``, the episode's
    first ``environment_state`` (block start and goal), cameras or not.
    """

    def __init__(self, env: gym.Env, terminate_on_success: bool = True,
                 cameras: list[str] | tuple[str, ...] = (), camera_size: int = DEFAULT_RENDER_SIZE):
        super().__init__(env)
        self.terminate_on_success = bool(terminate_on_success)
        model = env.unwrapped.model
        model_cameras = [model.camera(i).name for i in range(model.ncam)]
        self.cameras = check_cameras(cameras, camera_size, model_cameras + list(FREE_VIEWS))
        self._views = {c: c if c in model_cameras else FreeView(**FREE_VIEWS[c]) for c in self.cameras}
        self.camera_size = int(camera_size)
        self._cameras = FastRenderer(model, self.camera_size) if self.cameras else None
        self.task_params = np.zeros(env.observation_space["environment_state"].shape, dtype=np.float32)
        if self.cameras:
            space = {k: v for k, v in env.observation_space.spaces.items() if k != "environment_state"}
            space["pixels"] = spaces.Dict(
                {c: spaces.Box(0, 255, (self.camera_size, self.camera_size, 3), dtype=np.uint8) for c in self.cameras}
            )
            self.observation_space = spaces.Dict(space)

    @property
    def task_description(self) -> str:
        return TASK_DESCRIPTION

    @property
    def task(self) -> str:
        """LeRobot's rollout looks this attribute up in every sub-env (async vector envs fail without it)."""
        return TASK_DESCRIPTION

    def _frame(self) -> np.ndarray:
        """The plugin's front-camera render, with shadows, reflections and the skybox off: its 322k-face
        meshes take ~0.6 s per 128 x 128 frame with them under software EGL (no GPU), ~0.1 s without, and
        ``lerobot-eval`` renders every step of its first 10 episodes for the videos."""
        import mujoco

        base = self.env.unwrapped
        frame = base.render()
        viewer = getattr(base, "_viewer", None)
        if viewer is not None and not getattr(self, "_fast_scene", False):
            for flag in (mujoco.mjtRndFlag.mjRND_SHADOW, mujoco.mjtRndFlag.mjRND_REFLECTION,
                         mujoco.mjtRndFlag.mjRND_SKYBOX):
                viewer.scene.flags[flag] = 0
            self._fast_scene = True
            frame = base.render()
        return np.asarray(frame, dtype=np.uint8).copy()

    def _obs(self, obs: dict) -> dict:
        if self.cameras:
            obs = {k: v for k, v in obs.items() if k != "environment_state"}
            base = self.env.unwrapped
            goal = Marker((float(base.goal_pos[0]), float(base.goal_pos[1]), 5e-4), GOAL_MARK_RADIUS, GOAL_MARK_RGBA)
            obs["pixels"] = {c: self._cameras(base.data, self._views[c], (goal,)) for c in self.cameras}
        return obs

    def reset(self, *, seed=None, options=None):
        obs, info = self.env.reset(seed=seed, options=options)
        self.task_params = np.asarray(obs["environment_state"], dtype=np.float32).copy()
        return self._obs(obs), {**info, "is_success": False, "task_params": self.task_params.copy()}

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(np.asarray(action, dtype=np.float64))
        success = bool(info.get("succeed", False))
        if success and not self.terminate_on_success:
            terminated = False
        info = {**info, "is_success": success, "task_params": self.task_params.copy()}
        return self._obs(obs), reward, bool(terminated), bool(truncated), info

    def render(self):
        if self.env.unwrapped.render_mode != "rgb_array":
            return None
        return self._frame()

    def close(self):
        if self._cameras is not None:
            self._cameras.close()
        super().close()


def make_so101_pickplace(
    random_block_position: bool = True,
    action_scale: float = DEFAULT_ACTION_SCALE,
    cameras: list[str] | tuple[str, ...] = (),
    camera_size: int = DEFAULT_RENDER_SIZE,
    render_mode: str | None = "rgb_array",
    render_size: int = DEFAULT_RENDER_SIZE,
    terminate_on_success: bool = True,
) -> gym.Env:
    """The entry point of ``cnmp/SO101PickPlace-v0``: the plugin's ``SO101PickPlaceGymEnv`` (state
    observation; top-down IK and jaw pads on, as its own ``SO101PickPlace-v0``) in :class:`SO101Wrapper`.
    ``gym.make`` adds the time limit (300 steps unless ``max_episode_steps`` is given)."""
    pick_place_env = require_plugin()
    from lerobot_env_so101.mujoco_env import GymRenderingSpec

    env = pick_place_env.SO101PickPlaceGymEnv(
        render_spec=GymRenderingSpec(height=int(render_size), width=int(render_size)),
        render_mode=render_mode,
        image_obs=False,  # the plugin's own image option (its render()); the wrapper renders the cameras
        random_block_position=bool(random_block_position),
        action_scale=float(action_scale),
    )
    return SO101Wrapper(env, terminate_on_success=terminate_on_success, cameras=cameras, camera_size=camera_size)

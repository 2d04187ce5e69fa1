"""A thin env over MetaWorld's own task objects (metaworld 3.0.0): any v3 task, hand state and γ in the observation.

The physics, the task, its randomization and its success rule are MetaWorld's (``metaworld.MT1(task)``'s
env class, its ``info["success"]``); this wrapper only

* draws a fresh object / goal placement at every ``reset(seed=...)`` (MetaWorld's own ``_get_state_rand_vec``,
  seeded through its ``seed()``; the placement is not frozen to one of MT1's 50 stored tasks),
* exposes ``agent_pos`` = the hand position (x, y, z, m) and the gripper opening (MetaWorld's observation
  entries 0-3), and ``environment_state`` = γ = the first frame's main-object position (3) and goal position (3)
  (entries 4-6 and 36-38), constant within an episode,
* reports ``info["is_success"]`` = MetaWorld's ``info["success"]``, with optional termination on success,
* with ``cameras`` (names of the MetaWorld model's cameras, e.g. ``corner3``, ``gripperPOV``), observes each as
  ``pixels[<name>]`` (uint8, ``camera_size`` square, :class:`~lerobot_cnmp.sims.cameras.FastRenderer`) and
  drops ``environment_state``: the policy sees the hand state and the images only; γ stays in
  ``info["task_params"]`` (every reset and step, cameras or not) for the recorder's ground truth.

Actions are MetaWorld's: (dx, dy, dz, gripper) in [-1, 1]. Its scripted experts (``metaworld.policies``)
drive the recorder through :class:`lerobot_cnmp.sims.metaworld.expert.MetaWorldExpert`. Nothing is rendered
unless ``render_mode="rgb_array"`` (MetaWorld's offscreen renderer, slow on CPU).
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402
from gymnasium import spaces  # noqa: E402

from lerobot_cnmp.sims.cameras import FastRenderer, check_cameras  # noqa: E402
from lerobot_cnmp.sims.metaworld.task import (  # noqa: E402
    CONTROL_FPS,
    DEFAULT_TASK,
    GAMMA_DIM,
    STATE_DIM,
    import_metaworld,
    check_task,
)


class MetaWorldEnv(gym.Env):
    """One MetaWorld v3 task; see the module docstring.

    Args:
        task: a MetaWorld v3 task name (``metaworld.ALL_V3_ENVIRONMENTS``), e.g. ``reach-v3``, ``push-v3``.
        render_mode: ``"rgb_array"`` or None.
        render_size: side of the rendered square image, pixels.
        terminate_on_success: end the episode as soon as MetaWorld reports success.
        max_episode_steps: if given, the env truncates itself at this many steps (at most MetaWorld's 500).
        cameras: MetaWorld camera names observed as ``pixels[<name>]``; non-empty drops ``environment_state``.
        camera_size: side of each camera image, pixels.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": CONTROL_FPS}

    def __init__(self, task: str = DEFAULT_TASK, render_mode: str | None = None, render_size: int = 128,
                 terminate_on_success: bool = True, max_episode_steps: int | None = None,
                 cameras: list[str] | tuple[str, ...] = (), camera_size: int = 128):
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"unknown render_mode {render_mode!r}; choose 'rgb_array' or None")
        metaworld = import_metaworld()
        self.task_name = check_task(task)
        mt = metaworld.MT1(self.task_name, seed=0)
        self._mw = mt.train_classes[self.task_name](render_mode=render_mode, width=render_size, height=render_size)
        self._mw.set_task(mt.train_tasks[0])
        self._mw._freeze_rand_vec = False  # a new placement at each reset, from MetaWorld's own random vector
        self._mw.seeded_rand_vec = True  # drawn from its np_random, which reset(seed=...) seeds through seed()
        if max_episode_steps is not None and not 1 <= int(max_episode_steps) <= self._mw.max_path_length:
            raise ValueError(f"max_episode_steps must be in [1, {self._mw.max_path_length}] (MetaWorld's path "
                             f"length), got {max_episode_steps}")
        self._max_episode_steps = int(max_episode_steps or self._mw.max_path_length)
        self.render_mode = render_mode
        self.terminate_on_success = bool(terminate_on_success)
        model = self._mw.model
        self.cameras = check_cameras(cameras, camera_size, [model.camera(i).name for i in range(model.ncam)])
        self.camera_size = int(camera_size)
        self._cameras = FastRenderer(model, self.camera_size) if self.cameras else None
        space = {"agent_pos": spaces.Box(-np.inf, np.inf, shape=(STATE_DIM,), dtype=np.float32)}
        if self.cameras:
            space["pixels"] = spaces.Dict({c: spaces.Box(0, 255, (self.camera_size, self.camera_size, 3), np.uint8)
                                           for c in self.cameras})
        else:
            space["environment_state"] = spaces.Box(-np.inf, np.inf, shape=(GAMMA_DIM,), dtype=np.float32)
        self.observation_space = spaces.Dict(space)
        self.action_space = spaces.Box(-1.0, 1.0, shape=(4,), dtype=np.float32)
        self.raw_obs: np.ndarray | None = None  # MetaWorld's own 39-dim observation (what its experts read)
        self.gamma = np.zeros(GAMMA_DIM, dtype=np.float32)
        self._step = 0

    @property
    def task_description(self) -> str:
        return self.task_name

    @property
    def task(self) -> str:
        """The task name (LeRobot's rollout reads ``task`` or ``task_description`` of each env)."""
        return self.task_name

    def _obs(self) -> dict:
        obs = {"agent_pos": self.raw_obs[:STATE_DIM].astype(np.float32)}
        if self.cameras:
            obs["pixels"] = {c: self._cameras(self._mw.data, c) for c in self.cameras}
        else:
            obs["environment_state"] = self.gamma.copy()
        return obs

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        unknown = {k for k in (options or {}) if not str(k).startswith("lerobot_")}
        if unknown:
            raise ValueError(f"unknown reset options {sorted(unknown)}; this env takes none")
        if seed is not None:
            self._mw.seed(int(seed))
        self.raw_obs, _ = self._mw.reset()
        if self.cameras:  # MetaWorld places its goal marker after each step, not at reset: place it for frame 0
            for site in self._mw._target_site_config:
                self._mw._set_pos_site(*site)
        self.gamma = np.concatenate([self.raw_obs[4:7], self.raw_obs[36:39]]).astype(np.float32)
        self._step = 0
        return self._obs(), {"is_success": False, "task_params": self.gamma.copy()}

    def step(self, action):
        if self.raw_obs is None:
            raise RuntimeError("call reset() before step()")
        action = np.clip(np.asarray(action, dtype=np.float64).reshape(4), -1.0, 1.0)
        self.raw_obs, reward, _, mw_truncated, info = self._mw.step(action)
        self._step += 1
        success = bool(info.get("success", False))
        info = {**info, "is_success": success, "task_params": self.gamma.copy()}
        terminated = success and self.terminate_on_success
        truncated = bool((mw_truncated or self._step >= self._max_episode_steps) and not terminated)
        return self._obs(), float(reward), terminated, truncated, info

    def render(self):
        return self._mw.render() if self.render_mode == "rgb_array" else None

    def close(self):
        if self._cameras is not None:
            self._cameras.close()
        self._mw.close()

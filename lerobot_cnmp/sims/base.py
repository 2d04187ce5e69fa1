"""What the CNMP MuJoCo sims share: the episode options, the end of a step, rendering and contact queries."""

from __future__ import annotations

import gymnasium as gym
import mujoco
import numpy as np


def contacts_with(data, gid: int) -> np.ndarray:
    """Geom ids in contact with geom ``gid`` now."""
    if data.ncon == 0:
        return np.zeros(0, dtype=int)
    pairs = data.contact.geom[: data.ncon]
    other = np.where(pairs[:, 0] == gid, pairs[:, 1], np.where(pairs[:, 1] == gid, pairs[:, 0], -1))
    return other[other >= 0]


class MujocoSimEnv(gym.Env):
    """Base of the CNMP sims. A subclass sets ``camera`` (the MJCF camera to render), builds
    ``self.model`` / ``self.data`` after :meth:`_init_options`, keeps a ``self._step`` counter and provides
    ``_obs()`` and ``_info()`` (with ``"is_success"``)."""

    metadata = {"render_modes": ["rgb_array"]}
    camera: str = ""

    def _init_options(self, render_mode, render_size, terminate_on_success, max_episode_steps) -> None:
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"unknown render_mode {render_mode!r}; choose 'rgb_array' or None")
        if int(render_size) < 16:
            raise ValueError(f"render_size must be at least 16 pixels, got {render_size}")
        self.render_mode = render_mode
        self.render_size = int(render_size)
        self.terminate_on_success = bool(terminate_on_success)
        if max_episode_steps is not None:
            self._max_episode_steps = int(max_episode_steps)
        self._self_truncate = max_episode_steps is not None
        self._renderer = None

    def _step_result(self):
        """``(obs, reward, terminated, truncated, info)`` after ``self._step`` steps: reward 1 on success,
        termination on success if asked, truncation at ``max_episode_steps`` if the env counts them."""
        info = self._info()
        success = info["is_success"]
        terminated = bool(success and self.terminate_on_success)
        truncated = bool(self._self_truncate and self._step >= self._max_episode_steps and not terminated)
        return self._obs(), 1.0 if success else 0.0, terminated, truncated, info

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        if self._renderer is None:
            self._renderer = mujoco.Renderer(self.model, self.render_size, self.render_size)
        self._renderer.update_scene(self.data, camera=self.camera)
        return self._renderer.render().copy()

    def close(self):
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

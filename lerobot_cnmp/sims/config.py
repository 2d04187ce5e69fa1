"""What the CNMP sims' LeRobot ``EnvConfig``s share: rendering and episode options, their checks, the gym id
``cnmp/<task>``, the registration of each sim's gymnasium id by a string entry point (no env module is
imported until an env is made), and the features of the point-mass sims."""

from __future__ import annotations

from dataclasses import dataclass

import gymnasium as gym
from lerobot.configs import FeatureType, PolicyFeature
from lerobot.envs.configs import EnvConfig
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_STATE


def register_gym_id(gym_id: str, entry_point: str, max_episode_steps: int) -> None:
    """Register ``gym_id`` with gymnasium (once): ``entry_point`` is ``"module:callable"``, imported by
    ``gym.make`` only."""
    if gym_id not in gym.registry:
        gym.register(id=gym_id, entry_point=entry_point, max_episode_steps=max_episode_steps)


def point_mass_features(env_state_dim: int) -> dict[str, PolicyFeature]:
    """The features of a point-mass sim (obstacle2d, room): the (x, y) action, ``agent_pos`` (x, y) and
    ``environment_state`` (the encoded conditions, ``env_state_dim`` values)."""
    return {
        ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(2,)),
        "agent_pos": PolicyFeature(type=FeatureType.STATE, shape=(2,)),
        "environment_state": PolicyFeature(type=FeatureType.ENV, shape=(env_state_dim,)),
    }


def point_mass_features_map(**extra: str) -> dict[str, str]:
    """The env keys of a point-mass sim mapped to the policy's (``extra``: further env key -> policy key)."""
    return {ACTION: ACTION, "agent_pos": OBS_STATE, "environment_state": OBS_ENV_STATE, **extra}


@dataclass
class CNMPSimConfig(EnvConfig):
    """What the CNMP sims' configs share (not an env type itself): rendering and episode options.

    Fields:
        render_mode: ``rgb_array`` (for eval videos) or ``None``.
        render_size: side of the rendered square image, pixels.
        terminate_on_success: end the episode as soon as it succeeds (recording demos sets False).
    The gym id is ``cnmp/<task>``.
    """

    render_mode: str | None = "rgb_array"
    render_size: int = 256
    terminate_on_success: bool = True

    @property
    def gym_id(self) -> str:
        return f"cnmp/{self.task}"

    def _check_choice(self, name: str, choices) -> None:
        value = getattr(self, name)
        if value not in choices:
            raise ValueError(f"unknown {name} {value!r} for {self.type}; choose one of {list(choices)}")

    def _check_common(self) -> None:
        if self.render_mode not in (None, "rgb_array"):
            raise ValueError(f"unknown render_mode {self.render_mode!r}; choose 'rgb_array' or None")
        if self.episode_length < 1:
            raise ValueError(f"episode_length must be >= 1, got {self.episode_length}")
        if self.render_size < 16:
            raise ValueError(f"render_size must be >= 16, got {self.render_size}")

    @property
    def package_name(self) -> str:
        return "lerobot_cnmp.sims"

    def _common_gym_kwargs(self) -> dict:
        return {
            "render_mode": self.render_mode,
            "render_size": self.render_size,
            "terminate_on_success": self.terminate_on_success,
            "max_episode_steps": self.episode_length,
        }

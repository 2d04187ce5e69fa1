"""``--env.type=cnmp_so101``: the LeRobot ``EnvConfig`` of the SO-101 pick-and-place sim (the third-party plugin's
task through :mod:`lerobot_cnmp.sims.so101.env`) and its gymnasium id ``cnmp/SO101PickPlace-v0`` (imports neither
MuJoCo nor the plugin)."""

from __future__ import annotations

from dataclasses import dataclass, field

from lerobot.configs import FeatureType, PolicyFeature
from lerobot.envs.configs import EnvConfig
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_STATE

from lerobot_cnmp.sims.cameras import cameras_replace_task_params, check_cameras, ground_truth_features
from lerobot_cnmp.sims.config import CNMPSimConfig, register_gym_id
from lerobot_cnmp.sims.so101.task import (
    ACTION_NAMES,
    AGENT_POS_NAMES,
    CONTROL_FPS,
    DEFAULT_ACTION_SCALE,
    DEFAULT_MAX_EPISODE_STEPS,
    DEFAULT_RENDER_SIZE,
    ENV_STATE_NAMES,
    SO101_GYM_ID,
)

register_gym_id(SO101_GYM_ID, "lerobot_cnmp.sims.so101.env:make_so101_pickplace", DEFAULT_MAX_EPISODE_STEPS)


@EnvConfig.register_subclass("cnmp_so101")
@dataclass
class CNMPSO101Env(CNMPSimConfig):
    """The SO-101 arm picking a cube and placing it on a goal, both at random positions (the third-party
    ``lerobot-env-so101==0.4.0`` plugin's ``SO101PickPlace-v0``, wrapped by :mod:`lerobot_cnmp.sims.so101.env`).

    ``agent_pos`` (14) reaches the policy as ``observation.state``, ``environment_state`` (6: block x, y, z
    and goal x, y, z, m) as ``observation.environment_state``; the action is ``[dx, dy, dz, grasp]``.

    Fields:
        task: gymnasium task name (the id is ``cnmp/<task>``).
        fps: control frequency, Hz (the plugin's 0.1 s control step).
        episode_length: steps before truncation (the plugin's 300; the scripted expert is done in ~65).
        random_block_position: draw the block and the goal at each reset (default); False uses the
            plugin's fixed block (0.25, 0) and goal (0.20, 0.08).
        action_scale: metres per unit of ``dx, dy, dz`` (0.025, the plugin's controllers' scale; the
            plugin's own default is 1.0).
        cameras: cameras observed as ``observation.images.<name>``: ``table`` (a view over the workspace that
            the plugin's model lacks) and ``front`` (the model's own). Non-empty: the block and goal positions
            are NOT given to the policy (no ``environment_state``, as in a real SO-101 dataset); the recorder
            stores them (block start and goal) as ``ground_truth.task_params`` for reports.
        camera_size: side of each camera image, pixels (shadows, reflections and skybox off: ~0.1 s a frame
            with software EGL, no GPU; see :mod:`lerobot_cnmp.sims.so101.env`).
        render_mode, render_size, terminate_on_success: see :class:`CNMPSimConfig`.
    """

    task: str | None = "SO101PickPlace-v0"
    fps: int = CONTROL_FPS
    episode_length: int = DEFAULT_MAX_EPISODE_STEPS
    random_block_position: bool = True
    action_scale: float = DEFAULT_ACTION_SCALE
    cameras: list[str] = field(default_factory=list)
    camera_size: int = DEFAULT_RENDER_SIZE
    render_size: int = DEFAULT_RENDER_SIZE
    features: dict[str, PolicyFeature] = field(
        default_factory=lambda: {
            ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(len(ACTION_NAMES),)),
            "agent_pos": PolicyFeature(type=FeatureType.STATE, shape=(len(AGENT_POS_NAMES),)),
            "environment_state": PolicyFeature(type=FeatureType.ENV, shape=(len(ENV_STATE_NAMES),)),
        }
    )
    features_map: dict[str, str] = field(
        default_factory=lambda: {
            ACTION: ACTION,
            "agent_pos": OBS_STATE,
            "environment_state": OBS_ENV_STATE,
        }
    )

    def __post_init__(self):
        self._check_choice("task", ("SO101PickPlace-v0",))
        self._check_common()
        if not self.action_scale > 0:
            raise ValueError(f"action_scale must be positive, got {self.action_scale}")
        self.cameras = check_cameras(self.cameras, self.camera_size)
        cameras_replace_task_params(self.features, self.features_map, self.cameras, self.camera_size)

    @property
    def ground_truth(self) -> dict[str, str]:
        """Dataset feature -> the env ``info`` key the recorder stores it from (none when γ is observed)."""
        return ground_truth_features(self.cameras)

    @property
    def gym_kwargs(self) -> dict:
        return {
            "random_block_position": self.random_block_position,
            "action_scale": float(self.action_scale),
            "cameras": list(self.cameras),
            "camera_size": self.camera_size,
            **self._common_gym_kwargs(),
        }

"""``--env.type=cnmp_metaworld``: the LeRobot ``EnvConfig`` of a MetaWorld v3 task through our wrapper and its
gymnasium id ``cnmp/MetaWorld-v0`` (imports neither MuJoCo nor MetaWorld; checking the task name imports
MetaWorld)."""

from __future__ import annotations

from dataclasses import dataclass, field

from lerobot.configs import FeatureType, PolicyFeature
from lerobot.envs.configs import EnvConfig
from lerobot.processor import PolicyProcessorPipeline, RenameObservationsProcessorStep
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_STATE

from lerobot_cnmp.data.sm_spec import TASK_PARAMS
from lerobot_cnmp.sims.cameras import cameras_replace_task_params, check_cameras, ground_truth_features
from lerobot_cnmp.sims.config import CNMPSimConfig, register_gym_id
from lerobot_cnmp.sims.metaworld.task import CONTROL_FPS, MAX_PATH_LENGTH, check_task

METAWORLD_GYM_ID = "cnmp/MetaWorld-v0"
register_gym_id(METAWORLD_GYM_ID, "lerobot_cnmp.sims.metaworld.env:MetaWorldEnv", MAX_PATH_LENGTH)


@EnvConfig.register_subclass("cnmp_metaworld")
@dataclass
class CNMPMetaWorldEnv(CNMPSimConfig):
    """A MetaWorld v3 task through our thin wrapper (:mod:`lerobot_cnmp.sims.metaworld.env`): MetaWorld's physics,
    randomization and success flag; the hand state as ``agent_pos`` and γ (first frame's object and goal
    positions) as ``environment_state``, which reaches the policy as ``observation.task_params``.

    Fields:
        task: any MetaWorld v3 task name (``reach-v3``, ``push-v3``, ``pick-place-v3``, ...).
        fps: MetaWorld's control rate (80 Hz).
        episode_length: steps before truncation (at most MetaWorld's 500).
        render_mode, render_size, terminate_on_success: see :class:`CNMPSimConfig` (default no rendering:
            MetaWorld's renderer is slow on CPU).
        cameras: MetaWorld camera names (``corner``, ``corner2``, ``corner3``, ``topview``, ``behindGripper``,
            ``gripperPOV``) observed as ``observation.images.<name>``. Non-empty: γ is NOT given to the policy
            (no ``environment_state``); the recorder stores it as ``ground_truth.task_params`` for reports.
        camera_size: side of each camera image, pixels (shadows, reflections and skybox off: ~20-30 ms a
            128 x 128 frame on CPU).
    """

    task: str | None = "reach-v3"
    fps: int = CONTROL_FPS
    episode_length: int = 150
    render_mode: str | None = None
    render_size: int = 128
    cameras: list[str] = field(default_factory=list)
    camera_size: int = 128
    features: dict[str, PolicyFeature] = field(
        default_factory=lambda: {
            ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(4,)),
            "agent_pos": PolicyFeature(type=FeatureType.STATE, shape=(4,)),
            "environment_state": PolicyFeature(type=FeatureType.STATE, shape=(6,)),
        }
    )
    features_map: dict[str, str] = field(
        default_factory=lambda: {ACTION: ACTION, "agent_pos": OBS_STATE, "environment_state": TASK_PARAMS}
    )

    def __post_init__(self):
        check_task(self.task)
        if not 1 <= self.episode_length <= MAX_PATH_LENGTH:
            raise ValueError(f"episode_length must be in [1, {MAX_PATH_LENGTH}] (MetaWorld's path length), "
                             f"got {self.episode_length}")
        self._check_common()
        self.cameras = check_cameras(self.cameras, self.camera_size)
        cameras_replace_task_params(self.features, self.features_map, self.cameras, self.camera_size)

    @property
    def ground_truth(self) -> dict[str, str]:
        """Dataset feature -> the env ``info`` key the recorder stores it from (none when γ is observed)."""
        return ground_truth_features(self.cameras)

    @property
    def gym_id(self) -> str:
        return METAWORLD_GYM_ID

    @property
    def gym_kwargs(self) -> dict:
        return {"task": self.task, "cameras": list(self.cameras), "camera_size": self.camera_size,
                **self._common_gym_kwargs()}

    def get_env_processors(self):
        """γ arrives as ``observation.environment_state``; the policy reads it as ``observation.task_params``
        (with cameras there is no γ to rename)."""
        rename = RenameObservationsProcessorStep(rename_map={OBS_ENV_STATE: TASK_PARAMS})
        return PolicyProcessorPipeline(steps=[rename]), PolicyProcessorPipeline(steps=[])

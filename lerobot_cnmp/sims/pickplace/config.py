"""``--env.type=cnmp_pickplace``: the LeRobot ``EnvConfig`` of the pick-and-place sim and its gymnasium id
``cnmp/PickPlace-v0`` (imports no MuJoCo)."""

from __future__ import annotations

from dataclasses import dataclass, field

from lerobot.configs import FeatureType, PolicyFeature
from lerobot.envs.configs import EnvConfig
from lerobot.processor import PolicyProcessorPipeline, RenameObservationsProcessorStep
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_STATE

from lerobot_cnmp.data.sm_spec import TASK_PARAMS
from lerobot_cnmp.sims.config import CNMPSimConfig, register_gym_id
from lerobot_cnmp.sims.pickplace.model import CONTROL_FPS, DEFAULT_MAX_EPISODE_STEPS

PICKPLACE_GYM_ID = "cnmp/PickPlace-v0"
register_gym_id(PICKPLACE_GYM_ID, "lerobot_cnmp.sims.pickplace.env:PickPlaceEnv", DEFAULT_MAX_EPISODE_STEPS)


@EnvConfig.register_subclass("cnmp_pickplace")
@dataclass
class CNMPPickPlaceEnv(CNMPSimConfig):
    """UR10-like arm picking a box and placing it beyond a wall (CNMP paper, Sec. IV-C).

    The task parameters γ = (object height, obstacle height) in cm come out of the env as
    ``environment_state`` (the vector LeRobot's rollout passes through) and reach the policy as
    ``observation.task_params`` (renamed by this env's preprocessor), the feature the dataset stores them in.

    Fields:
        task: gymnasium task name (the id is ``cnmp/<task>``).
        fps: control frequency, Hz.
        episode_length: steps before truncation (the demonstrated motion takes 200).
        task_params: a fixed γ (object_cm, obstacle_cm) for every episode; None (default) draws γ uniformly
            from the training range, object in [2, 6] cm and obstacle in [2, 8] cm.
        render_mode, render_size, terminate_on_success: see :class:`CNMPSimConfig`.
    """

    task: str | None = "PickPlace-v0"
    fps: int = CONTROL_FPS
    episode_length: int = DEFAULT_MAX_EPISODE_STEPS
    task_params: tuple[float, float] | None = None
    features: dict[str, PolicyFeature] = field(
        default_factory=lambda: {
            ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(7,)),
            "agent_pos": PolicyFeature(type=FeatureType.STATE, shape=(7,)),
            "environment_state": PolicyFeature(type=FeatureType.STATE, shape=(2,)),
        }
    )
    features_map: dict[str, str] = field(
        default_factory=lambda: {ACTION: ACTION, "agent_pos": OBS_STATE, "environment_state": TASK_PARAMS}
    )

    def __post_init__(self):
        self._check_choice("task", ("PickPlace-v0",))
        if self.task_params is not None and len(self.task_params) != 2:
            raise ValueError(f"task_params must be (object_cm, obstacle_cm), got {self.task_params}")
        self._check_common()

    @property
    def gym_kwargs(self) -> dict:
        return {
            "task_params": None if self.task_params is None else tuple(float(v) for v in self.task_params),
            **self._common_gym_kwargs(),
        }

    def get_env_processors(self):
        """γ arrives as ``observation.environment_state``; the policy reads it as ``observation.task_params``."""
        rename = RenameObservationsProcessorStep(rename_map={OBS_ENV_STATE: TASK_PARAMS})
        return PolicyProcessorPipeline(steps=[rename]), PolicyProcessorPipeline(steps=[])

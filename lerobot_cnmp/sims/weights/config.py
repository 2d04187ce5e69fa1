"""``--env.type=cnmp_weights``: the LeRobot ``EnvConfig`` of the weights sim and its gymnasium id
``cnmp/Weights-v0`` (imports no MuJoCo)."""

from __future__ import annotations

from dataclasses import dataclass, field

from lerobot.configs import FeatureType, PolicyFeature
from lerobot.envs.configs import EnvConfig
from lerobot.utils.constants import ACTION, OBS_STATE

from lerobot_cnmp.sims.config import CNMPSimConfig, register_gym_id
from lerobot_cnmp.sims.weights.task import CONTROL_FPS, DEFAULT_MAX_EPISODE_STEPS, PERTURBATION_CHOICES

WEIGHTS_GYM_ID = "cnmp/Weights-v0"
register_gym_id(WEIGHTS_GYM_ID, "lerobot_cnmp.sims.weights.env:WeightsEnv", DEFAULT_MAX_EPISODE_STEPS)


@EnvConfig.register_subclass("cnmp_weights")
@dataclass
class CNMPWeightsEnv(CNMPSimConfig):
    """The arm sorting containers by shape and weight, sensed through fingers and a wrist F/T sensor (CNMP
    paper, Sec. IV-D). The SM is task space: tool point (3), finger positions (2), F/T (6); no observation
    names the class.

    Fields:
        task: gymnasium task name (the id is ``cnmp/<task>``).
        fps: control frequency, Hz.
        episode_length: steps before truncation (the demonstrated motion takes 200).
        perturbation: ``none`` or ``weight_switch`` (0.5 kg added once to a held light container during
            transport, so it becomes heavy; success then means the heavy zone).
        render_mode, render_size, terminate_on_success: see :class:`CNMPSimConfig`.
    """

    task: str | None = "Weights-v0"
    fps: int = CONTROL_FPS
    episode_length: int = DEFAULT_MAX_EPISODE_STEPS
    perturbation: str = "none"
    features: dict[str, PolicyFeature] = field(
        default_factory=lambda: {
            ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(11,)),
            "agent_pos": PolicyFeature(type=FeatureType.STATE, shape=(11,)),
        }
    )
    features_map: dict[str, str] = field(default_factory=lambda: {ACTION: ACTION, "agent_pos": OBS_STATE})

    def __post_init__(self):
        self._check_choice("task", ("Weights-v0",))
        self._check_choice("perturbation", PERTURBATION_CHOICES)
        self._check_common()

    @property
    def gym_kwargs(self) -> dict:
        return {"perturbation": self.perturbation, **self._common_gym_kwargs()}

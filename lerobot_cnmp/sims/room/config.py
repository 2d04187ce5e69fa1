"""``--env.type=cnmp_room``: the LeRobot ``EnvConfig`` of the room sim and its gymnasium id ``cnmp/Room-v0``
(imports no MuJoCo)."""

from __future__ import annotations

from dataclasses import dataclass, field

from lerobot.configs import FeatureType, PolicyFeature
from lerobot.envs.configs import EnvConfig
from lerobot.utils.constants import OBS_IMAGES

from lerobot_cnmp.sims.config import CNMPSimConfig, point_mass_features, point_mass_features_map, register_gym_id
from lerobot_cnmp.sims.room.model import CONTROL_FPS, DEFAULT_IMAGE_SIZE, ENV_STATE_DIM, MAX_IMAGE_SIZE
from lerobot_cnmp.sims.room.task import CONDITION_CHOICES, DEFAULT_MAX_EPISODE_STEPS

ROOM_GYM_ID = "cnmp/Room-v0"
register_gym_id(ROOM_GYM_ID, "lerobot_cnmp.sims.room.env:RoomEnv", DEFAULT_MAX_EPISODE_STEPS)


@EnvConfig.register_subclass("cnmp_room")
@dataclass
class CNMPRoomEnv(CNMPSimConfig):
    """Point mass crossing a room around two obstacles, seen as a top-down binary mask image (CNMP paper,
    Sec. IV-B).

    The env's observation ``pixels["top"]`` reaches the policy as ``observation.images.top`` (LeRobot's
    ``preprocess_observation``: float CHW in [0, 1]); its feature ``pixels/top`` is built from ``image_size``.

    Fields:
        task: gymnasium task name (the id is ``cnmp/<task>``).
        fps: control frequency, Hz (10 physics steps of 2 ms per control step).
        episode_length: steps before truncation (the demonstrated motion takes 100).
        condition: the conditions of each episode, points of the room's planned path: ``start_end``
            (default; the start at phase 0 and the end at phase 1), ``via_end`` (a point at a phase drawn
            in [0.3, 0.7], and the end) or ``via`` (that point only).
        image_size: side of the square mask image, pixels (16 to 1024).
        render_mode, render_size, terminate_on_success: see :class:`CNMPSimConfig`.
    """

    task: str | None = "Room-v0"
    fps: int = CONTROL_FPS
    episode_length: int = DEFAULT_MAX_EPISODE_STEPS
    condition: str = "start_end"
    image_size: int = DEFAULT_IMAGE_SIZE
    features: dict[str, PolicyFeature] = field(default_factory=lambda: point_mass_features(ENV_STATE_DIM))
    features_map: dict[str, str] = field(
        default_factory=lambda: point_mass_features_map(**{"pixels/top": f"{OBS_IMAGES}.top"})
    )

    def __post_init__(self):
        self._check_choice("task", ("Room-v0",))
        self._check_choice("condition", CONDITION_CHOICES)
        if not 16 <= self.image_size <= MAX_IMAGE_SIZE:
            raise ValueError(f"image_size must be in [16, {MAX_IMAGE_SIZE}] pixels, got {self.image_size}")
        self._check_common()
        # the image feature is built here, not in the default factory, so that it follows image_size
        self.features["pixels/top"] = PolicyFeature(
            type=FeatureType.VISUAL, shape=(self.image_size, self.image_size, 3)
        )

    @property
    def gym_kwargs(self) -> dict:
        return {"condition": self.condition, "image_size": self.image_size, **self._common_gym_kwargs()}

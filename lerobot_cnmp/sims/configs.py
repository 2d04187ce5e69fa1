"""LeRobot ``EnvConfig``s for the CNMP sims (``--env.type=cnmp_obstacle2d``, ``cnmp_pickplace``, ``cnmp_weights``,
``cnmp_room``)."""

from __future__ import annotations

from dataclasses import dataclass, field

from lerobot.configs import FeatureType, PolicyFeature
from lerobot.envs.configs import EnvConfig
from lerobot.processor import PolicyProcessorPipeline, RenameObservationsProcessorStep
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_IMAGES, OBS_STATE

from lerobot_cnmp.policy.configuration_cnmp import TASK_PARAMS

from lerobot_cnmp.sims.obstacle2d.env import (
    ACTUATOR_CHOICES,
    CONDITION_CHOICES,
    CONTROL_FPS,
    DEFAULT_MAX_EPISODE_STEPS,
    ENV_STATE_DIM,
    FAMILY_CHOICES,
    PERTURBATION_CHOICES,
    RATE_LIMIT,
    _check_family,
)
from lerobot_cnmp.sims.room.env import CONDITION_CHOICES as ROOM_CONDITION_CHOICES
from lerobot_cnmp.sims.room.env import CONTROL_FPS as ROOM_CONTROL_FPS
from lerobot_cnmp.sims.room.env import DEFAULT_IMAGE_SIZE as ROOM_DEFAULT_IMAGE_SIZE
from lerobot_cnmp.sims.room.env import DEFAULT_MAX_EPISODE_STEPS as ROOM_MAX_EPISODE_STEPS
from lerobot_cnmp.sims.room.env import ENV_STATE_DIM as ROOM_ENV_STATE_DIM
from lerobot_cnmp.sims.room.env import MAX_IMAGE_SIZE as ROOM_MAX_IMAGE_SIZE

OBSTACLE2D_GYM_ID = "cnmp/Obstacle2D-v0"
PICKPLACE_GYM_ID = "cnmp/PickPlace-v0"
WEIGHTS_GYM_ID = "cnmp/Weights-v0"
ROOM_GYM_ID = "cnmp/Room-v0"


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


@EnvConfig.register_subclass("cnmp_obstacle2d")
@dataclass
class CNMPObstacle2DEnv(CNMPSimConfig):
    """2D point mass avoiding a round obstacle, over or under it (CNMP paper, Sec. IV-A).

    Fields:
        task: gymnasium task name (the id is ``cnmp/<task>``).
        fps: control frequency, Hz (10 physics steps of 2 ms per control step).
        episode_length: steps before truncation (the nominal demonstrated motion takes 200).
        conditions: how each episode's conditions are chosen: ``mixed`` (default; one of the next four per
            episode), ``paper_via``, ``paper_early``, ``paper_end`` (the paper's Fig. 4 conditions) or
            ``random`` (random family member and condition set), ``start_goal`` (start and goal) or
            ``start_goal_early`` (those and an early point, which names the mode). With family ``shared``
            only the last three exist.
        perturbation: ``none``, ``push`` (0.12 displacement away from the obstacle at a random step in
            [50, 120]), ``push_toward`` (toward the obstacle, stopping 0.02 short of it), ``push_random`` (a
            random direction, same stop) or ``hold`` (held still for 30 steps from a random step in [50, 120]).
        family: ``mirrored`` (the modes start and end at mirrored heights) or ``shared`` (both modes share the
            start and the goal, the paper's setting).
        actuator: ``servo`` (the stiff position servo of the demos) or ``rate_limited`` (its set point moves at
            most ``rate_limit`` m/s toward the command: the body lags behind the demos' schedule).
        rate_limit: the ``rate_limited`` actuator's top speed, m/s (default 0.08; the demos move at up to ~0.5).
        render_mode, render_size, terminate_on_success: see :class:`CNMPSimConfig`.
    """

    task: str | None = "Obstacle2D-v0"
    fps: int = CONTROL_FPS
    episode_length: int = DEFAULT_MAX_EPISODE_STEPS
    conditions: str = "mixed"
    perturbation: str = "none"
    family: str = "mirrored"
    actuator: str = "servo"
    rate_limit: float = RATE_LIMIT
    features: dict[str, PolicyFeature] = field(
        default_factory=lambda: {
            ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(2,)),
            "agent_pos": PolicyFeature(type=FeatureType.STATE, shape=(2,)),
            "environment_state": PolicyFeature(type=FeatureType.ENV, shape=(ENV_STATE_DIM,)),
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
        self._check_choice("task", ("Obstacle2D-v0",))
        self._check_choice("conditions", CONDITION_CHOICES)
        self._check_choice("perturbation", PERTURBATION_CHOICES)
        self._check_choice("family", FAMILY_CHOICES)
        self._check_choice("actuator", ACTUATOR_CHOICES)
        _check_family(self.family, self.conditions)
        self._check_common()

    @property
    def gym_kwargs(self) -> dict:
        return {
            "conditions": self.conditions,
            "perturbation": self.perturbation,
            "family": self.family,
            "actuator": self.actuator,
            "rate_limit": self.rate_limit,
            **self._common_gym_kwargs(),
        }


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
    fps: int = 50
    episode_length: int = 250
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
    fps: int = 50
    episode_length: int = 260
    perturbation: str = "none"
    features: dict[str, PolicyFeature] = field(
        default_factory=lambda: {
            ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(11,)),
            "agent_pos": PolicyFeature(type=FeatureType.STATE, shape=(11,)),
        }
    )
    features_map: dict[str, str] = field(default_factory=lambda: {ACTION: ACTION, "agent_pos": OBS_STATE})

    def __post_init__(self):
        from lerobot_cnmp.sims.weights.env import PERTURBATION_CHOICES as WEIGHTS_PERTURBATIONS

        self._check_choice("task", ("Weights-v0",))
        self._check_choice("perturbation", WEIGHTS_PERTURBATIONS)
        self._check_common()

    @property
    def gym_kwargs(self) -> dict:
        return {"perturbation": self.perturbation, **self._common_gym_kwargs()}


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
    fps: int = ROOM_CONTROL_FPS
    episode_length: int = ROOM_MAX_EPISODE_STEPS
    condition: str = "start_end"
    image_size: int = ROOM_DEFAULT_IMAGE_SIZE
    features: dict[str, PolicyFeature] = field(
        default_factory=lambda: {
            ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(2,)),
            "agent_pos": PolicyFeature(type=FeatureType.STATE, shape=(2,)),
            "environment_state": PolicyFeature(type=FeatureType.ENV, shape=(ROOM_ENV_STATE_DIM,)),
        }
    )
    features_map: dict[str, str] = field(
        default_factory=lambda: {
            ACTION: ACTION,
            "agent_pos": OBS_STATE,
            "environment_state": OBS_ENV_STATE,
            "pixels/top": f"{OBS_IMAGES}.top",
        }
    )

    def __post_init__(self):
        self._check_choice("task", ("Room-v0",))
        self._check_choice("condition", ROOM_CONDITION_CHOICES)
        if not 16 <= self.image_size <= ROOM_MAX_IMAGE_SIZE:
            raise ValueError(f"image_size must be in [16, {ROOM_MAX_IMAGE_SIZE}] pixels, got {self.image_size}")
        self._check_common()
        # the image feature is built here, not in the default factory, so that it follows image_size
        self.features["pixels/top"] = PolicyFeature(
            type=FeatureType.VISUAL, shape=(self.image_size, self.image_size, 3)
        )

    @property
    def gym_kwargs(self) -> dict:
        return {"condition": self.condition, "image_size": self.image_size, **self._common_gym_kwargs()}


METAWORLD_GYM_ID = "cnmp/MetaWorld-v0"


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
    """

    task: str | None = "reach-v3"
    fps: int = 80
    episode_length: int = 150
    render_mode: str | None = None
    render_size: int = 128
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
        from lerobot_cnmp.sims.metaworld.env import check_task

        check_task(self.task)
        if not 1 <= self.episode_length <= 500:
            raise ValueError(f"episode_length must be in [1, 500] (MetaWorld's path length), got {self.episode_length}")
        self._check_common()

    @property
    def gym_id(self) -> str:
        return METAWORLD_GYM_ID

    @property
    def gym_kwargs(self) -> dict:
        return {"task": self.task, **self._common_gym_kwargs()}

    def get_env_processors(self):
        """γ arrives as ``observation.environment_state``; the policy reads it as ``observation.task_params``."""
        rename = RenameObservationsProcessorStep(rename_map={OBS_ENV_STATE: TASK_PARAMS})
        return PolicyProcessorPipeline(steps=[rename]), PolicyProcessorPipeline(steps=[])

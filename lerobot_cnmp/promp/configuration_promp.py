"""Configuration of the ProMP baseline policy (``--policy.type=promp``, evaluated by stock ``lerobot-eval``).

A ProMP (Paraschos et al. 2013; ``movement_primitives.promp``) over a dataset's ``action`` trajectories,
fitted in closed form by ``lerobot-cnmp-fit-promp`` (the library's EM; no gradient steps, so not by
``lerobot-train``) and executed open loop: at an episode's first step it is conditioned on the episode's γ
(a contextual ProMP; γ read from ``observation.task_params`` or, on an env that gives its task parameters as
its state, ``observation.environment_state``) or on the conditions of ``observation.environment_state``, and its mean action
trajectory is then commanded on the demos' schedule, whatever the robot senses.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from lerobot.configs import NormalizationMode, PreTrainedConfig
from lerobot.optim import AdamConfig
from lerobot.utils.constants import OBS_ENV_STATE

from lerobot_cnmp.data.sm_spec import TASK_PARAMS
from lerobot_cnmp.policy.configuration_cnmp import identity_normalization

PROMP_CONDITIONING = ("none", "task_params", "environment_state", "conditions")
# the contextual modes and the observation key each reads γ from
CONTEXT_KEYS = {"task_params": TASK_PARAMS, "environment_state": OBS_ENV_STATE}


@PreTrainedConfig.register_subclass("promp")
@dataclass
class ProMPConfig(PreTrainedConfig):
    """ProMP baseline: what it was fitted on and how it runs.

    Args:
        conditioning: What the plan is conditioned on at an episode's first step. ``task_params``: the
            episode's γ (``observation.task_params``), through the joint Gaussian of the demos' weights and γ
            (``ProMPBaseline``'s contextual ProMP). ``environment_state``: the same contextual ProMP with γ read
            from ``observation.environment_state`` (an env whose state is its task parameters, e.g. SO-101's
            block and goal positions). ``conditions``: the SM points of
            ``observation.environment_state`` in the CNMP condition layout (Gaussian conditioning of the
            weights). ``none``: the demos' mean.
        n_weights_per_dim: RBF weights per action dim (the paper's comparison used 31).
        condition_std: σ of a condition point in the Gaussian conditioning.
        context_ridge: Ridge λ on the standardized γ covariance (see ``ProMPBaseline``).
        schedule_steps: Control steps the plan spans: phase k / (schedule_steps - 1) at step k, then its last
            action is held. Set by the fit to the demos' median length.
        action_dim: Dims of ``action`` (set by the fit; sizes the weight buffers).
        task_dim: Dims of γ (set by the fit; 0 without γ).
    """

    conditioning: str = "task_params"
    n_weights_per_dim: int = 31
    condition_std: float = 1e-3
    context_ridge: float = 0.1
    schedule_steps: int = 0
    action_dim: int = 0
    task_dim: int = 0
    n_obs_steps: int = 1

    # the ProMP works in the dataset's units: LeRobot's normalizers pass through
    normalization_mapping: dict[str, NormalizationMode] = field(default_factory=identity_normalization)

    def __post_init__(self):
        super().__post_init__()
        if self.conditioning not in PROMP_CONDITIONING:
            raise ValueError(f"conditioning must be one of {PROMP_CONDITIONING}, got {self.conditioning!r}")
        if self.n_weights_per_dim < 2:
            raise ValueError(f"n_weights_per_dim must be >= 2, got {self.n_weights_per_dim}")
        if self.condition_std <= 0 or self.context_ridge <= 0:
            raise ValueError(f"condition_std and context_ridge must be > 0, got {self.condition_std}, "
                             f"{self.context_ridge}")
        if min(self.schedule_steps, self.action_dim, self.task_dim) < 0:
            raise ValueError("schedule_steps, action_dim and task_dim must be >= 0")
        if self.contextual and self.action_dim and not self.task_dim:
            raise ValueError(f"conditioning={self.conditioning!r} needs task_dim > 0 (the fit sets it from the "
                             f"dataset's {self.context_key!r})")

    @property
    def contextual(self) -> bool:
        """Whether the plan is the weights' Gaussian conditioned on γ (a contextual ProMP)."""
        return self.conditioning in CONTEXT_KEYS

    @property
    def context_key(self) -> str | None:
        """The observation key γ is read from (None for ``conditions`` / ``none``)."""
        return CONTEXT_KEYS.get(self.conditioning)

    @property
    def n_weights(self) -> int:
        return self.action_dim * self.n_weights_per_dim

    @property
    def observation_delta_indices(self) -> None:
        return None

    @property
    def action_delta_indices(self) -> None:
        return None

    @property
    def reward_delta_indices(self) -> None:
        return None

    def get_optimizer_preset(self) -> AdamConfig:  # required by LeRobot's interface; a ProMP is not trained by it
        return AdamConfig(lr=0.0)

    def get_scheduler_preset(self) -> None:
        return None

    def validate_features(self) -> None:
        if self.schedule_steps < 2 or self.action_dim < 1:
            raise ValueError("this ProMP config is not fitted (schedule_steps < 2 or action_dim 0): make one with "
                             "lerobot-cnmp-fit-promp")

"""ProMP as a LeRobot policy (``--policy.type=promp``): the open-loop baseline that ``lerobot-eval`` runs.

The distribution (the library's weight mean and covariance, and for a contextual ProMP the Gaussian of the
weights given γ) is stored as buffers, so the policy saves, loads and evaluates like any LeRobot policy. The
arithmetic is ``ProMPBaseline``'s (``movement_primitives``). Execution: at an episode's first
``select_action`` each batch row's plan is the conditioned mean over ``schedule_steps`` phases; step k
returns row's action k (then the last one), whatever the observation says (open loop).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot.utils.constants import OBS_ENV_STATE

from lerobot_cnmp.policy.checkpoint import check_weights_file
from lerobot_cnmp.promp.configuration_promp import ProMPConfig


class ProMPPolicy(PreTrainedPolicy):
    """Open-loop ProMP; fitted by ``lerobot-cnmp-fit-promp`` (``ProMPPolicy.from_baseline``), not trained."""

    config_class = ProMPConfig
    name = "promp"

    def __init__(self, config: ProMPConfig, dataset_meta=None, dataset_stats=None, **kwargs):
        if not isinstance(config, ProMPConfig):
            raise TypeError(f"ProMPPolicy needs a ProMPConfig; got {type(config).__name__}")
        super().__init__(config)
        config.validate_features()
        self.config = config
        n, g = config.n_weights, config.task_dim
        self.register_buffer("weight_mean", torch.zeros(n, dtype=torch.float64))
        self.register_buffer("weight_cov", torch.eye(n, dtype=torch.float64))
        if config.contextual:
            self.register_buffer("context_mu_g", torch.zeros(g, dtype=torch.float64))
            self.register_buffer("context_sd_g", torch.ones(g, dtype=torch.float64))
            self.register_buffer("context_mu_w", torch.zeros(n, dtype=torch.float64))
            self.register_buffer("context_gain", torch.zeros(n, g, dtype=torch.float64))
            self.register_buffer("context_cov", torch.eye(n, dtype=torch.float64))
        self._baseline = None
        self.reset()

    @classmethod
    def from_baseline(cls, baseline, config: ProMPConfig) -> ProMPPolicy:
        """A policy holding a fitted ``ProMPBaseline``'s distribution."""
        policy = cls(config)
        arrays = baseline.to_arrays()
        for name, buf in policy.named_buffers():
            if name not in arrays:
                raise ValueError(f"the baseline has no {name!r}: was it fitted with γ as the config's conditioning "
                                 f"{config.conditioning!r} needs?")
            if tuple(arrays[name].shape) != tuple(buf.shape):
                raise ValueError(f"{name}: the baseline's shape {arrays[name].shape} is not the config's {tuple(buf.shape)}")
            buf.copy_(torch.from_numpy(arrays[name]))
        return policy

    @classmethod
    def _load_as_safetensor(cls, model, model_file: str, map_location: str, strict: bool):
        """LeRobot's loading, after checking that ``model_file`` is a whole safetensors file (named if not)."""
        check_weights_file(model_file)
        return super()._load_as_safetensor(model, model_file, map_location, strict)

    def baseline(self):
        """The ``ProMPBaseline`` of the buffers (rebuilt once after loading)."""
        from lerobot_cnmp.promp.baselines import ProMPBaseline

        if self._baseline is None:
            c = self.config
            self._baseline = ProMPBaseline.from_arrays(
                {k: v.cpu().numpy() for k, v in self.named_buffers()}, sm_dim=c.action_dim,
                n_weights_per_dim=c.n_weights_per_dim, condition_std=c.condition_std, context_ridge=c.context_ridge)
        return self._baseline

    # ---- LeRobot interface -------------------------------------------------------------------------

    def get_optim_params(self) -> list:
        return []

    def forward(self, batch: dict[str, Tensor]):
        raise NotImplementedError("a ProMP is fitted in closed form, not by gradient steps: use "
                                  "lerobot-cnmp-fit-promp --dataset_root=... --output_dir=... instead of lerobot-train")

    def reset(self) -> None:
        self._plan = None  # [B, schedule_steps, action_dim], built at an episode's first step
        self._step = 0

    def plan(self, batch: dict[str, Tensor]) -> np.ndarray:
        """Each batch row's conditioned mean action trajectory ``[B, schedule_steps, action_dim]``."""
        from lerobot_cnmp.execution.conditions import conditions_from_vector

        c = self.config
        phases = np.linspace(0.0, 1.0, c.schedule_steps)
        key = c.context_key or OBS_ENV_STATE
        if c.conditioning != "none" and key not in batch:
            raise KeyError(f"this ProMP is conditioned on {key!r} (conditioning={c.conditioning!r}) but the "
                           f"observation has only {sorted(batch)}")
        if c.conditioning == "none":
            ref = next(v for v in batch.values() if isinstance(v, Tensor))
            rows = ref.shape[0] if ref.ndim > 1 else 1
            plans = [self.baseline().predict(phases, [])[0]] * rows
        else:
            x = batch[key].detach().cpu().numpy().astype(np.float64)
            x = x.reshape(-1, x.shape[-1])
            if c.contextual:
                plans = [self.baseline().predict(phases, [], task_params=row)[0] for row in x]
            else:
                plans = [self.baseline().predict(phases, conditions_from_vector(row, c.action_dim))[0] for row in x]
        return np.stack(plans)

    @torch.no_grad()
    def predict_action_chunk(self, batch: dict[str, Tensor], **kwargs) -> Tensor:
        """The rest of the episode's plan from the current step ``[B, n, action_dim]`` (does not advance)."""
        if self._plan is None:
            self._plan = self.plan(batch)
        rest = self._plan[:, min(self._step, self.config.schedule_steps - 1):]
        return torch.from_numpy(np.ascontiguousarray(rest, dtype=np.float32))

    @torch.no_grad()
    def select_action(self, batch: dict[str, Tensor], **kwargs) -> Tensor:
        if self._plan is None:
            self._plan = self.plan(batch)
        action = self._plan[:, min(self._step, self.config.schedule_steps - 1)]
        self._step += 1
        device = next((v.device for v in batch.values() if isinstance(v, Tensor)), torch.device("cpu"))
        return torch.from_numpy(np.ascontiguousarray(action, dtype=np.float32)).to(device)

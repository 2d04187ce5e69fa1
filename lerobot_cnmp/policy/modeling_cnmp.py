"""CNMP as a LeRobot policy (``--policy.type=cnmp``): the network, its normalizer and image encoders, with
LeRobot's training and execution entry points forwarded to :mod:`lerobot_cnmp.policy.training` and
:class:`~lerobot_cnmp.execution.executor.CNMPExecutor`. The network itself: :mod:`lerobot_cnmp.model`."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot_cnmp.data.bank import EpisodeBank
from lerobot_cnmp.execution.executor import CNMPExecutor
from lerobot_cnmp.execution.modes import ModeSelector
from lerobot_cnmp.policy.checkpoint import check_weights_file
from lerobot_cnmp.model.cnmp import CNMP, Context, ConvEncoder, Episodes, Targets
from lerobot_cnmp.model.mixture import MixtureCNMP
from lerobot_cnmp.model.normalizer import SMNormalizer
from lerobot_cnmp.model.numpy_cnmp import NumpyTwin
from lerobot_cnmp.policy import training
from lerobot_cnmp.policy.configuration_cnmp import CNMPConfig
from lerobot_cnmp.policy.inputs import observed_episode_inputs, observed_task_params
from lerobot_cnmp.policy.rules import resolve_rules


def _network_from_config(config: CNMPConfig) -> CNMP:
    """The network a config describes: the paper's CNMP, or with ``n_experts`` K > 1 the mixture decoder; its
    per-dim NLL weights from ``commanded_loss_weight``. (The one place the model's settings are read.)"""
    shape = dict(sm_dim=config.sm_dim, task_dim=config.episode_dim, encoder_layers=config.encoder_layers,
                 decoder_layers=config.decoder_layers, min_std=config.min_std,
                 phase_frequencies=config.phase_frequencies)
    if config.linear_task_term and config.episode_dim == 0:
        raise ValueError("linear_task_term=true needs task parameters γ (the dataset/env gives none): set it to false")
    if config.n_experts > 1:
        return MixtureCNMP(**shape, n_experts=config.n_experts, gate_entropy_coef=config.mixture.gate_entropy_coef,
                           batch_entropy_coef=config.mixture.batch_entropy_coef,
                           shared_decoder_layers=config.mixture.shared_decoder_layers,
                           assignment_draws=config.mixture.assignment_draws,
                           unconditional_nll_coef=config.mixture.unconditional_nll_coef)
    model = CNMP(**shape, nll_beta=config.nll_beta, linear_task_term=bool(config.linear_task_term))
    spec = config.spec
    if config.commanded_loss_weight != 1.0 and not spec.tied:
        weights = torch.ones(config.sm_dim)
        weights[list(spec.commanded)] = config.commanded_loss_weight
        model.dim_weights = weights
    return model



def _executor_for(policy: "CNMPPolicy") -> CNMPExecutor:
    """The execution loop of a policy, given its collaborators (the network, the normalizer, the SM spec, the
    execution settings), not the policy itself."""
    c = policy.config
    return CNMPExecutor(
        policy.network, policy.normalizer, c.spec, c.execution, c, policy.episode_inputs, policy.task_params,
        modes=ModeSelector(c.mixture.mode_switch_margin, c.mixture.expert_selection) if c.n_experts > 1 else None,
        conditions=c.conditions,
        feature_widths={k: ft.shape[0] for k, ft in c.input_features.items() if len(ft.shape) == 1})

class CNMPPolicy(PreTrainedPolicy):
    """CNMP as a LeRobot policy.

    Training (``forward``): :func:`lerobot_cnmp.policy.training.training_loss` on the demonstrations the policy
    holds (``bank``). Execution (``select_action``, ``predict_action_chunk``, ``reset``) is forwarded to
    :class:`~lerobot_cnmp.execution.executor.CNMPExecutor` (``self.executor``): the paper's loop of Sec. III /
    Fig. 3, chunks and RTC, with its own settings (``config.execution``). The user's conditions:
    ``config.conditions`` (``--policy.conditions``) or :meth:`set_conditions`."""

    config_class = CNMPConfig
    name = "cnmp"

    def __init__(self, config: CNMPConfig, dataset_meta=None, dataset_stats=None, **kwargs):
        if not isinstance(config, CNMPConfig):
            raise TypeError(
                f"CNMPPolicy needs a CNMPConfig; got {type(config).__name__} (a checkpoint of another policy type?)"
            )
        super().__init__(config)
        config.resolve_sm(dataset_meta.features if dataset_meta is not None else None)
        config.validate_features()
        resolve_rules(config, from_dataset=dataset_meta is not None and not config.pretrained_path)
        self.config = config
        # One conv encoder per image feature; its embedding joins γ as the episode-level input of E and Q.
        self.image_encoders = nn.ModuleDict({
            key.replace(".", "_"): ConvEncoder(tuple(config.input_features[key].shape), config.image_channels,
                                               config.image_embed_dim, keypoints=config.image_encoder.keypoints,
                                               downsample=config.image_encoder.downsample,
                                               center=config.image_encoder.center)
            for key in config.image_keys
        })
        self.model = _network_from_config(config)
        # the auxiliary head of image_encoder.final_point_weight: images' embedding -> the SM at point_phases
        self.final_point_head = (nn.Linear(len(config.image_keys) * config.image_embed_dim,
                                           config.sm_dim * len(config.image_encoder.point_phases))
                                 if config.image_keys and config.image_encoder.final_point_weight > 0 else None)
        self.normalizer = SMNormalizer(config.sm_dim, config.task_dim)
        # the mask of execution's feedback point (joint layout: the sensed dims); None in the tied layout,
        # where the fed-back point is a whole SM point
        spec = config.spec
        sensed_only = torch.zeros(config.sm_dim)
        sensed_only[spec.sensed] = 1.0
        self.register_buffer("sensed_only_mask", None if spec.tied or not spec.sensed else sensed_only,
                             persistent=False)
        if config.sampling.feedback_draw_weight > 0 and self.sensed_only_mask is None:
            raise ValueError(
                "feedback_draw_weight > 0 needs the joint layout with sensed dims (execution conditions on them); "
                f"this SM is {'tied to the action' if spec.tied else 'commanded only'}: set it to 0")
        self.bank: EpisodeBank | None = None  # the training demonstrations
        self._first_frames: training.FirstFrames | None = None
        if dataset_meta is not None:
            self.set_dataset(dataset_meta)
        self._numpy_twin = NumpyTwin()  # execution copy of self.model, see network()
        self.executor = _executor_for(self)  # the execution loop and its state (validates the user's conditions)

    @classmethod
    def _load_as_safetensor(cls, model, model_file: str, map_location: str, strict: bool):
        """Load weights strictly: a checkpoint of another CNMP configuration is an error, not a silent
        partial load; a truncated or corrupt weights file is named as such."""
        check_weights_file(model_file)
        try:
            return super()._load_as_safetensor(model, model_file, map_location, strict=True)
        except RuntimeError as e:
            raise ValueError(
                f"the weights in {model_file} do not fit this CNMP configuration (layer sizes, SM or γ dims "
                f"differ, or a checkpoint from before the SM normalizer moved into the weights: retrain it): {e}"
            ) from e

    def generate_model_card(self, dataset_repo_id, model_type="cnmp", license=None, tags=None, cfg=None,
                            dataset_meta=None, eval_info: dict | None = None, repo_id: str | None = None):
        """The model card (``lerobot-train --policy.push_to_hub=true``, ``lerobot-cnmp-push``)."""
        from lerobot_cnmp.policy.card import model_card

        return model_card(self.config, dataset_repo_id, license=license, tags=tags, cfg=cfg, eval_info=eval_info,
                          repo_id=repo_id)

    # ---- training (lerobot_cnmp.policy.training) ------------------------------------------------------

    def set_dataset(self, dataset_meta) -> None:
        training.set_dataset(self, dataset_meta)

    def set_bank(self, bank: EpisodeBank, fps: float | None) -> None:
        training.set_bank(self, bank, fps)

    def episodes_for(self, episode_index: Tensor, generator: torch.Generator | None = None, draws: int = 1) -> Episodes:
        return training.episodes_for(self, episode_index, generator, draws)

    def feedback_draws(self, episode_index: Tensor, generator: torch.Generator | None = None,
                       inputs: Tensor | None = None) -> tuple[Context, Targets]:
        return training.feedback_draws(self, episode_index, generator, inputs)

    def forward(self, batch: dict[str, Tensor], generator: torch.Generator | None = None) -> tuple[Tensor, dict]:
        return training.training_loss(self, batch, generator)

    def get_optim_params(self) -> dict:
        return self.parameters()

    # ---- execution (lerobot_cnmp.execution.executor) --------------------------------------------------

    def network(self):
        """The network that execution runs: its numpy twin on CPU (``execution.numpy_execution``, rebuilt
        whenever a weight changes), else the torch model."""
        if (not self.config.execution.numpy_execution or self.training or self.model.frequencies.device.type != "cpu"
                or isinstance(self.model, MixtureCNMP)):
            return self.model
        return self._numpy_twin(self.model)

    def task_params(self, batch: dict[str, Tensor]) -> Tensor | None:
        """γ read from the observation (raw units), [B, G]; None when the CNMP has no task features."""
        return observed_task_params(self.config.spec, batch)

    def episode_inputs(self, batch: dict[str, Tensor]) -> Tensor | None:
        """The episode-level input of E and Q read from the observation: normalized γ and each image feature's
        embedding, [B, episode_dim]; None when there is neither."""
        return observed_episode_inputs(self.config, self.normalizer, self.image_encoders, batch)

    def set_conditions(self, conditions) -> None:
        """Give (or change, mid-episode: the next action is planned with them) the user's conditions, in the
        dataset's units and dim names: see :meth:`lerobot_cnmp.execution.executor.CNMPExecutor.set_conditions`."""
        self.executor.set_conditions(conditions)

    def reset(self) -> None:
        """Restart every env's execution state (at each episode start); the user's conditions stay."""
        if getattr(self, "executor", None) is not None:
            self.executor.reset()

    def supports_rtc(self) -> bool:
        """CNMP does Real-Time Chunking natively: it conditions the new chunk on the leftover actions."""
        return True

    @torch.no_grad()
    def predict_action_chunk(self, batch: dict[str, Tensor], inference_delay: int = 0,
                             prev_chunk_left_over: Tensor | None = None, n_steps: int | None = None,
                             return_std: bool = False, timestep: int | None = None, **kwargs):
        """The planned actions from the current phase over the next ``execution.n_action_steps`` (or
        ``n_steps``), [B, n, A] in the dataset's units (the predicted mean; σ with ``return_std=True``); the
        phase clock moves to the chunk's last step. RTC: ``prev_chunk_left_over`` [T, A] and
        ``inference_delay``; async: ``timestep`` of the observation (see :mod:`lerobot_cnmp.execution.executor`)."""
        actions, std = self.executor.chunk(batch, n_steps, inference_delay, prev_chunk_left_over, timestep)
        return (actions, std) if return_std else actions

    @torch.no_grad()
    def select_action(self, batch: dict[str, Tensor], **kwargs) -> Tensor:
        """One step of the execution loop for every env of the batch (:meth:`CNMPExecutor.step`)."""
        return self.executor.step(batch)

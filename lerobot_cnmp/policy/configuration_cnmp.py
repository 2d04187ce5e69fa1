"""Configuration of the CNMP policy (``--policy.type=cnmp``): the model and its training.

Defaults follow the paper (Seker et al., RSS 2019, Sec. III and IV-A) where it gives a value; where the
original trains with batch 1 and one query per step, we batch episodes and queries and raise the learning rate
accordingly. Settings of one concern form a section, ``--policy.<section>.<field>``: ``sampling``
(:class:`SamplingConfig`), ``mixture`` (:class:`MixtureConfig`), ``execution`` (:class:`ExecutionConfig`),
``image_encoder`` (:class:`~lerobot_cnmp.policy.image_config.ImageEncoderConfig`).
Configs of older layouts load through :func:`lerobot_cnmp.policy.legacy.upgrade_config_dict`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from lerobot.configs import NormalizationMode, PreTrainedConfig
from lerobot.optim import AdamConfig, CosineDecayWithWarmupSchedulerConfig, OptimizerConfig
from lerobot.utils.constants import ACTION, OBS_ENV_STATE

from lerobot_cnmp.data import sm_spec
from lerobot_cnmp.data.sm_spec import TASK_PARAMS, SMSpec  # noqa: F401  (TASK_PARAMS: re-exported)
from lerobot_cnmp.execution.conditions import slot_size
from lerobot_cnmp.execution.config import ExecutionConfig
from lerobot_cnmp.policy.config_checks import check as _check, is_count as _is_count
from lerobot_cnmp.policy.image_config import ImageEncoderConfig
from lerobot_cnmp.policy.legacy import decode_with_upgrade  # noqa: F401  (installs the legacy upgrade on decoding)


@OptimizerConfig.register_subclass("cnmp_adam")
@dataclass
class CNMPAdamConfig(AdamConfig):
    """LeRobot's Adam with torch's ``fused`` switch (``lerobot-train`` saves it as ``"type": "cnmp_adam"``)."""

    fused: bool = True


def identity_normalization() -> dict[str, NormalizationMode]:
    """LeRobot's normalizer steps pass every feature type through unchanged."""
    return {kind: NormalizationMode.IDENTITY for kind in ("VISUAL", "STATE", "ENV", "ACTION")}


@dataclass
class SamplingConfig:
    """How a training step draws observations (context) and queries (targets) from demonstrations
    (``--policy.sampling.<field>``; :func:`lerobot_cnmp.model.sampling.sample_context_and_targets`).

    Args:
        n_max_context: Most observations drawn from a demonstration per draw (n ~ U{1..n_max}).
        m_max_targets: Most query points per draw (m ~ U{1..m_max}); the paper uses 1.
        context_in_targets: Also use the drawn observations as queries (as the CNPs of Garnelo et al. do),
            which trains the model to pass through its conditions. The paper draws queries independently.
        partial_obs_prob: Probability that an observation constrains only a random non-empty subset of the SM
            dims, so the model can be conditioned on any subset of dims.
        sensed_obs_prob: Probability that an observation (not already a partial one) constrains exactly the
            sensed dims, as execution's feedback does (joint layout; the tied layout senses every dim).
        feedback_draw_weight: Weight w of *execution-shaped* draws (joint layout; 0: none, the paper): the
            sensed dims at the episode's first frame and at a uniform frame j, queried at j, j + 1 and
            ``feedback_draw_queries`` uniform frames; loss = (1 - w) NLL(random draws) + w NLL(execution-shaped
            draws). Use it when the action depends sharply on the sensed state (a reactive demonstrator).
        feedback_draw_queries: Uniform frames an execution-shaped draw queries besides j and j + 1; None:
            ``m_max_targets``. 0 trains exactly execution's two queries (behaviour cloning on (τ, state, γ)).
        draws_per_sample: Independent draws from each sampled episode per step: the loss sees
            batch_size x draws_per_sample draws (``lerobot-train`` loads one frame per sample, for its episode).
    """

    n_max_context: int = 8
    m_max_targets: int = 16
    context_in_targets: bool = True
    partial_obs_prob: float = 0.25
    sensed_obs_prob: float = 0.5
    feedback_draw_weight: float = 0.0
    feedback_draw_queries: int | None = None
    draws_per_sample: int = 1

    def __post_init__(self):
        for name in ("n_max_context", "m_max_targets", "draws_per_sample"):
            _check(_is_count(getattr(self, name), 1), f"sampling.{name} must be an integer >= 1, got {getattr(self, name)}")
        for name in ("partial_obs_prob", "sensed_obs_prob", "feedback_draw_weight"):
            _check(0.0 <= getattr(self, name) <= 1.0, f"sampling.{name} must be in [0, 1], got {getattr(self, name)}")
        _check(self.feedback_draw_queries is None or _is_count(self.feedback_draw_queries),
               f"sampling.feedback_draw_queries must be an integer >= 0 (or None), got {self.feedback_draw_queries}")


EXPERT_SELECTION = ("most_probable", "sample")


@dataclass
class MixtureConfig:
    """The mixture decoder's settings (``--policy.mixture.<field>``), read when ``n_experts`` K > 1.

    K query networks (experts) share the representation r; a gate π(r) = softmax(W r + b) weighs them (CNEP,
    Yildirim & Ugur, arXiv 2402.08424). Each episode's expert is the one the mixture assigns it on the empty
    context (the demonstrations' clusters); every context drawn from the episode trains that expert and the
    gate toward it. Three settings default to None, "the default for the model's K": for K > 1 the setting
    with which the mixture met its four benchmark bars (docs/mixture.md), for K = 1 the neutral value (any
    other value with K = 1 is an error). With K = 1 the other settings are not read.

    Args:
        gate_entropy_coef: Weight of the per-context gate entropy mean_b H(π_b) / log K, added to the loss:
            each context should commit to one expert.
        batch_entropy_coef: Weight of the batch's gate entropy H(mean_b π_b) / log K, subtracted: over a batch
            every expert should be used.
        shared_decoder_layers: How many of ``decoder_layers``' hidden layers the experts share (a trunk over
            [t_q, γ, r]; each expert keeps the layers after it and its own output layer). 0: K whole query
            networks. None: all hidden layers for K > 1, 0 for K = 1.
        assignment_draws: Which queries decide an episode's expert. p >= 1: those of its first p draws (of
            ``sampling.draws_per_sample``), the expert shared by all its draws; 0: each draw's own queries.
            None: 1 for K > 1, 0 for K = 1.
        unconditional_nll_coef: Weight c of the unconditional mixture's NLL (experts and gate on the empty
            context) in the loss c · NLL⁰_mix + Σ_k ρ_k (NLL_k - log π_k). None: 0.25 for K > 1, 1 for K = 1.
        expert_selection: Execution: at an episode's first step follow the most probable expert
            (``"most_probable"``) or one drawn from π (``"sample"``).
        mode_switch_margin: Execution: the followed expert c is kept until another is more probable than it
            by more than this margin (π_k* - π_c > margin, k* = argmax π) after re-conditioning. In [0, 1).
    """

    gate_entropy_coef: float = 0.2
    batch_entropy_coef: float = 0.88
    shared_decoder_layers: int | None = None
    assignment_draws: int | None = None
    unconditional_nll_coef: float | None = None
    expert_selection: str = "most_probable"
    mode_switch_margin: float = 0.3

    def __post_init__(self):
        for name in ("gate_entropy_coef", "batch_entropy_coef"):
            _check(0.0 <= getattr(self, name) < math.inf, f"mixture.{name} must be a finite number >= 0, got {getattr(self, name)}")
        for name in ("shared_decoder_layers", "assignment_draws"):
            value = getattr(self, name)
            _check(value is None or _is_count(value), f"mixture.{name} must be an integer >= 0 (or None), got {value}")
            setattr(self, name, None if value is None else int(value))
        c = self.unconditional_nll_coef
        _check(c is None or 0.0 < c < math.inf, f"mixture.unconditional_nll_coef must be a finite number > 0, got {c}")
        _check(self.expert_selection in EXPERT_SELECTION,
               f"mixture.expert_selection must be one of {EXPERT_SELECTION}, got {self.expert_selection!r}")
        _check(0.0 <= self.mode_switch_margin < 1.0, f"mixture.mode_switch_margin must be in [0, 1), got {self.mode_switch_margin}")

    def resolve(self, n_experts: int, hidden_layers: int) -> None:
        """Fill the None settings with the default for K = ``n_experts`` and check the others fit the model."""
        mixture = n_experts > 1
        defaults = {"shared_decoder_layers": hidden_layers if mixture else 0,
                    "assignment_draws": 1 if mixture else 0,
                    "unconditional_nll_coef": 0.25 if mixture else 1.0}
        for name, default in defaults.items():
            if getattr(self, name) is None:
                setattr(self, name, default)
            _check(mixture or getattr(self, name) == default,
                   f"mixture.{name}={getattr(self, name)} applies to a mixture, but n_experts is 1: set n_experts > 1 "
                   f"or leave mixture.{name} unset")
        _check(self.shared_decoder_layers <= hidden_layers,
               f"mixture.shared_decoder_layers must be between 0 and the {hidden_layers} hidden layers of "
               f"decoder_layers, got {self.shared_decoder_layers}")


@PreTrainedConfig.register_subclass("cnmp")
@dataclass
class CNMPConfig(PreTrainedConfig):
    """Conditional Neural Movement Primitive.

    The sensorimotor (SM) trajectory the CNMP learns is a set of dataset dims over phase
    (:mod:`lerobot_cnmp.data.sm_spec`): by default ``observation.state`` ⊕ ``action`` (sensed and commanded
    dims); frame k of an episode is at phase t = its time since the episode's start / the episode's duration.
    Execution conditions on the sensed dims of the live observation and outputs the predicted ``action``.
    Conditions (via-points, goals, in SM units) reach the policy through ``observation.environment_state`` in
    the layout of :mod:`lerobot_cnmp.execution.conditions`; task parameters γ are features read at an
    episode's first frame.

    Args:
        encoder_layers: Widths of the encoder E's layers; the last is the size of the representation r.
        decoder_layers: Hidden widths of the query network Q (its output layer, 2 x SM dim, is added).
        min_std: Floor of the predicted σ (normalized units): σ = min_std + softplus(raw).
        phase_frequencies: K > 0 adds sin/cos(k·π·t), k = 1..K, to the phase input of E and Q (Fourier
            features, for sharper timing); 0 feeds the raw phase t only, as in the paper.
        linear_task_term: Add ProMP's linear map from the episode input (γ, image embeddings) to μ, A(t)·γ. None: by
            the rule of :func:`lerobot_cnmp.policy.rules.linear_task_term` when training from a dataset, else off.
        n_experts: K, the number of query networks. 1: the paper's CNMP, one Gaussian decoder. K > 1: a
            mixture decoder (``mixture``), for demonstrations with modes the conditions do not decide.
        mixture: The mixture decoder's settings (:class:`MixtureConfig`).
        sampling: How a training step draws observations and queries (:class:`SamplingConfig`).
        nll_beta: β of the β-NLL (Seitzer et al., ICLR 2022): each SM dim's NLL term is weighted by
            stop_gradient(σ^(2β)); 0 is the paper's NLL, 0.5 keeps fitting dims the model finds hard early.
        commanded_loss_weight: Weight of each commanded (action) dim's NLL term, the sensed dims' being 1
            (shifts the fit toward the action when the SM has many sensed dims). Single decoder only.
        sm: The SM declaration: entries ``"feature"`` (all its dims) or ``"feature:dim"`` (a dim by name or
            index), in order; every ``action`` dim must be included; dims of other features are *sensed* (fed
            back online). None: ``observation.state`` and ``action`` (just ``action`` with
            ``state_tracks_action``). Training rewrites it in the canonical ``"feature:index"`` form.
        state_tracks_action: The tied layout: the SM is ``action`` and ``observation.state`` measures those
            dims, reaching each command within a control step (position servos); the sensed state is fed back
            as the SM point reached and a PD law (``execution.pd_*``) tracks the prediction.
        task_features: Features read at each episode's first frame as γ. None: ``observation.task_params`` if
            present, else an ``observation.environment_state`` not in the condition layout.
        sm_names: The SM dims' names (filled at training from the dataset's dim names).
        use_task_params: Condition on γ. None: when the dataset has it; True: require it; False: ignore it.
        use_images: Condition on the image features through a conv encoder (paper Sec. IV-B), which sees each
            episode's *first* camera frame; its embedding joins γ as an episode-level input.
        image_channels: Widths of the conv encoder's layers (3x3 conv + ReLU + 2x2 max-pool each; the paper:
            8, 16, 32, 64). Images need sides of at least 2^len(image_channels) pixels.
        image_embed_dim: Size of each image's embedding.
        image_encoder: Its spatial-softmax head and training augmentation (:class:`ImageEncoderConfig`).
        demo_duration_s: Duration of a demonstration (median over the training episodes, set when training
            from scratch starts). Execution runs the movement in this time.
        dataset_fps: The training dataset's frame rate (set when training starts).
        max_conditions: Most conditions (the user's plus an env's ``environment_state`` slots) one execution
            conditions on, besides the start and the feedback.
        conditions: Conditions given at deployment (``--policy.conditions``): a JSON list of dicts or a path
            to a .json/.yaml file, in the dataset's units and dim names, e.g. ``[{"t": 1.0, "gripper.pos": 0}]``
            (``t``: phase in [0, 1], or ``time_s``). Validated when the policy is built.
        execution: How the CNMP is executed (:class:`~lerobot_cnmp.execution.config.ExecutionConfig`).
        optimizer_lr: Adam learning rate (the paper: 1e-4 with batch 1; batched training tolerates more).
        optimizer_weight_decay: Adam weight decay.
        optimizer_grad_clip_norm: Gradient clipping used by ``lerobot-train``.
        optimizer_fused: Use torch's fused Adam kernel (same algorithm, fewer kernel launches).
        scheduler_decay_lr: Cosine-decay the learning rate from ``optimizer_lr`` to this over the run
            (``--steps``); None keeps it constant (the paper).
        normalization_mapping: LeRobot's normalizer modes; IDENTITY only (CNMP normalizes its SM and γ itself,
            with statistics saved in its weights).

    The paper's own settings: ``encoder_layers=(128, 128)``, ``decoder_layers=(128, 128)``,
    ``sampling.n_max_context=5``, ``sampling.m_max_targets=1``, ``sampling.context_in_targets=false``,
    ``sampling.partial_obs_prob=0``, ``optimizer_lr=1e-4``, ``scheduler_decay_lr=null`` and batch size 1.
    """

    # Network (paper: MLPs of 128 units).
    encoder_layers: tuple[int, ...] = (128, 128, 128)
    decoder_layers: tuple[int, ...] = (128, 128, 128)
    min_std: float = 0.01
    phase_frequencies: int = 0
    linear_task_term: bool | None = None
    n_experts: int = 1
    mixture: MixtureConfig = field(default_factory=MixtureConfig)

    # Training loss and its draws.
    sampling: SamplingConfig = field(default_factory=SamplingConfig)
    nll_beta: float = 0.0
    commanded_loss_weight: float = 1.0

    # The SM space (lerobot_cnmp.data.sm_spec) and task parameters γ.
    sm: tuple[str, ...] | None = None
    state_tracks_action: bool = False
    task_features: tuple[str, ...] | None = None
    sm_names: tuple[str, ...] | None = None
    use_task_params: bool | None = None

    # Images (paper Sec. IV-B): a conv encoder embeds each image feature; the embedding joins γ.
    use_images: bool = False
    image_channels: tuple[int, ...] = (8, 16, 32, 64)
    image_embed_dim: int = 32
    image_encoder: ImageEncoderConfig = field(default_factory=ImageEncoderConfig)

    # Execution (paper Sec. III): timing of the demonstrations, conditions, the executor's settings.
    demo_duration_s: float | None = None
    dataset_fps: float | None = None
    max_conditions: int = 8
    conditions: str | None = None
    execution: ExecutionConfig = field(default_factory=ExecutionConfig)

    # Optimizer.
    optimizer_lr: float = 1e-3
    optimizer_weight_decay: float = 0.0
    optimizer_grad_clip_norm: float = 10.0
    optimizer_fused: bool = True
    scheduler_decay_lr: float | None = 1e-5

    normalization_mapping: dict[str, NormalizationMode] = field(default_factory=identity_normalization)

    def __post_init__(self):
        super().__post_init__()
        for name, kind in (("mixture", MixtureConfig), ("sampling", SamplingConfig), ("execution", ExecutionConfig),
                           ("image_encoder", ImageEncoderConfig)):
            if isinstance(getattr(self, name), dict):  # CNMPConfig(mixture={...}) from Python
                setattr(self, name, kind(**getattr(self, name)))
        for name in ("encoder_layers", "decoder_layers", "image_channels"):
            setattr(self, name, tuple(int(w) for w in getattr(self, name)))
        for name in ("sm", "task_features", "sm_names"):
            if getattr(self, name) is not None:
                setattr(self, name, tuple(str(x) for x in getattr(self, name)))
        _check(self.encoder_layers and min(self.encoder_layers) >= 1,
               f"encoder_layers must be non-empty positive widths, got {self.encoder_layers}")
        _check(min(self.decoder_layers, default=1) >= 1, f"decoder_layers must be positive widths, got {self.decoder_layers}")
        _check(self.image_channels and min(self.image_channels) >= 1 and self.image_embed_dim >= 1,
               f"image_channels must be non-empty positive widths and image_embed_dim >= 1, got "
               f"{self.image_channels}, {self.image_embed_dim}")
        _check(_is_count(self.n_experts, 1), f"n_experts (the number of decoders K) must be an integer >= 1, got {self.n_experts}")
        self.n_experts = int(self.n_experts)
        self.mixture.resolve(self.n_experts, len(self.decoder_layers))
        _check(_is_count(self.phase_frequencies), f"phase_frequencies must be an integer >= 0, got {self.phase_frequencies}")
        _check(self.min_std > 0, f"min_std must be > 0, got {self.min_std}")
        _check(0.0 <= self.nll_beta <= 1.0, f"nll_beta must be in [0, 1], got {self.nll_beta}")
        _check(self.commanded_loss_weight > 0, f"commanded_loss_weight must be > 0, got {self.commanded_loss_weight}")
        _check(self.n_experts == 1 or (self.commanded_loss_weight == 1.0 and not self.linear_task_term), "commanded_loss"
               f"_weight applies to the single decoder, as linear_task_term does: use n_experts=1, got {self.n_experts}")
        for name in ("demo_duration_s", "dataset_fps"):
            _check(getattr(self, name) is None or getattr(self, name) > 0, f"{name} must be > 0, got {getattr(self, name)}")
        _check(_is_count(self.max_conditions), f"max_conditions must be an integer >= 0, got {self.max_conditions}")
        for kind in ("STATE", "ENV", "ACTION"):
            mode = self.normalization_mapping.get(kind, NormalizationMode.IDENTITY)
            _check(mode is NormalizationMode.IDENTITY, f"normalization_mapping[{kind!r}] = {mode}: CNMP normalizes "
                   "its SM and γ itself (statistics saved with its weights); LeRobot's normalizer must pass them "
                   "through (IDENTITY)")
        self._spec: SMSpec | None = None

    # ---- LeRobot interface -------------------------------------------------------------------------

    @property
    def observation_delta_indices(self) -> None:
        return None

    @property
    def action_delta_indices(self) -> None:
        """None: ``lerobot-train`` loads one frame per sample (for its episode id); the policy draws the
        sample's observations and queries from the whole episode (:mod:`lerobot_cnmp.data.bank`)."""
        return None

    @property
    def reward_delta_indices(self) -> None:
        return None

    def get_optimizer_preset(self) -> AdamConfig:
        return CNMPAdamConfig(
            lr=self.optimizer_lr,
            weight_decay=self.optimizer_weight_decay,
            grad_clip_norm=self.optimizer_grad_clip_norm,
            fused=self.optimizer_fused,
        )

    def get_scheduler_preset(self) -> CosineDecayWithWarmupSchedulerConfig | None:
        if self.scheduler_decay_lr is None:
            return None
        # A decay horizon longer than any run: LeRobot rescales it to the run's --steps.
        return CosineDecayWithWarmupSchedulerConfig(
            num_warmup_steps=0, num_decay_steps=10**9, peak_lr=self.optimizer_lr, decay_lr=self.scheduler_decay_lr
        )

    def resolve_sm(self, ds_features: dict[str, dict] | None = None) -> SMSpec:
        """Resolve ``sm`` / ``task_features`` against a dataset's features (names and shapes; training) or,
        without one, against this config's own input/output features, and store the canonical form."""
        spec = sm_spec.resolve(self.sm, self.task_features, self.state_tracks_action,
                               ds_features if ds_features is not None else sm_spec.features_from_policy(self),
                               self.use_task_params)
        self.sm = tuple(d.key for d in spec.dims)
        self.task_features = tuple(k for k, _ in spec.task_features)
        if ds_features is not None or self.sm_names is None or len(self.sm_names) != spec.size:
            self.sm_names = tuple(spec.names)
        self._spec = spec
        return spec

    @property
    def spec(self) -> SMSpec:
        if getattr(self, "_spec", None) is None:
            self.resolve_sm()
        return self._spec

    def validate_features(self) -> None:
        if self.action_feature is None:
            raise ValueError(f"CNMP needs the output feature {ACTION!r} (the commanded SM); none was given")
        if len(self.action_feature.shape) != 1:
            raise ValueError(f"CNMP needs a flat {ACTION!r} vector, got shape {self.action_feature.shape}")
        spec = self.spec
        if spec.action_dim != self.action_feature.shape[0]:
            raise ValueError(f"this CNMP's SM commands {spec.action_dim} {ACTION!r} dims but the env/dataset's "
                             f"{ACTION!r} has {self.action_feature.shape[0]}")
        for feature, pairs in spec.sensed_features.items():
            ft = self.input_features.get(feature)
            if ft is None:
                raise ValueError(f"the SM senses {feature!r} but the inputs have no such feature; inputs: "
                                 f"{sorted(self.input_features)}")
            if max(k for _, k in pairs) >= ft.shape[0]:
                raise ValueError(f"the SM reads dim {max(k for _, k in pairs)} of {feature!r}, which has shape {tuple(ft.shape)}")
        env = self.env_state_feature
        if self.condition_feature and env.shape[-1] % slot_size(self.sm_dim) != 0:
            raise ValueError(
                f"{OBS_ENV_STATE!r} has {env.shape[-1]} values, not a multiple of 2 + 2 x {self.sm_dim} (the CNMP "
                f"condition layout of lerobot_cnmp.execution.conditions); declare it as task parameters "
                f"(--policy.task_features='[{OBS_ENV_STATE}]') if it holds task data"
            )
        if self.env_condition_slots > self.max_conditions:
            raise ValueError(f"{OBS_ENV_STATE!r} carries {self.env_condition_slots} condition slots, more than "
                             f"max_conditions={self.max_conditions}")
        for name in ("feedback_dims", "tracking_dims", "pd_dims"):
            dims = getattr(self.execution, name)
            if dims is not None and (not dims or min(dims) < 0 or max(dims) >= self.sm_dim):
                raise ValueError(f"{name} {dims} outside the SM dimensions 0..{self.sm_dim - 1}")
        for name in ("feedback_dims", "tracking_dims"):
            dims = getattr(self.execution, name)
            if dims is not None and not set(dims) <= set(spec.sensed):
                raise ValueError(f"{name} {dims} must be sensed SM dims {spec.sensed} (names: "
                                 f"{[self.sm_names[i] for i in spec.sensed] if self.sm_names else '?'})")
        if self.use_images and not self.image_features:
            raise ValueError(
                f"use_images=True but the dataset/env has no image feature; available inputs: {sorted(self.input_features)}"
            )
        for key in self.image_keys:
            shape = tuple(self.input_features[key].shape)
            pools = len(self.image_channels) - int(self.image_encoder.keypoints)
            side = self.image_encoder.downsample * 2 ** pools
            if len(shape) != 3 or min(shape[1:]) < side:
                raise ValueError(
                    f"image feature {key!r} has shape {shape}; the conv encoder needs [channels, height, width] "
                    f"with sides of at least {side} pixels ({pools} 2x2 poolings after a downsample by "
                    f"{self.image_encoder.downsample})")

    # ---- Derived sizes -------------------------------------------------------------------------------

    @property
    def sm_dim(self) -> int:
        return self.spec.size

    @property
    def task_dim(self) -> int:
        return self.spec.task_dim

    @property
    def image_keys(self) -> list[str]:
        """The image features the CNMP conditions on (sorted). Each episode's *first* camera frame is the one
        the conv encoder sees, in training and in execution."""
        if self.use_images is not True:
            return []
        return sorted(self.image_features)

    @property
    def episode_dim(self) -> int:
        """Size of the episode-level input of E and Q: γ plus one embedding per image feature."""
        return self.task_dim + len(self.image_keys) * self.image_embed_dim

    @property
    def condition_feature(self) -> bool:
        """Whether ``observation.environment_state`` carries condition slots (not γ, not SM)."""
        env = self.env_state_feature
        if env is None:
            return False
        used = {d.feature for d in self.spec.dims} | {k for k, _ in self.spec.task_features}
        return OBS_ENV_STATE not in used

    @property
    def env_condition_slots(self) -> int:
        """The condition slots of ``observation.environment_state`` (our envs' layout); 0 without them."""
        return self.env_state_feature.shape[-1] // slot_size(self.sm_dim) if self.condition_feature else 0

    @property
    def n_action_steps(self) -> int:
        """Actions per ``predict_action_chunk`` (``execution.n_action_steps``), where LeRobot's callers look."""
        return self.execution.n_action_steps


decode_with_upgrade(CNMPConfig)  # configs of older layouts load (lerobot_cnmp.policy.legacy)

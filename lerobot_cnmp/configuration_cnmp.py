"""Configuration of the CNMP policy (``--policy.type=cnmp``).

Defaults follow the paper (Seker et al., RSS 2019, Sec. III and IV-A) where it gives a value: MLP encoder
and query (decoder) networks of 128 units, mean aggregation, Gaussian output with a softplus σ, NLL loss,
1..n_max observations per training sample. Where the original trains with batch 1 and one query per
step, we batch episodes and queries (``batch_size`` of ``lerobot-train``, ``m_max_targets``) and raise
the learning rate accordingly; every such choice is a field here.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from lerobot.configs import NormalizationMode, PreTrainedConfig
from lerobot.optim import AdamConfig, CosineDecayWithWarmupSchedulerConfig, OptimizerConfig
from lerobot.utils.constants import ACTION, OBS_ENV_STATE

from lerobot_cnmp import sm_spec
from lerobot_cnmp.conditions import slot_size
from lerobot_cnmp.sm_spec import TASK_PARAMS, SMSpec  # noqa: F401  (TASK_PARAMS: re-exported)


@OptimizerConfig.register_subclass("cnmp_adam")
@dataclass
class CNMPAdamConfig(AdamConfig):
    """LeRobot's Adam with torch's ``fused`` switch (``lerobot-train`` saves it as ``"type": "cnmp_adam"``)."""

    fused: bool = True


@PreTrainedConfig.register_subclass("cnmp")
@dataclass
class CNMPConfig(PreTrainedConfig):
    """Conditional Neural Movement Primitive.

    The sensorimotor (SM) trajectory the CNMP learns is a set of dataset dims over phase (see
    :mod:`lerobot_cnmp.sm_spec`): by default ``observation.state`` ⊕ ``action`` (sensed and commanded dims),
    frame ``k`` of an episode at phase ``t`` = its time since the episode's start / the episode's duration.
    Execution conditions on the sensed dims of the live observation and outputs the predicted ``action``.
    Conditions (via-points, goals, in SM units) reach the policy through ``observation.environment_state``
    in the layout of :mod:`lerobot_cnmp.conditions` (when the dataset's ``environment_state`` has that
    layout); task parameters γ are features read at an episode's first frame.

    Args:
        sm: The SM declaration: entries ``"feature"`` (all its dims) or ``"feature:dim"`` (a dim by the
            dataset's dim name or index), in order; every ``action`` dim must be included (execution outputs
            them); dims of other features are *sensed* (fed back online). None: ``observation.state`` and
            ``action`` (just ``action`` with ``state_tracks_action``). Training rewrites it in the canonical
            ``"feature:index"`` form (saved in the checkpoint) and fills ``sm_names``.
        state_tracks_action: The tied layout: the SM is ``action`` and ``observation.state`` measures those
            same dims, reaching each command within a control step (our sims' position servos). The sensed
            state is then fed back as the SM point the previous command reached and a PD law (``pd_*``) tracks
            the prediction. False (default): nothing assumes the state equals a command.
        task_features: Features read at each episode's first frame as task parameters γ (numeric vectors).
            None: ``observation.task_params`` if present, else an ``observation.environment_state`` that is not
            in the CNMP condition layout (e.g. an object's position). Resolved at training.
        sm_names: The SM dims' names (filled at training from the dataset's dim names).
        encoder_layers: Widths of the encoder E's layers; the last is the size of the representation r.
        decoder_layers: Hidden widths of the query network Q (its output layer, 2 x SM dim, is added).
        phase_frequencies: K > 0 adds sin/cos(k·π·t), k = 1..K, to the phase input of E and Q (Fourier
            features, for sharper timing); 0 feeds the raw phase t only, as in the paper.
        min_std: Floor of the predicted σ (normalized units): σ = min_std + softplus(raw).
        n_max_context: Most observations sampled from a demonstration per training sample (n ~ U{1..n_max}).
        m_max_targets: Most query points per training sample (m ~ U{1..m_max}); the paper uses 1.
        context_in_targets: Also use the sampled observations as queries (as the CNPs of Garnelo et al. do),
            which trains the model to pass through its conditions. The paper draws queries independently.
        partial_obs_prob: Probability that a sampled observation constrains only a random non-empty subset
            of the SM dimensions, so the model can be conditioned on any subset of dimensions.
        sensed_obs_prob: Probability that a sampled observation (not already a partial one) constrains exactly
            the sensed dims, as execution's feedback does (joint layout only; the tied layout senses every dim).
        feedback_draw_weight: Weight w of *execution-shaped* draws in the loss (joint layout; 0: none, the
            paper). Execution conditions on the sensed dims at the first step (t = 0, with
            ``condition_on_start``) and at the current phase τ, and commands the action predicted at τ. A random
            draw rarely has that shape: its query at τ shares the aggregated representation with observations
            at other phases. With w > 0 each step also draws, per draw, exactly that context (the sensed dims at
            the episode's first frame and at a uniform frame j) with queries at j, j + 1 and ``m_max_targets``
            uniform frames; loss = (1 - w) NLL(random draws) + w NLL(execution-shaped draws). Use it when the
            action depends sharply on the sensed state (a reactive demonstrator, delta actions).
        nll_beta: β of the β-NLL (Seitzer et al., ICLR 2022): each SM dim's NLL term is weighted by
            stop_gradient(σ^(2β)). 0 is the paper's NLL. With the plain NLL the mean's gradient is scaled by
            1/σ², so a dim the model finds hard early (large σ) stops being fitted and stays blurred; β = 0.5
            keeps fitting it. Training only: prediction and execution are unchanged.
        draws_per_sample: Independent (observations, queries) draws made from each sampled episode per step:
            the loss sees batch_size x draws_per_sample draws. Every draw takes its frames from the whole
            episode (:mod:`lerobot_cnmp.bank`), so this only multiplies the training signal per loaded sample
            (``lerobot-train`` loads one frame per sample, for its episode id).
        use_task_params: Condition on γ (``task_features``). None: use it when the dataset has it. True:
            require it (a dataset without it is rejected). False: ignore it.
        use_images: Condition on the image features (``observation.images.*``) through a conv encoder, as the
            paper's Sec. IV-B does with a top-down mask of the room. Off unless True (a dataset's cameras are
            then required). The encoder sees each episode's *first* camera frame, in training (read once per
            episode from the dataset) and in execution (the frame at the first step after ``reset``); its
            embedding joins γ as an episode-level input.
        image_channels: Widths of the conv encoder's layers (3x3 conv + ReLU + 2x2 max-pool each; the
            paper: 8, 16, 32, 64). Images need sides of at least 2^len(image_channels) pixels.
        image_embed_dim: Size of each image's embedding (a linear layer after the convolutions).
        demo_duration_s: Duration of a demonstration in seconds (the median over the training episodes,
            from their timestamps; set when training from scratch starts, kept when fine-tuning, like the
            normalization). Execution runs the movement in this time.
        dataset_fps: The training dataset's frame rate (set when training starts).
        control_fps: The rate at which execution is called (``select_action`` per second). None: the
            dataset's fps. The phase advances by 1 / (control_fps x demo_duration_s) per step, so a robot
            controlled at another rate than the recording runs the movement in the same time.
        online_feedback: The paper's execution loop: every control step, condition on the current sensed SM
            (``feedback_dims`` of ``observation.state``) besides the episode's conditions, track the
            prediction with the PD law below, and stop the phase while the tracking error is large.
            False: replay the trajectory generated at t = 0 (the open-loop baseline; the phase always advances).
        feedback_dims: SM dimensions fed back (conditioned on) and, unless ``tracking_dims`` says otherwise,
            used for the tracking error; None: all.
        tracking_dims: SM dimensions of the tracking error that stops the phase; None: ``feedback_dims``.
            E.g. feed force readings back (they carry the information) but stop the phase on position only.
        condition_on_start: Keep the state sensed at the first step after ``reset()`` as a condition at
            t = 0 for the whole episode (the start of the movement, as in the paper's Fig. 2).
        phase_step: Phase advance per control step; None: 1 / (control_fps x demo_duration_s), the
            demonstrations' pace in seconds.
        phase_stop_threshold: The phase does not advance while the tracking error (max over the fed-back
            dims of |sensed SM - SM commanded at the previous step|, in action standard deviations) is above
            this. None: never stop.
        pd_kp, pd_kd: PD law on the position target (tied layout only; the joint layout outputs the
            predicted action itself): action = s + kp·e + kd·(e - e_prev), e = SM(τ) - s.
            kp < 1 approaches the prediction gradually (a first-order lag), which keeps the accelerations,
            and the inertial loads a wrist F/T sensor reads, close to the demonstrations' when the prediction
            jumps after re-conditioning.
            kp = 1, kd = 0 commands the predicted SM itself.
        pd_dims: SM dimensions the PD law applies to; the others are commanded the prediction SM(τ) itself
            (e.g. a gripper, whose command is a set point, not a position to approach). None: all.
        sigma_scaled_gains: Scale kp per dim by sigma_ref / σ (the predicted σ, normalized units): softer
            where the demonstrations vary more (the paper's compliance proposal), clipped to [kp_min, kp_max].
        numpy_execution: On CPU, execute (``select_action``, ``predict_action_chunk``) with a numpy copy of
            the network (``NumpyCNMP``: same weights and equations, 2-4x less time per control step than
            torch's per-op dispatch). False: run the torch model.
        optimizer_lr: Adam learning rate (the paper: 1e-4 with batch 1; batched training tolerates more).
        optimizer_grad_clip_norm: Gradient clipping used by ``lerobot-train``.
        optimizer_fused: Use torch's fused Adam kernel (one kernel for all parameters instead of ~10 small
            ops per tensor: a training step at batch 1 on CPU drops by ~0.7 ms). Same algorithm.
        scheduler_decay_lr: Cosine-decay the learning rate from ``optimizer_lr`` to this value over the whole
            run (``--steps``); None keeps it constant (the paper).

    The paper's own settings, for reproduction: ``encoder_layers=(128, 128)``, ``decoder_layers=(128, 128)``,
    ``n_max_context=5``, ``m_max_targets=1``, ``context_in_targets=false``, ``partial_obs_prob=0``,
    ``optimizer_lr=1e-4``, ``scheduler_decay_lr=null`` and batch size 1.
    """

    # Network (paper: MLPs of 128 units).
    encoder_layers: tuple[int, ...] = (128, 128, 128)
    decoder_layers: tuple[int, ...] = (128, 128, 128)
    min_std: float = 0.01
    phase_frequencies: int = 0

    # Training-step sampling.
    n_max_context: int = 8
    m_max_targets: int = 16
    context_in_targets: bool = True
    partial_obs_prob: float = 0.25
    sensed_obs_prob: float = 0.5
    feedback_draw_weight: float = 0.0
    draws_per_sample: int = 1
    nll_beta: float = 0.0

    # The SM space (lerobot_cnmp.sm_spec) and task parameters γ.
    sm: tuple[str, ...] | None = None
    state_tracks_action: bool = False
    task_features: tuple[str, ...] | None = None
    sm_names: tuple[str, ...] | None = None
    use_task_params: bool | None = None

    # Images (paper Sec. IV-B): a conv encoder embeds each image feature; the embedding joins γ.
    use_images: bool = False
    image_channels: tuple[int, ...] = (8, 16, 32, 64)
    image_embed_dim: int = 32

    # Execution (paper Sec. III: online conditioning, PD tracking, phase stopping).
    demo_duration_s: float | None = None
    dataset_fps: float | None = None
    control_fps: float | None = None
    online_feedback: bool = True
    feedback_dims: tuple[int, ...] | None = None
    tracking_dims: tuple[int, ...] | None = None
    pd_dims: tuple[int, ...] | None = None
    condition_on_start: bool = True
    phase_step: float | None = None
    phase_stop_threshold: float | None = 0.15
    pd_kp: float = 1.0
    pd_kd: float = 0.0
    sigma_scaled_gains: bool = False
    sigma_ref: float = 0.05
    kp_min: float = 0.2
    kp_max: float = 1.0
    numpy_execution: bool = True

    # Optimizer.
    optimizer_lr: float = 1e-3
    optimizer_weight_decay: float = 0.0
    optimizer_grad_clip_norm: float = 10.0
    optimizer_fused: bool = True
    scheduler_decay_lr: float | None = 1e-5

    normalization_mapping: dict[str, NormalizationMode] = field(
        default_factory=lambda: {
            # CNMP normalizes its SM and γ itself, with statistics saved in its weights (SMNormalizer in
            # modeling_cnmp): LeRobot's normalizer steps pass these features through, so the statistics
            # lerobot-train gives them when fine-tuning (--policy.path) cannot change CNMP's scaling.
            "VISUAL": NormalizationMode.IDENTITY,
            "STATE": NormalizationMode.IDENTITY,
            "ENV": NormalizationMode.IDENTITY,
            "ACTION": NormalizationMode.IDENTITY,
        }
    )

    def __post_init__(self):
        super().__post_init__()
        self.encoder_layers = tuple(int(w) for w in self.encoder_layers)
        self.decoder_layers = tuple(int(w) for w in self.decoder_layers)
        self.image_channels = tuple(int(w) for w in self.image_channels)
        if not self.image_channels or min(self.image_channels) < 1 or self.image_embed_dim < 1:
            raise ValueError(
                f"image_channels must be non-empty positive widths and image_embed_dim >= 1, got "
                f"{self.image_channels}, {self.image_embed_dim}"
            )
        if not self.encoder_layers or min(self.encoder_layers) < 1:
            raise ValueError(f"encoder_layers must be non-empty positive widths, got {self.encoder_layers}")
        if min(self.decoder_layers, default=1) < 1:
            raise ValueError(f"decoder_layers must be positive widths, got {self.decoder_layers}")
        if self.phase_frequencies < 0:
            raise ValueError(f"phase_frequencies must be >= 0, got {self.phase_frequencies}")
        if not self.min_std > 0:
            raise ValueError(f"min_std must be > 0, got {self.min_std}")
        if self.n_max_context < 1 or self.m_max_targets < 1:
            raise ValueError(
                f"n_max_context and m_max_targets must be >= 1, got {self.n_max_context}, {self.m_max_targets}"
            )
        if not 0.0 <= self.sensed_obs_prob <= 1.0:
            raise ValueError(f"sensed_obs_prob must be in [0, 1], got {self.sensed_obs_prob}")
        if not 0.0 <= self.partial_obs_prob <= 1.0:
            raise ValueError(f"partial_obs_prob must be in [0, 1], got {self.partial_obs_prob}")
        if self.draws_per_sample < 1:
            raise ValueError(f"draws_per_sample must be >= 1, got {self.draws_per_sample}")
        if not 0.0 <= self.feedback_draw_weight <= 1.0:
            raise ValueError(f"feedback_draw_weight must be in [0, 1], got {self.feedback_draw_weight}")
        if not 0.0 <= self.nll_beta <= 1.0:
            raise ValueError(f"nll_beta must be in [0, 1], got {self.nll_beta}")
        if self.demo_duration_s is not None and not self.demo_duration_s > 0:
            raise ValueError(f"demo_duration_s must be > 0, got {self.demo_duration_s}")
        for name in ("dataset_fps", "control_fps"):
            if getattr(self, name) is not None and not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        for name in ("sm", "task_features", "sm_names"):
            if getattr(self, name) is not None:
                setattr(self, name, tuple(str(x) for x in getattr(self, name)))
        if self.phase_step is not None and not 0.0 < self.phase_step <= 1.0:
            raise ValueError(f"phase_step must be in (0, 1], got {self.phase_step}")
        if self.phase_stop_threshold is not None and not self.phase_stop_threshold > 0:
            raise ValueError(f"phase_stop_threshold must be > 0 (or None to never stop), got {self.phase_stop_threshold}")
        if not self.pd_kp > 0 or self.pd_kd < 0:
            raise ValueError(f"PD gains need pd_kp > 0 and pd_kd >= 0, got pd_kp={self.pd_kp}, pd_kd={self.pd_kd}")
        if not 0 < self.kp_min <= self.kp_max or not self.sigma_ref > 0:
            raise ValueError(
                f"need 0 < kp_min <= kp_max and sigma_ref > 0, got kp_min={self.kp_min}, kp_max={self.kp_max}, "
                f"sigma_ref={self.sigma_ref}"
            )
        for name in ("feedback_dims", "tracking_dims", "pd_dims"):
            if getattr(self, name) is not None:
                setattr(self, name, tuple(int(d) for d in getattr(self, name)))
                if not getattr(self, name):
                    raise ValueError(f"{name} must name at least one SM dimension (or be None)")
        for kind in ("STATE", "ENV", "ACTION"):
            mode = self.normalization_mapping.get(kind, NormalizationMode.IDENTITY)
            if mode is not NormalizationMode.IDENTITY:
                raise ValueError(
                    f"normalization_mapping[{kind!r}] = {mode}: CNMP normalizes its SM and γ itself (statistics "
                    "saved with its weights); LeRobot's normalizer must pass them through (IDENTITY)"
                )
        self._spec: SMSpec | None = None

    # ---- LeRobot interface -------------------------------------------------------------------------

    @property
    def observation_delta_indices(self) -> None:
        return None

    @property
    def action_delta_indices(self) -> None:
        """None: ``lerobot-train`` loads one frame per sample (for its episode id); the policy draws the
        sample's observations and queries from the whole episode (:mod:`lerobot_cnmp.bank`)."""
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
                f"condition layout of lerobot_cnmp.conditions); declare it as task parameters "
                f"(--policy.task_features='[{OBS_ENV_STATE}]') if it holds task data"
            )
        for name in ("feedback_dims", "tracking_dims", "pd_dims"):
            dims = getattr(self, name)
            if dims is not None and (not dims or min(dims) < 0 or max(dims) >= self.sm_dim):
                raise ValueError(f"{name} {dims} outside the SM dimensions 0..{self.sm_dim - 1}")
        for name in ("feedback_dims", "tracking_dims"):
            dims = getattr(self, name)
            if dims is not None and not set(dims) <= set(spec.sensed):
                raise ValueError(f"{name} {dims} must be sensed SM dims {spec.sensed} (names: "
                                 f"{[self.sm_names[i] for i in spec.sensed] if self.sm_names else '?'})")
        if self.use_images and not self.image_features:
            raise ValueError(
                f"use_images=True but the dataset/env has no image feature; available inputs: {sorted(self.input_features)}"
            )
        for key in self.image_keys:
            shape = tuple(self.input_features[key].shape)
            side = 2 ** len(self.image_channels)
            if len(shape) != 3 or min(shape[1:]) < side:
                raise ValueError(
                    f"image feature {key!r} has shape {shape}; the conv encoder needs [channels, height, width] "
                    f"with sides of at least {side} pixels ({len(self.image_channels)} 2x2 poolings)"
                )

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
    def max_conditions(self) -> int:
        return self.env_state_feature.shape[-1] // slot_size(self.sm_dim) if self.condition_feature else 0

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

from lerobot_cnmp.data import sm_spec
from lerobot_cnmp.execution.conditions import slot_size
from lerobot_cnmp.execution.config import LEGACY_EXECUTION_FIELDS, ExecutionConfig, apply_legacy_execution
from lerobot_cnmp.data.sm_spec import TASK_PARAMS, SMSpec  # noqa: F401  (TASK_PARAMS: re-exported)


@OptimizerConfig.register_subclass("cnmp_adam")
@dataclass
class CNMPAdamConfig(AdamConfig):
    """LeRobot's Adam with torch's ``fused`` switch (``lerobot-train`` saves it as ``"type": "cnmp_adam"``)."""

    fused: bool = True


GATE_COMMIT = ("always", "where_decided", "redundant")  # CNMPConfig.gate_commit (CNMP.mixture_loss)
MIXTURE_NLL = ("assigned", "likelihood", "cnep")  # CNMPConfig.mixture_nll (CNMP.mixture_loss)


def identity_normalization() -> dict[str, NormalizationMode]:
    """LeRobot's normalizer steps pass every feature type through unchanged."""
    return {kind: NormalizationMode.IDENTITY for kind in ("VISUAL", "STATE", "ENV", "ACTION")}


@PreTrainedConfig.register_subclass("cnmp")
@dataclass
class CNMPConfig(PreTrainedConfig):
    """Conditional Neural Movement Primitive.

    The sensorimotor (SM) trajectory the CNMP learns is a set of dataset dims over phase (see
    :mod:`lerobot_cnmp.data.sm_spec`): by default ``observation.state`` ⊕ ``action`` (sensed and commanded dims),
    frame ``k`` of an episode at phase ``t`` = its time since the episode's start / the episode's duration.
    Execution conditions on the sensed dims of the live observation and outputs the predicted ``action``.
    Conditions (via-points, goals, in SM units) reach the policy through ``observation.environment_state``
    in the layout of :mod:`lerobot_cnmp.execution.conditions` (when the dataset's ``environment_state`` has that
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
        n_experts: K, the number of query networks (experts). 1 (default): the paper's CNMP, one Gaussian
            decoder. K > 1: CNEP's mixture decoder (Yildirim & Ugur, arXiv 2402.08424): K decoders over the
            same representation r and a gate π(r) = softmax(W r + b) over them, trained with
            Σ_k π_k NLL_k + the two entropy terms below (``CNMP.mixture_loss``). Use it when the
            demonstrations have modes the conditions do not decide (a single decoder averages them).
        mixture_nll: How the experts' NLLs combine through the gate (``CNMP.mixture_loss``): ``"assigned"``
            (default: each episode's expert is decided by the mixture on the empty context, i.e. by the demos'
            clusters, and every context drawn from it trains that expert and the gate toward it: a context that
            decides the mode commits, one shared by modes gets their shares; it met the sine, weights (6 seeds
            of 6) and shared-obstacle bars, not the training-cost one: a decoder pass more per step, and on data
            without modes the clusters are arbitrary), ``"likelihood"`` (the mixture likelihood
            -log Σ_k π_k Π_q N_k of each context: π a posterior, but where the context decides the mode one
            expert may cover two modes while another idles and π splits between them: weights bars on 1 seed
            of 6; meets the training-cost bar) or ``"cnep"`` (CNEP's expected NLL Σ_k π_k NLL_k: the gate
            learns a hard choice everywhere, and an ambiguous context gets one expert that averages its modes;
            on the sine benchmark 0.074 against 0.022 for the likelihood). Figures: README "Mixture decoder".
        assignment_draws: With ``mixture_nll="assigned"``, which queries decide an episode's expert. 0
            (default): each draw's own queries, the empty-context pass running on every draw. p >= 1: the
            queries of the episode's first p of its ``draws_per_sample`` draws, the expert then shared by all
            its draws and the empty-context rows (those p only) run in the context's decoder pass (a cheaper
            step: with 8 draws and ``shared_decoder_layers`` 3, about half the weights task's training time at
            the same bars; figures and the cost bar: README "Mixture decoder").
        unconditional_nll_coef: With ``mixture_nll="assigned"``, the weight c of the unconditional mixture's
            NLL (the experts and gate on the empty context, which decide each episode's expert) in the loss:
            c · NLL⁰_mix + Σ_k ρ_k (NLL_k - log π_k). 1 (default): the two count alike. The unconditional
            mixture trains the same decoder (through the shared trunk) on r = 0, a second task beside the
            conditional one; a smaller c leaves it the clustering and the decoder to the contexts (README
            "Mixture decoder": with 0.25, ``assignment_draws`` 1 and ``shared_decoder_layers`` 3 the mixture
            meets all four bars there, the training-cost one in 1.35x-1.54x the single decoder's time on 5
            seeds; with 1, on 1 seed of 5).
        gate_entropy_coef: Weight of the per-episode gate entropy mean_b H(π_b) / log K, *added* to the loss:
            each context should commit to one expert. CNEP's 7.553, relative to its NLL weight, is 0.62; with
            the likelihood that collapses ambiguous contexts onto one averaging expert (weights task: 0.89 on
            one expert before the grasp), 0 leaves informative contexts uncommitted (after the lift max π
            0.54-0.85): 0.2 is between (README "Mixture decoder").
        gate_commit: Which contexts the gate-entropy term asks to commit (``CNMP.mixture_loss``): ``"always"``
            (every context, CNEP's) or ``"where_decided"`` (each episode's term weighted by 1 - H(π)/log K,
            without gradient: a context the gate spreads over modes is left a posterior, one it leans on is
            pushed to one expert) or ``"redundant"`` (instead of the entropy, the gate's mass split between
            experts whose predictions for the context agree within their σ: a context whose experts predict
            different modes is left a posterior, one whose experts agree is committed to one of them).
            README "Mixture decoder" has the weights-task figures of all three with the likelihood; none meets
            both weights bars there (``"redundant"``: 0 % of masses above 0.9 after the lift).
        batch_entropy_coef: Weight of the batch's gate entropy H(mean_b π_b) / log K, *subtracted*: over a
            batch every expert should be used (no expert left untrained). CNEP's 10.672, relative: 0.88.
        shared_decoder_layers: With K > 1, how many of ``decoder_layers``' hidden layers the experts share (a
            trunk over [t_q, γ, r]; each expert keeps the layers after it and its own output layer). None (the
            default): all hidden layers but the last for K > 1 (2 of the default 3), 0 for K = 1 (a positive
            value with K = 1 is an error). 0: K whole query networks, CNEP's. A trunk trains on every episode
            instead of each expert on its share and costs about one network's work instead of K. With it (2
            of 3) the mixture met the sine (0.004 on seeds 0 and 1, against 0.022 and 0.052 with 0),
            training-cost (1.66x; with 0 not reached) and shared-obstacle bars of README "Mixture decoder",
            and the weights-gate bars on 1 training seed of 6 (with the likelihood; figures of 2026-12-04).
        expert_selection: Execution with K > 1 (:class:`lerobot_cnmp.execution.modes.ModeSelector`): at an episode's
            first step, follow the most probable expert (``"most_probable"``) or one drawn from π
            (``"sample"``, e.g. to spread choices over equally likely modes).
        mode_switch_margin: Execution with K > 1: the followed expert c is kept while no expert is more
            probable than it by more than this margin after re-conditioning on the fed-back SM; when
            π_k* - π_c > margin (k* = argmax π), the policy switches to k* (a hysteresis: small flickers of π
            do not make it jump between modes). In [0, 1).
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
        feedback_draw_queries: The number of uniform frames queried by an execution-shaped draw besides j and
            j + 1; None: ``m_max_targets``. 0 trains exactly execution's two queries (the action and the next
            sensed state given the current one), the objective of behaviour cloning on (τ, state, γ); with many
            uniform queries, the action at j is one term among them.
        nll_beta: β of the β-NLL (Seitzer et al., ICLR 2022): each SM dim's NLL term is weighted by
            stop_gradient(σ^(2β)). 0 is the paper's NLL. With the plain NLL the mean's gradient is scaled by
            1/σ², so a dim the model finds hard early (large σ) stops being fitted and stays blurred; β = 0.5
            keeps fitting it. Training only: prediction and execution are unchanged.
        commanded_loss_weight: The weight of each commanded (action) dim's NLL term, the sensed dims' being 1.
            With an SM of many sensed dims and a few action dims (e.g. 14 state dims and a 4-dim delta action)
            the loss is mostly the state's, while execution outputs only the action; > 1 shifts the fit to
            the action. Training only; a single decoder (n_experts = 1); no effect in the tied layout (every dim
            is both).
        draws_per_sample: Independent (observations, queries) draws made from each sampled episode per step:
            the loss sees batch_size x draws_per_sample draws. Every draw takes its frames from the whole
            episode (:mod:`lerobot_cnmp.data.bank`), so this only multiplies the training signal per loaded sample
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
        max_conditions: The condition capacity: most conditions (the user's plus those an env writes in
            ``observation.environment_state`` slots) one execution conditions on, besides the start and the
            feedback. A model setting, independent of the dataset: a checkpoint trained on a robot's dataset
            without condition slots still takes goals from the user.
        conditions: Conditions given at deployment (``--policy.conditions``): a JSON list of dicts, or a path to
            a .json/.yaml file, in the dataset's units and dim names, e.g.
            ``[{"t": 1.0, "shoulder_pan.pos": 12.5, "gripper.pos": 0}]`` (``t``: phase in [0, 1], or ``time_s``:
            seconds from the movement's start). Validated when the policy is built; see
            :func:`lerobot_cnmp.execution.executor.parse_conditions`. From Python: ``policy.set_conditions(...)``.
        execution: How the CNMP is executed (phase clock, feedback, phase stopping, PD, chunks):
            :class:`lerobot_cnmp.execution.executor.ExecutionConfig`, ``--policy.execution.<field>``. Configs and
            checkpoints with these fields at the top level (before ``execution`` existed) load unchanged.
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

    # Mixture decoder (CNEP): K experts and a gate; K = 1 is the plain CNMP.
    n_experts: int = 1
    gate_entropy_coef: float = 0.2
    batch_entropy_coef: float = 0.88
    mixture_nll: str = "assigned"
    assignment_draws: int = 0
    unconditional_nll_coef: float = 1.0
    gate_commit: str = "always"
    shared_decoder_layers: int | None = None
    expert_selection: str = "most_probable"
    mode_switch_margin: float = 0.3

    # Training-step sampling.
    n_max_context: int = 8
    m_max_targets: int = 16
    context_in_targets: bool = True
    partial_obs_prob: float = 0.25
    sensed_obs_prob: float = 0.5
    feedback_draw_weight: float = 0.0
    feedback_draw_queries: int | None = None
    draws_per_sample: int = 1
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

    # Execution (paper Sec. III): timing of the demonstrations, conditions, the executor's own settings.
    demo_duration_s: float | None = None
    dataset_fps: float | None = None
    max_conditions: int = 8
    conditions: str | None = None
    execution: ExecutionConfig = field(default_factory=ExecutionConfig)

    # Deprecated aliases of ``execution.<same name>``: the flat layout of checkpoints and configs written before
    # the executor had its own config. Given (a config.json, ``--policy.pd_kp=...``, ``CNMPConfig(pd_kp=...)``),
    # they move into ``execution`` and are reset to None; see ``executor.apply_legacy_execution``.
    control_fps: float | None = None
    phase_step: float | None = None
    online_feedback: bool | None = None
    condition_on_start: bool | None = None
    feedback_dims: tuple[int, ...] | None = None
    tracking_dims: tuple[int, ...] | None = None
    phase_stop_threshold: float | None = None
    pd_kp: float | None = None
    pd_kd: float | None = None
    pd_dims: tuple[int, ...] | None = None
    sigma_scaled_gains: bool | None = None
    sigma_ref: float | None = None
    kp_min: float | None = None
    kp_max: float | None = None
    numpy_execution: bool | None = None

    # Optimizer.
    optimizer_lr: float = 1e-3
    optimizer_weight_decay: float = 0.0
    optimizer_grad_clip_norm: float = 10.0
    optimizer_fused: bool = True
    scheduler_decay_lr: float | None = 1e-5

    # CNMP normalizes its SM and γ itself, with statistics saved in its weights (SMNormalizer in
    # modeling_cnmp): LeRobot's normalizer steps pass these features through, so the statistics
    # lerobot-train gives them when fine-tuning (--policy.path) cannot change CNMP's scaling.
    normalization_mapping: dict[str, NormalizationMode] = field(default_factory=identity_normalization)

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
        if isinstance(self.n_experts, bool) or not float(self.n_experts).is_integer() or self.n_experts < 1:
            raise ValueError(f"n_experts (the number of decoders K) must be an integer >= 1, got {self.n_experts}")
        self.n_experts = int(self.n_experts)
        if self.gate_entropy_coef < 0 or self.batch_entropy_coef < 0:
            raise ValueError(f"gate_entropy_coef and batch_entropy_coef must be >= 0, got {self.gate_entropy_coef}, "
                             f"{self.batch_entropy_coef}")
        if self.gate_commit not in GATE_COMMIT:
            raise ValueError(f"gate_commit must be one of {GATE_COMMIT}, got {self.gate_commit!r}")
        if self.shared_decoder_layers is None:  # the default: all hidden layers but the last for a mixture
            self.shared_decoder_layers = max(len(self.decoder_layers) - 1, 0) if self.n_experts > 1 else 0
        if not 0 <= self.shared_decoder_layers <= len(self.decoder_layers):
            raise ValueError(f"shared_decoder_layers must be between 0 and the {len(self.decoder_layers)} hidden "
                             f"layers of decoder_layers, got {self.shared_decoder_layers}")
        if self.shared_decoder_layers and self.n_experts == 1:
            raise ValueError(f"shared_decoder_layers={self.shared_decoder_layers} shares decoder layers between "
                             "experts, but n_experts is 1: set n_experts > 1 or shared_decoder_layers 0")
        if self.mixture_nll not in MIXTURE_NLL:
            raise ValueError(f"mixture_nll must be one of {MIXTURE_NLL}, got {self.mixture_nll!r}")
        if self.expert_selection not in ("most_probable", "sample"):
            raise ValueError(f"expert_selection must be 'most_probable' or 'sample', got {self.expert_selection!r}")
        if not 0.0 <= self.mode_switch_margin < 1.0:
            raise ValueError(f"mode_switch_margin must be in [0, 1), got {self.mode_switch_margin}")
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
        if isinstance(self.assignment_draws, bool) or not float(self.assignment_draws).is_integer() \
                or self.assignment_draws < 0:  # NaN and inf are not integers either
            raise ValueError(f"assignment_draws must be an integer >= 0, got {self.assignment_draws}")
        self.assignment_draws = int(self.assignment_draws)
        if not 0.0 < self.unconditional_nll_coef < float("inf"):  # NaN included
            raise ValueError(f"unconditional_nll_coef must be a finite number > 0, got {self.unconditional_nll_coef}")
        if self.unconditional_nll_coef != 1.0 and (self.n_experts == 1 or self.mixture_nll != "assigned"):
            raise ValueError(f"unconditional_nll_coef weighs the unconditional mixture of mixture_nll='assigned' with "
                             f"n_experts > 1; got n_experts={self.n_experts}, mixture_nll={self.mixture_nll!r}: "
                             f"set unconditional_nll_coef 1")
        if self.assignment_draws and (self.n_experts == 1 or self.mixture_nll != "assigned"):
            raise ValueError(f"assignment_draws decides each episode's expert for mixture_nll='assigned' with "
                             f"n_experts > 1; got n_experts={self.n_experts}, mixture_nll={self.mixture_nll!r}: "
                             f"set assignment_draws 0")
        if self.draws_per_sample < 1:
            raise ValueError(f"draws_per_sample must be >= 1, got {self.draws_per_sample}")
        if not 0.0 <= self.feedback_draw_weight <= 1.0:
            raise ValueError(f"feedback_draw_weight must be in [0, 1], got {self.feedback_draw_weight}")
        if self.feedback_draw_queries is not None and (int(self.feedback_draw_queries) != self.feedback_draw_queries
                                                       or self.feedback_draw_queries < 0):
            raise ValueError(f"feedback_draw_queries must be an integer >= 0 (or None), got {self.feedback_draw_queries}")
        if not self.commanded_loss_weight > 0:
            raise ValueError(f"commanded_loss_weight must be > 0, got {self.commanded_loss_weight}")
        if self.commanded_loss_weight != 1.0 and self.n_experts > 1:
            raise ValueError("commanded_loss_weight applies to the single decoder: use n_experts=1 or "
                             f"commanded_loss_weight=1, got n_experts={self.n_experts}")
        if not 0.0 <= self.nll_beta <= 1.0:
            raise ValueError(f"nll_beta must be in [0, 1], got {self.nll_beta}")
        if self.demo_duration_s is not None and not self.demo_duration_s > 0:
            raise ValueError(f"demo_duration_s must be > 0, got {self.demo_duration_s}")
        if self.dataset_fps is not None and not self.dataset_fps > 0:
            raise ValueError(f"dataset_fps must be > 0, got {self.dataset_fps}")
        if self.max_conditions < 0:
            raise ValueError(f"max_conditions must be >= 0, got {self.max_conditions}")
        if isinstance(self.execution, dict):
            self.execution = ExecutionConfig(**self.execution)
        legacy = {name: getattr(self, name) for name in LEGACY_EXECUTION_FIELDS}
        self.execution = apply_legacy_execution(self.execution, legacy)
        for name in LEGACY_EXECUTION_FIELDS:
            setattr(self, name, None)
        for name in ("sm", "task_features", "sm_names"):
            if getattr(self, name) is not None:
                setattr(self, name, tuple(str(x) for x in getattr(self, name)))
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
    def env_condition_slots(self) -> int:
        """The condition slots of ``observation.environment_state`` (our envs' layout); 0 without them."""
        return self.env_state_feature.shape[-1] // slot_size(self.sm_dim) if self.condition_feature else 0

    @property
    def n_action_steps(self) -> int:
        """Actions per ``predict_action_chunk`` (``execution.n_action_steps``), where LeRobot's callers look."""
        return self.execution.n_action_steps


"""Conditional Neural Movement Primitives (Seker, Imre, Piater, Ugur, RSS 2019).

Read top-down:

1. ``sample_context_and_targets`` -- the training step's draw (paper Sec. III-B): from each demonstration
   in the batch, n ~ U{1..n_max} observations (t_i, SM(t_i)) and m ~ U{1..m_max} queries (t_q, SM(t_q)).
2. ``CNMP`` -- pure torch:  r_i = E([t_i, γ, SM_i ⊙ mask_i, mask_i]);  r = mean_i r_i  (``aggregate``);
   (μ_q, σ_q) = Q([t_q, γ, r])  (``decode``);  loss = -log N(SM(t_q) | μ_q, σ_q)  (``nll``, Eq. 1).
3. ``CNMPPolicy`` -- the LeRobot face: turns ``lerobot-train`` batches into episode samples for (1)-(2),
   and executes online in ``select_action`` (condition on goals + current state, predict the next SM).

Everything works on padded batches with validity masks; padded entries never change an output.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F  # noqa: N812
from torch import Tensor, nn

from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot.utils.constants import OBS_ENV_STATE

from lerobot_cnmp.bank import EpisodeBank
from lerobot_cnmp.conditions import decode_conditions
from lerobot_cnmp.configuration_cnmp import CNMPConfig


# --------------------------------------------------------------------------------------------------------
# Data containers
# --------------------------------------------------------------------------------------------------------


@dataclass
class Episodes:
    """Demonstrations (or windows of them) in a batch: ``values[b, j]`` is SM at ``phase[b, j]``."""

    values: Tensor  # [B, W, D]
    phase: Tensor  # [B, W] in [0, 1]
    valid: Tensor  # [B, W] bool
    task_params: Tensor | None = None  # [B, G]


@dataclass
class Context:
    """Observations to condition on: SM ``values`` at ``phase``, ``mask`` = which SM dims are given."""

    phase: Tensor  # [B, N]
    values: Tensor  # [B, N, D]
    mask: Tensor  # [B, N, D] float 0/1
    valid: Tensor  # [B, N] bool
    task_params: Tensor | None = None  # [B, G]


@dataclass
class Targets:
    phase: Tensor  # [B, M]
    values: Tensor  # [B, M, D]
    valid: Tensor  # [B, M] bool


# --------------------------------------------------------------------------------------------------------
# 1. The training step's draw
# --------------------------------------------------------------------------------------------------------


def _random_valid_order(valid: Tensor, generator: torch.Generator | None) -> Tensor:
    """A random permutation of each row's indices with the valid entries first."""
    scores = torch.rand(valid.shape, generator=generator, device=valid.device)
    scores = scores.masked_fill(~valid, 2.0)
    return scores.argsort(dim=1)


def _uniform_count(upper: Tensor, generator: torch.Generator | None) -> Tensor:
    """Per row, an integer uniform in {1, ..., upper} (upper >= 1)."""
    u = torch.rand(upper.shape, generator=generator, device=upper.device)
    return 1 + (u * upper).long().clamp(max=upper - 1)


def sample_context_and_targets(
    episodes: Episodes,
    n_max: int,
    m_max: int,
    partial_obs_prob: float = 0.0,
    generator: torch.Generator | None = None,
    context_in_targets: bool = False,
    sensed_mask: Tensor | None = None,
    sensed_obs_prob: float = 0.0,
) -> tuple[Context, Targets]:
    """Sample, per episode, n ~ U{1..min(n_max, #valid)} observations and m ~ U{1..min(m_max, #valid)}
    queries among its valid entries (plus the n observations themselves with ``context_in_targets``).
    With probability ``partial_obs_prob`` an observation constrains only a random non-empty subset of the
    SM dimensions; with probability ``sensed_obs_prob`` (of the rest) only the dims of ``sensed_mask`` [D]
    (what execution feeds back: the sensed dims without the commanded ones)."""
    values, phase, valid = episodes.values, episodes.phase, episodes.valid
    B, W, D = values.shape  # noqa: N806
    n_valid = valid.sum(dim=1)
    if bool((n_valid < 1).any()):
        raise ValueError("every episode in the batch needs at least one valid (non-padded) frame")

    def draw(k_max: int):
        order = _random_valid_order(valid, generator)[:, : min(k_max, W)]
        count = _uniform_count(n_valid.clamp(max=k_max), generator)
        keep = torch.arange(order.shape[1], device=values.device)[None, :] < count[:, None]
        idx = order
        return (
            phase.gather(1, idx),
            values.gather(1, idx[..., None].expand(-1, -1, D)),
            keep,
        )

    c_phase, c_values, c_valid = draw(n_max)
    t_phase, t_values, t_valid = draw(m_max)

    mask = torch.ones_like(c_values)
    if partial_obs_prob > 0 and D > 1:
        bits = torch.rand(c_values.shape, generator=generator, device=values.device) < 0.5
        # Guarantee a non-empty subset: force one random dim on.
        forced = torch.randint(D, c_values.shape[:2], generator=generator, device=values.device)
        bits = bits | F.one_hot(forced, D).bool()
        partial = torch.rand(c_values.shape[:2], generator=generator, device=values.device) < partial_obs_prob
        mask = torch.where(partial[..., None], bits.float(), mask)
    else:
        partial = torch.zeros(c_values.shape[:2], dtype=torch.bool, device=values.device)
    if sensed_mask is not None and sensed_obs_prob > 0:
        sensed = torch.rand(c_values.shape[:2], generator=generator, device=values.device) < sensed_obs_prob
        sensed = sensed & ~partial
        mask = torch.where(sensed[..., None], sensed_mask.to(mask)[None, None, :].expand_as(mask), mask)

    context = Context(c_phase, c_values, mask, c_valid, episodes.task_params)
    if context_in_targets:
        t_phase, t_values, t_valid = (torch.cat(p, 1) for p in ((c_phase, t_phase), (c_values, t_values), (c_valid, t_valid)))
    return context, Targets(t_phase, t_values, t_valid)


# --------------------------------------------------------------------------------------------------------
# 2. The model
# --------------------------------------------------------------------------------------------------------


def mlp(in_dim: int, widths: tuple[int, ...]) -> nn.Sequential:
    """Linear layers with ReLU between them (none after the last)."""
    layers: list[nn.Module] = []
    for i, w in enumerate(widths):
        layers.append(nn.Linear(in_dim, w))
        if i < len(widths) - 1:
            layers.append(nn.ReLU())
        in_dim = w
    return nn.Sequential(*layers)


def run_mlp(layers: nn.Sequential, x: Tensor, start: int = 0) -> Tensor:
    """``layers(x)`` from layer ``start`` on, without the per-module call overhead (a few µs per layer on CPU,
    which is most of a control step's time). Same parameters, same result."""
    for layer in list(layers)[start:]:
        x = F.linear(x, layer.weight, layer.bias) if isinstance(layer, nn.Linear) else F.relu(x, inplace=True)
    return x


class ConvEncoder(nn.Module):
    """Image -> embedding (paper Sec. IV-B): per width in ``channels`` a 3x3 conv, ReLU and 2x2 max-pool
    (the paper: 8, 16, 32, 64), then a linear layer to ``embed_dim``."""

    def __init__(self, in_shape: tuple[int, int, int], channels: tuple[int, ...], embed_dim: int):
        super().__init__()
        c, h, w = in_shape
        layers: list[nn.Module] = []
        for width in channels:
            layers += [nn.Conv2d(c, width, 3, padding=1), nn.ReLU(), nn.MaxPool2d(2)]
            c, h, w = width, h // 2, w // 2
        self.conv = nn.Sequential(*layers)
        self.project = nn.Linear(c * h * w, embed_dim)

    def forward(self, images: Tensor) -> Tensor:
        return self.project(self.conv(images).flatten(1))


class CNMP(nn.Module):
    """Encoder E -> mean aggregation -> query network Q with a Gaussian output (pure torch)."""

    def __init__(
        self,
        sm_dim: int,
        task_dim: int = 0,
        encoder_layers: tuple[int, ...] = (128, 128, 128),
        decoder_layers: tuple[int, ...] = (128, 128, 128),
        min_std: float = 0.01,
        phase_frequencies: int = 0,
        nll_beta: float = 0.0,
    ):
        super().__init__()
        self.sm_dim, self.task_dim, self.min_std, self.nll_beta = sm_dim, task_dim, min_std, nll_beta
        self.register_buffer(
            "frequencies", torch.pi * torch.arange(1, phase_frequencies + 1, dtype=torch.float32), persistent=False
        )
        t_dim = 1 + 2 * phase_frequencies
        self.encoder = mlp(t_dim + task_dim + 2 * sm_dim, tuple(encoder_layers))
        self.decoder = mlp(t_dim + task_dim + encoder_layers[-1], (*decoder_layers, 2 * sm_dim))

    def phase_features(self, t: Tensor) -> Tensor:
        """[..., 1 + 2K]: t itself, plus sin / cos of k·π·t for k = 1..K (none by default, as in the paper)."""
        t = t[..., None]
        if self.frequencies.numel() == 0:
            return t
        angles = t * self.frequencies
        return torch.cat([t, angles.sin(), angles.cos()], dim=-1)

    def _inputs(self, head: list[Tensor], tail: list[Tensor], task_params: Tensor | None, n: int) -> Tensor:
        """[*head, γ, *tail] along the last dim, γ repeated over the n points (the input layout of E and Q)."""
        if self.task_dim:
            if task_params is None:
                raise ValueError(f"this CNMP was trained with {self.task_dim} task parameters γ; none given")
            if task_params.shape[-1] != self.task_dim:
                raise ValueError(
                    f"task parameters γ have {task_params.shape[-1]} dims, the model expects {self.task_dim}"
                )
            head = [*head, task_params[:, None, :].expand(-1, n, -1)]
        parts = head + tail
        return parts[0] if len(parts) == 1 else torch.cat(parts, dim=-1)

    def encode(self, context: Context) -> Tensor:
        """r_i = E(t_i, γ, SM_i ⊙ mask_i, mask_i): one representation per observation, [B, N, R]."""
        x = self._inputs(
            [self.phase_features(context.phase)],
            [context.values * context.mask, context.mask],
            context.task_params,
            context.phase.shape[1],
        )
        return run_mlp(self.encoder, x)

    @staticmethod
    def aggregate(r_i: Tensor, valid: Tensor) -> Tensor:
        """r = mean of the valid r_i, [B, R] (order- and padding-invariant)."""
        w = valid.to(r_i.dtype)
        return torch.bmm(w[:, None, :], r_i)[:, 0] / w.sum(dim=1, keepdim=True).clamp(min=1.0)

    def decode(self, r: Tensor, query_phase: Tensor, task_params: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """(μ, σ) = Q(t_q, γ, r) for every query phase, each [B, M, D]; σ = min_std + softplus(.).

        Q's first layer is linear in its input [t_q, γ, r], so it is computed as W_t·t_q + (W_γr·[γ, r] + b):
        the second term once per episode, not once per query (a 200-query trajectory costs little more than
        its last layers)."""
        first = self.decoder[0]
        t_dim = 1 + 2 * self.frequencies.numel()
        per_episode = self._inputs([], [r[:, None, :]], task_params, 1)  # [B, 1, G + R]
        h = F.linear(per_episode, first.weight[:, t_dim:], first.bias) + F.linear(
            self.phase_features(query_phase), first.weight[:, :t_dim]
        )
        out = run_mlp(self.decoder, h, start=1)
        mean, raw = out.split(self.sm_dim, dim=-1)
        return mean, self.min_std + F.softplus(raw)

    def condition(self, context: Context) -> Tensor:
        """The representation r of a context (encode + aggregate)."""
        return self.aggregate(self.encode(context), context.valid)

    def forward(self, context: Context, query_phase: Tensor) -> tuple[Tensor, Tensor]:
        return self.decode(self.condition(context), query_phase, context.task_params)

    @staticmethod
    def nll(mean: Tensor, std: Tensor, targets: Targets, beta: float = 0.0) -> Tensor:
        """Eq. 1: -log N(SM(t_q) | μ_q, σ_q), summed over SM dims, averaged over the valid queries. With
        ``beta`` > 0, the β-NLL: each dim's term weighted by stop_gradient(σ^(2β))."""
        per_dim = 0.5 * ((targets.values - mean) / std) ** 2 + std.log() + 0.5 * np.log(2 * np.pi)
        if beta:
            per_dim = per_dim * std.detach() ** (2.0 * beta)
        per_query = per_dim.sum(dim=-1)
        w = targets.valid.to(per_query.dtype)
        return (per_query * w).sum() / w.sum().clamp(min=1.0)

    def training_loss(self, context: Context, targets: Targets) -> tuple[Tensor, dict]:
        """One training step's loss on a drawn (context, targets) pair, with monitoring figures."""
        mean, std = self(context, targets.phase)
        loss = self.nll(mean, std, targets, self.nll_beta)
        with torch.no_grad():
            w = targets.valid[..., None].to(mean.dtype)
            mae = ((mean - targets.values).abs() * w).sum() / (w.sum() * mean.shape[-1]).clamp(min=1.0)
            mean_std = (std * w).sum() / (w.sum() * mean.shape[-1]).clamp(min=1.0)
        return loss, {"nll": loss.item(), "mae": mae.item(), "std": mean_std.item()}


class NumpyCNMP:
    """A frozen numpy copy of a :class:`CNMP` for execution on CPU: the same inference equations (encode,
    masked-mean aggregate, decode with Q's first layer split) on the same weights.

    A batch-1 control step is ~25 small ops; torch spends several µs of dispatch on each, numpy about one,
    so this runs a control step 2-4x faster on CPU. Training stays in torch; the policy rebuilds this copy
    whenever the weights change. ``tests/test_model.py`` checks it against :class:`CNMP`."""

    def __init__(self, model: CNMP):
        def layers(seq: nn.Sequential) -> list[tuple[np.ndarray, np.ndarray]]:
            return [(m.weight.detach().cpu().numpy().T.copy(), m.bias.detach().cpu().numpy().copy())
                    for m in seq if isinstance(m, nn.Linear)]

        self.encoder, decoder = layers(model.encoder), layers(model.decoder)
        self.frequencies = model.frequencies.cpu().numpy()
        self.sm_dim, self.task_dim, self.min_std = model.sm_dim, model.task_dim, model.min_std
        t_dim = 1 + 2 * self.frequencies.size
        (w, b), self.decoder = decoder[0], decoder[1:]
        self.decoder_t, self.decoder_rest, self.decoder_bias = w[:t_dim], w[t_dim:], b

    def phase_features(self, t: np.ndarray) -> np.ndarray:
        t = t[..., None]
        if not self.frequencies.size:
            return t
        angles = t * self.frequencies
        return np.concatenate([t, np.sin(angles), np.cos(angles)], axis=-1)

    @staticmethod
    def _mlp(x: np.ndarray, layers) -> np.ndarray:
        for i, (w, b) in enumerate(layers):
            x = x @ w
            x += b
            if i < len(layers) - 1:
                np.maximum(x, 0.0, out=x)
        return x

    def __call__(self, context: Context, query_phase: Tensor) -> tuple[Tensor, Tensor]:
        phase, values, mask = context.phase.numpy(), context.values.numpy(), context.mask.numpy()
        valid = context.valid.numpy().astype(np.float32)
        gamma = None if context.task_params is None or not self.task_dim else context.task_params.numpy()
        head = [self.phase_features(phase)]
        if gamma is not None:
            head.append(np.broadcast_to(gamma[:, None, :], (*phase.shape, self.task_dim)))
        r_i = self._mlp(np.concatenate([*head, values * mask, mask], axis=-1), self.encoder)  # E
        r = (valid[:, None, :] @ r_i)[:, 0] / np.maximum(valid.sum(1, keepdims=True), 1.0)  # mean of valid r_i
        if gamma is not None:
            r = np.concatenate([gamma, r], axis=-1)
        h = (r @ self.decoder_rest + self.decoder_bias)[:, None, :] + self.phase_features(query_phase.numpy()) @ self.decoder_t
        np.maximum(h, 0.0, out=h)
        out = self._mlp(h, self.decoder)  # Q
        mean, raw = out[..., : self.sm_dim], out[..., self.sm_dim :]
        return torch.from_numpy(np.ascontiguousarray(mean)), torch.from_numpy(self.min_std + np.logaddexp(0.0, raw))


# --------------------------------------------------------------------------------------------------------
# 3. The LeRobot policy
# --------------------------------------------------------------------------------------------------------


def check_finite(name: str, x: Tensor) -> None:
    if not bool(torch.isfinite(x).all()):
        raise ValueError(f"{name} contains NaN or infinite values")


class SMNormalizer(nn.Module):
    """The SM's and γ's normalization statistics, as buffers saved with the weights (``model.safetensors``).

    Every SM input -- demonstrations, sensed dims, condition values -- is scaled by the same per-dim
    statistics, computed once from the training demonstrations (:meth:`EpisodeBank.sm_stats`). Held here and
    not in LeRobot's normalizer steps, they survive ``lerobot-train --policy.path=...`` (fine-tuning), whose
    processors are rebuilt with the new dataset's raw statistics: the checkpoint's buffers load over them."""

    def __init__(self, sm_dim: int, task_dim: int):
        super().__init__()
        self.register_buffer("sm_mean", torch.zeros(sm_dim))
        self.register_buffer("sm_std", torch.full((sm_dim,), float("nan")))
        self.register_buffer("task_mean", torch.zeros(task_dim))
        self.register_buffer("task_std", torch.full((task_dim,), float("nan")))

    @property
    def ready(self) -> bool:
        return bool(torch.isfinite(self.sm_std).all()) and bool(torch.isfinite(self.task_std).all())

    def set(self, sm: tuple[np.ndarray, np.ndarray], task: tuple[np.ndarray, np.ndarray] | None) -> None:
        with torch.no_grad():
            self.sm_mean.copy_(torch.as_tensor(sm[0]))
            self.sm_std.copy_(torch.as_tensor(sm[1]))
            if task is not None:
                self.task_mean.copy_(torch.as_tensor(task[0]))
                self.task_std.copy_(torch.as_tensor(task[1]))

    def require(self) -> None:
        if not self.ready:
            raise RuntimeError(
                "this CNMP has no normalization statistics: train it on a dataset (lerobot-train, CNMPModel.fit) "
                "or load a checkpoint")

    def sm(self, x: Tensor) -> Tensor:
        return (x - self.sm_mean) / self.sm_std

    def sm_inverse(self, x: Tensor, dims: list[int] | None = None) -> Tensor:
        if dims is None:
            return x * self.sm_std + self.sm_mean
        return x * self.sm_std[dims] + self.sm_mean[dims]

    def task(self, g: Tensor) -> Tensor:
        return (g - self.task_mean) / self.task_std


class CNMPPolicy(PreTrainedPolicy):
    """CNMP as a LeRobot policy.

    Training (``forward``): a batch item names an episode (``episode_index``, from the frame LeRobot's loader
    drew); its observations and queries are drawn from that whole episode's SM, held in memory
    (:class:`~lerobot_cnmp.bank.EpisodeBank`, read from the dataset when LeRobot builds the policy with
    ``dataset_meta``, or given by the in-memory API). One sampler and one loss serve both paths.

    Execution (``select_action``, the paper's loop of Sec. III / Fig. 3): per env, the policy keeps a phase
    τ (0 after ``reset``) that advances by Δ = 1 / (control_fps x demo_duration_s) per call. Each step it
    1. holds τ while the tracking error (sensed SM vs the SM expected now, in normalized units) exceeds
       ``phase_stop_threshold`` (with ``online_feedback``; open loop always advances);
    2. conditions on the episode's conditions (``observation.environment_state`` slots), on the sensed dims at
       the first step (t = 0, ``condition_on_start``) and, with ``online_feedback``, on the current sensed
       dims: at τ in the joint layout (frame k's state and action share a phase), at τ - Δ in the tied layout
       (the state step k - 1's command reached);
    3. outputs the predicted ``action`` dims at τ (joint layout), or the PD command s + kp·e + kd·(e - e_prev),
       e = μ(τ) - s (tied layout), in the dataset's units.
    γ and the conv encoder's image are read at the first step of an episode, as training reads them at the
    episode's first frame.
    """

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
        self.config = config
        # One conv encoder per image feature; its embedding joins γ as the episode-level input of E and Q.
        self.image_encoders = nn.ModuleDict({
            key.replace(".", "_"): ConvEncoder(tuple(config.input_features[key].shape), config.image_channels,
                                               config.image_embed_dim)
            for key in config.image_keys
        })
        self.model = CNMP(
            sm_dim=config.sm_dim,
            task_dim=config.episode_dim,
            encoder_layers=config.encoder_layers,
            decoder_layers=config.decoder_layers,
            min_std=config.min_std,
            phase_frequencies=config.phase_frequencies,
            nll_beta=config.nll_beta,
        )
        self.normalizer = SMNormalizer(config.sm_dim, config.task_dim)
        spec = config.spec
        # the mask of execution's feedback point (joint layout: the sensed dims); None in the tied layout,
        # where the fed-back point is a whole SM point
        sensed_only = torch.zeros(config.sm_dim)
        sensed_only[spec.sensed] = 1.0
        self.register_buffer("sensed_only_mask", None if spec.tied or not spec.sensed else sensed_only,
                             persistent=False)
        if config.feedback_draw_weight > 0 and self.sensed_only_mask is None:
            raise ValueError(
                "feedback_draw_weight > 0 needs the joint layout with sensed dims (execution conditions on them); "
                f"this SM is {'tied to the action' if spec.tied else 'commanded only'}: set it to 0")
        self.bank: EpisodeBank | None = None
        self._first_frames: FirstFrames | None = None
        if dataset_meta is not None:
            self.set_dataset(dataset_meta)
        self._numpy_model: NumpyCNMP | None = None  # execution copy of self.model, see executor()
        self._numpy_key: tuple | None = None
        self.reset()

    @classmethod
    def _load_as_safetensor(cls, model, model_file: str, map_location: str, strict: bool):
        """Load weights strictly: a checkpoint of another CNMP configuration is an error, not a silent
        partial load."""
        try:
            return super()._load_as_safetensor(model, model_file, map_location, strict=True)
        except RuntimeError as e:
            raise ValueError(
                f"the weights in {model_file} do not fit this CNMP configuration (layer sizes, SM or γ dims "
                f"differ, or a checkpoint from before the SM normalizer moved into the weights: retrain it): {e}"
            ) from e

    # ---- sharing --------------------------------------------------------------------------------------

    def generate_model_card(self, dataset_repo_id, model_type="cnmp", license=None, tags=None, cfg=None,
                            dataset_meta=None, eval_info: dict | None = None, repo_id: str | None = None):
        """The model card of a CNMP checkpoint (used by ``lerobot-train --policy.push_to_hub=true`` and by
        ``lerobot_cnmp.hub.push_checkpoint``): what it is, what it was trained on, its settings, its
        evaluation figures when given, and how to run it. Built offline (no Hub validation call)."""
        from huggingface_hub import ModelCard, ModelCardData

        c = self.config
        repo_id = repo_id or getattr(c, "repo_id", None) or "<repo_id>"
        dataset_repo_id = dataset_repo_id or (cfg.dataset.repo_id if cfg is not None else None)
        data = ModelCardData(
            license=license or c.license or "apache-2.0", library_name="lerobot", pipeline_tag="robotics",
            tags=sorted({"robotics", "lerobot", "cnmp", "movement-primitives", *(tags or c.tags or [])}),
            datasets=dataset_repo_id, model_name="cnmp",
        )
        inputs = ", ".join(f"`{k}` {list(v.shape)}" for k, v in c.input_features.items())
        trained = f"[{dataset_repo_id}](https://huggingface.co/datasets/{dataset_repo_id})" if dataset_repo_id else "(not recorded)"
        steps = f", {cfg.steps} steps of batch {cfg.batch_size}" if cfg is not None else ""
        groups = list((eval_info or {}).get("per_group", {}))  # lerobot-eval's eval_info names the env
        env_type = groups[0] if groups else "<env type, e.g. cnmp_obstacle2d>"
        images = ""
        if c.image_keys:
            images = (f"\n- Images ({', '.join(f'`{k}`' for k in c.image_keys)}) through a conv encoder: 3x3 conv + 2x2 "
                      f"max-pool per width in {list(c.image_channels)}, embedding {c.image_embed_dim} per image.")
        # the in-memory API (CNMPModel) takes SM trajectories only: image checkpoints run as a policy
        imports = "load_pretrained" if c.image_keys else "CNMPModel, load_pretrained"
        api = ("" if c.image_keys else
               f'\nmodel = CNMPModel.load("{repo_id}")                                   # or the in-memory API')
        results = "No evaluation figures were attached to this card."
        if eval_info:
            overall = eval_info.get("overall", eval_info)
            results = (f"`lerobot-eval`: **pc_success {overall.get('pc_success')}** over "
                       f"{overall.get('n_episodes')} episodes.")
        body = f"""# CNMP policy `{repo_id}`

A Conditional Neural Movement Primitive (Seker, Imre, Piater, Ugur, RSS 2019) trained with the
lerobot-cnmp plugin as a LeRobot policy (`--policy.type=cnmp`): an encoder over
observed (phase, SM) points, mean aggregation and a Gaussian query network predict the sensorimotor (SM)
trajectory given any subset of SM points and task parameters γ; executed online with re-conditioning on
the sensed state, PD tracking and phase stopping.

## Training

- Data: {trained}{steps}.
- SM: {c.sm_dim} dims ({', '.join(c.sm_names or [])}); inputs: {inputs}; task parameters γ: {c.task_dim} dims.
- Encoder {list(c.encoder_layers)}, query network {list(c.decoder_layers)}, n_max {c.n_max_context},
  m_max {c.m_max_targets}, draws per sample {c.draws_per_sample}, phase Fourier features {c.phase_frequencies}.{images}
- Every setting is in `config.json`; the SM and γ normalization statistics are in `model.safetensors`
  (`normalizer.*`), and the processors pass CNMP's features through.

## Evaluation

{results}

## Use

```bash
pip install -e .   # in a lerobot-cnmp checkout: registers --policy.type=cnmp and its sims
lerobot-eval --policy.path={repo_id} --env.type={env_type} --eval.n_episodes=50 --policy.device=cpu
```

```python
from lerobot_cnmp.api import {imports}
policy, preprocessor, postprocessor = load_pretrained("{repo_id}")   # weights carry the normalization{api}
```
"""
        return ModelCard(f"---\n{data.to_yaml()}\n---\n\n{body}")

    # ---- training -------------------------------------------------------------------------------------

    def set_dataset(self, dataset_meta) -> None:
        """Read the training demonstrations' SM and γ from a LeRobot dataset (its metadata's local root) and,
        for a new policy, the normalization statistics, the demos' duration and fps."""
        bank = EpisodeBank.from_dataset(dataset_meta.root, self.config.spec)
        self.set_bank(bank, fps=float(dataset_meta.fps))
        if self.config.image_keys:
            self._first_frames = FirstFrames(dataset_meta, self.config.image_keys)

    def set_bank(self, bank: EpisodeBank, fps: float | None) -> None:
        c = self.config
        if bank.values.shape[1] != c.sm_dim:
            raise ValueError(f"the demonstrations have {bank.values.shape[1]} SM dims, the policy {c.sm_dim}")
        self.bank = bank
        if not self.normalizer.ready:  # a checkpoint's statistics (fine-tuning) load over these afterwards
            self.normalizer.set(bank.sm_stats(), bank.task_stats())
        if c.demo_duration_s is None:
            c.demo_duration_s = bank.median_duration_s()
        if c.dataset_fps is None:
            c.dataset_fps = fps if fps is not None else 1.0

    def episodes_for(self, episode_index: Tensor, generator: torch.Generator | None = None, draws: int = 1) -> Episodes:
        """``draws`` independent draws per named episode (rows ``b * draws .. b * draws + draws - 1``): each
        n_max + m_max frames uniform over the whole episode, normalized. The episode-level input (γ, the conv
        encoder's embedding of the first frame) is computed once per named episode."""
        if self.bank is None:
            raise RuntimeError(
                "CNMP trains on demonstrations it holds in memory: build the policy with `dataset_meta=` "
                "(lerobot-train does) or train with lerobot_cnmp.api.CNMPModel.fit")
        self.normalizer.require()
        c = self.config
        dev = self.normalizer.sm_std.device
        episode_index = episode_index.reshape(-1)
        values, phase = self.bank.draw(episode_index.repeat_interleave(draws), c.n_max_context + c.m_max_targets,
                                       generator)
        values = self.normalizer.sm(values.to(dev))
        valid = torch.ones(phase.shape, dtype=torch.bool, device=dev)
        return Episodes(values, phase.to(dev), valid, self._training_inputs(episode_index, draws))

    def _training_inputs(self, episode_index: Tensor, draws: int) -> Tensor | None:
        """The episode-level input (normalized γ, the conv encoder's embedding of the first frame) of each named
        episode, computed once and repeated over its ``draws``; None when there is neither."""
        c = self.config
        dev = self.normalizer.sm_std.device
        gamma = self.bank.task_params_of(episode_index)
        parts = []
        if gamma is not None and c.task_dim:
            parts.append(self.normalizer.task(gamma.to(dev)))
        if c.image_keys:
            if self._first_frames is None:
                raise RuntimeError("this CNMP conditions on images: build it with `dataset_meta=` to train")
            images = self._first_frames(episode_index)
            parts += [self.image_encoders[k.replace(".", "_")](images[k].to(dev)) for k in c.image_keys]
        inputs = None if not parts else (parts[0] if len(parts) == 1 else torch.cat(parts, dim=-1))
        if inputs is not None and draws > 1:
            inputs = inputs.repeat_interleave(draws, dim=0)
        return inputs

    def forward(self, batch: dict[str, Tensor], generator: torch.Generator | None = None) -> tuple[Tensor, dict]:
        c = self.config
        if "episode_index" not in batch:
            raise KeyError(f"CNMP training batches need 'episode_index' (LeRobot's loader gives it); got {sorted(batch)}")
        episodes = self.episodes_for(batch["episode_index"], generator, draws=c.draws_per_sample)
        context, targets = sample_context_and_targets(
            episodes, c.n_max_context, c.m_max_targets, c.partial_obs_prob, generator, c.context_in_targets,
            self.sensed_only_mask, c.sensed_obs_prob,
        )
        loss, info = self.model.training_loss(context, targets)
        w = c.feedback_draw_weight
        if w > 0:
            fb_loss, fb_info = self.model.training_loss(*self.feedback_draws(batch["episode_index"], generator))
            info = {**info, "nll_random": info["nll"], "nll_feedback": fb_info["nll"]}
            loss = (1.0 - w) * loss + w * fb_loss
            info["nll"] = loss.item()
        return loss, info

    def feedback_draws(self, episode_index: Tensor, generator: torch.Generator | None = None) -> tuple[Context, Targets]:
        """Execution-shaped draws (``feedback_draw_weight``), ``draws_per_sample`` per named episode: the
        context is the sensed dims at the episode's first frame (with ``condition_on_start``) and at a uniform
        frame j; the queries are j, j + 1 and ``m_max_targets`` uniform frames."""
        c = self.config
        dev = self.normalizer.sm_std.device
        episode_index = episode_index.reshape(-1)
        inputs = self._training_inputs(episode_index, c.draws_per_sample)
        values, phase = self.bank.draw_feedback(episode_index.repeat_interleave(c.draws_per_sample),
                                                c.m_max_targets, generator)
        values, phase = self.normalizer.sm(values.to(dev)), phase.to(dev)
        first = 0 if c.condition_on_start else 1
        n_ctx = 2 - first
        b = values.shape[0]
        mask = self.sensed_only_mask[None, None, :].expand(b, n_ctx, -1)
        context = Context(phase[:, first:2], values[:, first:2], mask,
                          torch.ones(b, n_ctx, dtype=torch.bool, device=dev), inputs)
        targets = Targets(phase[:, 1:], values[:, 1:], torch.ones(b, phase.shape[1] - 1, dtype=torch.bool, device=dev))
        return context, targets

    def get_optim_params(self) -> dict:
        return self.parameters()

    # ---- execution ------------------------------------------------------------------------------------

    def reset(self) -> None:
        """Restart every env's execution state (called by lerobot-eval at each episode start)."""
        self._phase: Tensor | None = None  # τ per env
        self._start: Tensor | None = None  # sensed SM at the first step (condition_on_start), normalized
        self._target: Tensor | None = None  # tied: SM commanded at the previous step (normalized)
        self._expected: Tensor | None = None  # joint: sensed SM predicted for this step (normalized)
        self._error: Tensor | None = None  # previous PD error e, for the D term
        self._inputs: Tensor | None = None  # γ and image embeddings read at the first step
        self._has_inputs = False

    @property
    def phase_step(self) -> float:
        c = self.config
        if c.phase_step is not None:
            return c.phase_step
        if c.demo_duration_s is None:
            raise RuntimeError(
                "demo_duration_s is unknown: train on a dataset (it is set from the episodes' timestamps) or set "
                "--policy.demo_duration_s or --policy.phase_step"
            )
        fps = c.control_fps or c.dataset_fps or 1.0
        return min(1.0, 1.0 / (fps * c.demo_duration_s))

    @staticmethod
    def _dims_mask(like: Tensor, dims) -> Tensor:
        if dims is None:
            return torch.ones_like(like)
        mask = torch.zeros_like(like)
        mask[..., list(dims)] = 1.0
        return mask

    def _feedback_mask(self, like: Tensor) -> Tensor:
        """The fed-back dims: ``feedback_dims``, else every sensed dim."""
        c = self.config
        dims = c.feedback_dims if c.feedback_dims is not None else (None if c.spec.tied else c.spec.sensed)
        return self._dims_mask(like, dims)

    def sensed_sm(self, batch: dict[str, Tensor]) -> Tensor:
        """The live observation's sensed dims as a normalized SM vector [B, D] (other dims 0)."""
        spec = self.config.spec
        out = None
        for feature, pairs in spec.sensed_features.items():
            if feature not in batch:
                raise KeyError(f"the CNMP feeds back {feature!r}: the observation needs it; it has {sorted(batch)}")
            x = batch[feature]
            x = x.reshape(x.shape[0], -1) if x.ndim != 2 else x
            if x.shape[-1] <= max(k for _, k in pairs):
                raise ValueError(f"{feature!r} has {x.shape[-1]} dims, the SM reads dim {max(k for _, k in pairs)} "
                                 f"of it (the checkpoint's SM does not match this env/robot)")
            if spec.tied and x.shape[-1] != spec.size:
                raise ValueError(f"{feature!r} has {x.shape[-1]} dims, the SM has {spec.size}")
            if out is None:
                out = torch.zeros(x.shape[0], spec.size, dtype=torch.float32, device=x.device)
            idx = torch.tensor([i for i, _ in pairs], device=x.device)
            src = torch.tensor([k for _, k in pairs], device=x.device)
            vals = x[:, src].float()
            check_finite(feature, vals)
            out[:, idx] = vals
        if out is None:
            return None
        full = self.normalizer.sm(out)
        mask = torch.zeros(spec.size, device=out.device)
        mask[spec.sensed] = 1.0
        return full * mask

    def _episode_inputs(self, batch: dict[str, Tensor]) -> Tensor | None:
        """The episode-level input of E and Q read at the first step of the episode: γ and the embedding of
        each image feature, [B, episode_dim]; None when there is neither."""
        c = self.config
        parts = []
        for key, size in c.spec.task_features:
            if key not in batch:
                raise KeyError(f"this CNMP is conditioned on task parameters: the observation needs {key!r}; it has "
                               f"{sorted(batch)}")
            g = batch[key]
            g = g.reshape(g.shape[0], -1) if g.ndim != 3 else g[:, 0]
            if g.shape[-1] != size:
                raise ValueError(f"task feature {key!r} has {g.shape[-1]} values, the CNMP was trained with {size}")
            check_finite(key, g)
            parts.append(g.float())
        if parts:
            parts = [self.normalizer.task(torch.cat(parts, dim=-1))]
        for key in c.image_keys:
            if key not in batch:
                raise KeyError(f"this CNMP is conditioned on the image {key!r}; the observation has {sorted(batch)}")
            img = batch[key]
            img = img[:, 0] if img.ndim == 5 else img
            check_finite(key, img)
            parts.append(self.image_encoders[key.replace(".", "_")](img))
        if not parts:
            return None
        return parts[0] if len(parts) == 1 else torch.cat(parts, dim=-1)

    def _condition_slots(self, batch: dict[str, Tensor]):
        d = self.config.sm_dim
        env = batch[OBS_ENV_STATE]
        present, c_phase, c_values, c_mask = decode_conditions(env, d)
        given = present > 0.5
        check_finite(OBS_ENV_STATE + " (flags, phases, masks)", torch.stack([present, c_phase], -1))
        used = given[..., None] & (c_mask > 0.5)
        if bool((~torch.isfinite(c_values) & used).any()):
            raise ValueError(f"a condition in {OBS_ENV_STATE} has NaN or infinite values in a constrained dim")
        if bool(((c_phase < 0) | (c_phase > 1))[given].any()):
            raise ValueError("a condition in environment_state has a phase outside [0, 1]")
        values = torch.where(used, self.normalizer.sm(torch.nan_to_num(c_values.float())), torch.zeros_like(c_values))
        return c_phase, values, c_mask.float(), given & (c_mask.sum(-1) > 0)

    def execution_context(self, batch: dict[str, Tensor], phase: Tensor, sensed: Tensor | None = None) -> Context:
        """Conditions from ``environment_state``, the sensed dims at the first step at t = 0 and (with
        ``online_feedback``) the current sensed dims (at τ, or τ - Δ in the tied layout)."""
        c = self.config
        self.normalizer.require()
        phases, values, masks, valids = [], [], [], []
        if c.max_conditions and OBS_ENV_STATE in batch:
            for lst, x in zip((phases, values, masks, valids), self._condition_slots(batch), strict=True):
                lst.append(x)
        need_state = (c.online_feedback or c.condition_on_start) and bool(c.spec.sensed)
        if need_state and sensed is None:
            sensed = self.sensed_sm(batch)
        start_mask = self._dims_mask(sensed[0], None if c.spec.tied else c.spec.sensed) if need_state else None
        if c.condition_on_start and need_state:
            if self._start is None or self._start.shape[0] != sensed.shape[0]:
                self._start = sensed.clone()
            phases.append(torch.zeros_like(phase)[:, None])
            values.append(self._start[:, None, :])
            masks.append(start_mask.expand_as(sensed)[:, None, :])
            valids.append(torch.ones_like(phase, dtype=torch.bool)[:, None])
        if c.online_feedback and need_state:
            at = (phase - self.phase_step).clamp(min=0.0) if c.spec.tied else phase
            phases.append(at[:, None])
            values.append(sensed[:, None, :])
            masks.append(self._feedback_mask(sensed)[:, None, :])
            valids.append(torch.ones_like(phase, dtype=torch.bool)[:, None])
        if not phases:
            raise ValueError(
                "nothing to condition on: the observation has no environment_state conditions and both "
                "online_feedback and condition_on_start are off"
            )
        valid = torch.cat(valids, dim=1)
        if not bool(valid.any(dim=1).all()):
            raise ValueError("an env in the batch has no condition to condition on (empty context)")
        if not self._has_inputs:
            self._inputs, self._has_inputs = self._episode_inputs(batch), True
        return Context(torch.cat(phases, 1), torch.cat(values, 1), torch.cat(masks, 1), valid, self._inputs)

    def tracking_error(self, sensed: Tensor) -> Tensor:
        """Per env, max over the tracked dims (``tracking_dims``, else the fed-back ones) of |sensed SM - SM
        expected now| (tied: the SM commanded at the previous step), in normalized units."""
        ref = self._target if self.config.spec.tied else self._expected
        if ref is None:
            return torch.zeros(sensed.shape[0], device=sensed.device, dtype=sensed.dtype)
        c = self.config
        dims = c.tracking_dims if c.tracking_dims is not None else c.feedback_dims
        mask = self._dims_mask(sensed, dims) if dims is not None else self._feedback_mask(sensed)
        return ((sensed - ref).abs() * mask).amax(dim=-1)

    def pd_gains(self, std: Tensor) -> tuple[Tensor, Tensor]:
        """(kp, kd) per env and SM dim: kp constant or scaled by sigma_ref / σ within [kp_min, kp_max]; outside
        ``pd_dims`` kp = 1 and kd = 0 (the prediction itself is commanded)."""
        c = self.config
        kp = torch.full_like(std, c.pd_kp) if not c.sigma_scaled_gains else (c.pd_kp * c.sigma_ref / std).clamp(
            c.kp_min, c.kp_max)
        kd = torch.full_like(std, c.pd_kd)
        if c.pd_dims is not None:
            on = self._dims_mask(std, c.pd_dims)
            kp, kd = on * kp + (1 - on), on * kd
        return kp, kd

    def _ensure_state(self, batch: dict[str, Tensor]) -> int:
        ref = next((v for k, v in batch.items() if isinstance(v, Tensor) and k.startswith("observation.")), None)
        if ref is None:
            raise KeyError(f"the observation has no 'observation.*' tensor; it has {sorted(batch)}")
        n = ref.shape[0]
        if self._phase is None or self._phase.shape[0] != n:
            self.reset()
            self._phase = torch.zeros(n, device=ref.device, dtype=torch.float32)
        return n

    def executor(self):
        """The network that execution runs: the numpy copy on CPU (``numpy_execution``, rebuilt whenever a
        weight changes), else the torch model."""
        if not self.config.numpy_execution or self.training or self.model.frequencies.device.type != "cpu":
            return self.model
        key = tuple((p.data_ptr(), p._version) for p in self.model.parameters())
        if self._numpy_key != key:
            self._numpy_model, self._numpy_key = NumpyCNMP(self.model), key
        return self._numpy_model

    def _predict(self, batch: dict[str, Tensor], sensed: Tensor | None, queries: Tensor) -> tuple[Tensor, Tensor]:
        """(μ, σ) of the SM at ``queries`` [B, M] (normalized units), [B, M, D] each."""
        return self.executor()(self.execution_context(batch, self._phase, sensed), queries)

    @torch.no_grad()
    def predict_action_chunk(self, batch: dict[str, Tensor], **kwargs) -> Tensor:
        """The action predicted at the current phase, [B, 1, A] in the dataset's units (no phase update, no PD)."""
        self._ensure_state(batch)
        sensed = self.sensed_sm(batch) if self.config.spec.sensed else None
        mean, _ = self._predict(batch, sensed, self._phase[:, None])
        return self.normalizer.sm_inverse(mean[..., self.config.spec.commanded], self.config.spec.commanded)

    @torch.no_grad()
    def select_action(self, batch: dict[str, Tensor], **kwargs) -> Tensor:
        """One step of the execution loop (see the class docstring), for every env of the batch."""
        c = self.config
        spec = c.spec
        self._ensure_state(batch)  # resets the state of a new batch of envs
        self.normalizer.require()
        sensed = self.sensed_sm(batch) if spec.sensed else None
        if self._target is not None or self._expected is not None:  # not the first step: the phase may advance
            advance = torch.ones_like(self._phase, dtype=torch.bool)
            if c.online_feedback and c.phase_stop_threshold is not None and sensed is not None:
                advance = self.tracking_error(sensed) <= c.phase_stop_threshold
            self._phase = torch.where(advance, (self._phase + self.phase_step).clamp(max=1.0), self._phase)
        if spec.tied:
            mean, std = self._predict(batch, sensed, self._phase[:, None])
            target, std = mean[:, 0], std[:, 0]
            action = target
            if c.online_feedback and sensed is not None:
                error = target - sensed
                previous = self._error if self._error is not None else error
                kp, kd = self.pd_gains(std)
                action = sensed + kp * error + kd * (error - previous)
                self._error = error
            self._target = target
            return self.normalizer.sm_inverse(action)
        nxt = (self._phase + self.phase_step).clamp(max=1.0)
        mean, _ = self._predict(batch, sensed, torch.stack([self._phase, nxt], dim=1))
        self._expected = mean[:, 1]
        return self.normalizer.sm_inverse(mean[:, 0, spec.commanded], spec.commanded)


class FirstFrames:
    """Each training episode's first camera frame per image feature, read once from the dataset (LeRobot's own
    decoder) and kept as uint8 on the CPU: the image the conv encoder sees for that episode."""

    def __init__(self, dataset_meta, keys: list[str]):
        self.meta, self.keys = dataset_meta, list(keys)
        self.cache: dict[int, dict[str, Tensor]] = {}
        self._dataset = None
        eps = dataset_meta.episodes
        self.first = dict(zip(np.asarray(eps["episode_index"]).tolist(), np.asarray(eps["dataset_from_index"]).tolist(),
                              strict=True))

    def _load(self, ep: int) -> dict[str, Tensor]:
        if self._dataset is None:
            from lerobot.datasets.lerobot_dataset import LeRobotDataset

            self._dataset = LeRobotDataset(self.meta.repo_id, root=self.meta.root)
        mapping = self._dataset.absolute_to_relative_idx
        absolute = int(self.first[ep])
        item = self._dataset[mapping[absolute] if mapping else absolute]
        return {k: (item[k].clamp(0, 1) * 255).round().to(torch.uint8) for k in self.keys}

    def __call__(self, episode_index: Tensor) -> dict[str, Tensor]:
        eps = episode_index.reshape(-1).tolist()
        for e in set(eps):
            if e not in self.cache:
                if e not in self.first:
                    raise KeyError(f"episode {e} is not in the dataset")
                self.cache[e] = self._load(e)
        return {k: torch.stack([self.cache[e][k] for e in eps]).float() / 255.0 for k in self.keys}

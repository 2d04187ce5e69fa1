"""Conditional Neural Movement Primitives (Seker, Imre, Piater, Ugur, RSS 2019).

Read top-down:

1. ``sample_context_and_targets`` -- the training step's draw (paper Sec. III-B): from each demonstration
   in the batch, n ~ U{1..n_max} observations (t_i, SM(t_i)) and m ~ U{1..m_max} queries (t_q, SM(t_q)).
2. ``CNMP`` -- pure torch:  r_i = E([t_i, γ, SM_i ⊙ mask_i, mask_i]);  r = mean_i r_i  (``aggregate``);
   (μ_q, σ_q) = Q([t_q, γ, r])  (``decode``);  loss = -log N(SM(t_q) | μ_q, σ_q)  (``nll``, Eq. 1).
   With ``n_experts`` K > 1 (CNEP, Yildirim & Ugur 2024): K query networks Q_1..Q_K over the same r and a gate
   π = softmax(W_g r + b_g); loss = -log Σ_k π_k Π_q N_k (or CNEP's Σ_k π_k NLL_k) + gate entropy terms
   (``mixture_loss``); see ``CNMP``.
3. ``CNMPPolicy`` -- the LeRobot face: turns ``lerobot-train`` batches into episode samples for (1)-(2);
   execution (condition on goals + current state, predict the next SM) is :mod:`lerobot_cnmp.execution.executor`.

Everything works on padded batches with validity masks; padded entries never change an output.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F  # noqa: N812
from torch import Tensor, nn

from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot_cnmp.data.bank import EpisodeBank
from lerobot_cnmp.policy.configuration_cnmp import GATE_COMMIT, MIXTURE_NLL, CNMPConfig
from lerobot_cnmp.execution.executor import CNMPExecutor, check_finite


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


class ExpertMLPs(nn.Module):
    """K query networks Q_1..Q_K of one shape, their weights stacked so that each layer of all K experts is
    one batched matmul: ``weights[l]`` [K, out, in], ``biases[l]`` [K, out] (each expert initialized as
    ``nn.Linear`` initializes itself). ReLU between layers, none after the last, as :func:`mlp`."""

    def __init__(self, n_experts: int, in_dim: int, widths: tuple[int, ...]):
        super().__init__()
        self.weights, self.biases = nn.ParameterList(), nn.ParameterList()
        for w in widths:
            layers = [nn.Linear(in_dim, w) for _ in range(n_experts)]
            self.weights.append(nn.Parameter(torch.stack([m.weight.data for m in layers])))
            self.biases.append(nn.Parameter(torch.stack([m.bias.data for m in layers])))
            in_dim = w

    def forward(self, h: Tensor, start: int = 0) -> Tensor:
        """[K, N, in] -> [K, N, out]: layers ``start`` on (``h``: layer start - 1's output, before its ReLU)."""
        for i in range(start, len(self.weights)):
            if i > 0:
                h = F.relu(h)
            h = torch.baddbmm(self.biases[i][:, None, :], h, self.weights[i].transpose(1, 2))
        return h


class CNMP(nn.Module):
    """Encoder E -> mean aggregation -> query network Q with a Gaussian output (pure torch).

    ``n_experts`` K > 1 is CNEP's mixture decoder (Yildirim & Ugur, "Conditional Neural Expert Processes",
    arXiv 2402.08424): K query networks ("experts") Q_k over the same representation r and a gate
    π(r) = softmax(W_g r + b_g) over them (``decoders``, ``gate``). The experts predict (μ_k, σ_k) each; the
    gate says which of them the context r belongs to. ``forward`` / ``decode`` then return the most probable
    expert's (μ, σ); ``mixture`` returns all of them with π. K = 1 is the plain CNMP (``decoder``)."""

    def __init__(
        self,
        sm_dim: int,
        task_dim: int = 0,
        encoder_layers: tuple[int, ...] = (128, 128, 128),
        decoder_layers: tuple[int, ...] = (128, 128, 128),
        min_std: float = 0.01,
        phase_frequencies: int = 0,
        n_experts: int = 1,
        gate_entropy_coef: float = 0.2,
        batch_entropy_coef: float = 0.88,
        mixture_nll: str = "assigned",
        nll_beta: float = 0.0,
        gate_commit: str = "always",
        shared_decoder_layers: int = 0,
        assignment_draws: int = 0,
        unconditional_nll_coef: float = 1.0,
    ):
        super().__init__()
        if not float(n_experts).is_integer() or n_experts < 1:  # NaN and inf included
            raise ValueError(f"n_experts (the number of decoders K) must be an integer >= 1, got {n_experts}")
        self.sm_dim, self.task_dim, self.min_std = sm_dim, task_dim, min_std
        self.n_experts = int(n_experts)
        if mixture_nll not in MIXTURE_NLL:
            raise ValueError(f"mixture_nll must be one of {MIXTURE_NLL}, got {mixture_nll!r}")
        if nll_beta and self.n_experts > 1:
            raise ValueError(f"nll_beta (β-NLL) applies to the single decoder: use n_experts=1 or nll_beta=0, got "
                             f"n_experts={n_experts}, nll_beta={nll_beta}")
        self.gate_entropy_coef, self.batch_entropy_coef = gate_entropy_coef, batch_entropy_coef
        self.mixture_nll = mixture_nll
        if not float(assignment_draws).is_integer() or assignment_draws < 0:  # NaN and inf included
            raise ValueError(f"assignment_draws must be an integer >= 0, got {assignment_draws}")
        self.assignment_draws = int(assignment_draws)
        if not 0.0 < unconditional_nll_coef < float("inf"):  # NaN included
            raise ValueError(f"unconditional_nll_coef must be a finite number > 0, got {unconditional_nll_coef}")
        self.unconditional_nll_coef = float(unconditional_nll_coef)
        if gate_commit not in GATE_COMMIT:
            raise ValueError(f"gate_commit must be one of {GATE_COMMIT}, got {gate_commit!r}")
        self.gate_commit = gate_commit
        self.nll_beta = nll_beta
        self.register_buffer("dim_weights", None, persistent=False)  # [D] NLL weights; None: all 1 (Eq. 1)
        self.register_buffer(
            "frequencies", torch.pi * torch.arange(1, phase_frequencies + 1, dtype=torch.float32), persistent=False
        )
        t_dim = 1 + 2 * phase_frequencies
        self.encoder = mlp(t_dim + task_dim + 2 * sm_dim, tuple(encoder_layers))
        q_in, q_widths = t_dim + task_dim + encoder_layers[-1], (*decoder_layers, 2 * sm_dim)
        if self.n_experts == 1:  # the plain CNMP: today's parameter names, so its checkpoints load
            self.decoder = mlp(q_in, q_widths)
        else:  # CNEP: K experts and the gate over them, both reading the same r
            n_shared = int(shared_decoder_layers)
            if not 0 <= n_shared <= len(decoder_layers):
                raise ValueError(f"shared_decoder_layers must be between 0 and the {len(decoder_layers)} hidden layers "
                                 f"of decoder_layers, got {shared_decoder_layers}")
            if n_shared:  # a trunk of the query network shared by the experts, their own layers after it
                self.trunk = mlp(q_in, tuple(decoder_layers[:n_shared]))
                q_in, q_widths = decoder_layers[n_shared - 1], q_widths[n_shared:]
            self.decoders = ExpertMLPs(self.n_experts, q_in, q_widths)
            self.gate = nn.Linear(encoder_layers[-1], self.n_experts)
            # training state of mixture_nll="assigned" (not saved): each expert's running share of the episodes
            self.register_buffer("expert_share", torch.full((self.n_experts,), 1.0 / self.n_experts), persistent=False)

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
        With K > 1 experts: the most probable expert's (μ_k*, σ_k*), k* = argmax_k π_k(r).

        Q's first layer is linear in its input [t_q, γ, r], so it is computed as W_t·t_q + (W_γr·[γ, r] + b):
        the second term once per episode, not once per query (a 200-query trajectory costs little more than
        its last layers)."""
        if self.n_experts > 1:
            means, stds = self.decode_experts(r, query_phase, task_params)
            return pick_expert(means, stds, self.gate_probs(r).argmax(dim=-1))
        out = run_mlp(self.decoder, self._first_layer(self.decoder[0], r, query_phase, task_params), start=1)
        mean, raw = out.split(self.sm_dim, dim=-1)
        return mean, self.min_std + F.softplus(raw)

    def _first_layer(self, first: nn.Linear, r: Tensor, query_phase: Tensor, task_params: Tensor | None) -> Tensor:
        """A query network's first layer on [t_q, γ, r], [B, M, H]: W_t·t_q + (W_γr·[γ, r] + b), the second
        term once per episode (see ``decode``)."""
        t_dim = 1 + 2 * self.frequencies.numel()
        per_episode = self._inputs([], [r[:, None, :]], task_params, 1)  # [B, 1, G + R]
        return F.linear(per_episode, first.weight[:, t_dim:], first.bias) + F.linear(
            self.phase_features(query_phase), first.weight[:, :t_dim])

    def gate_probs(self, r: Tensor) -> Tensor:
        """π(r) = softmax(W_g r + b_g): each expert's probability of being the context's mode, [B, K]."""
        if self.n_experts == 1:
            return torch.ones(r.shape[0], 1, dtype=r.dtype, device=r.device)
        return torch.softmax(self.gate(r), dim=-1)

    def decode_experts(self, r: Tensor, query_phase: Tensor, task_params: Tensor | None = None
                       ) -> tuple[Tensor, Tensor]:
        """(μ_k, σ_k) = Q_k(t_q, γ, r) of every expert k, each [B, K, M, D] (first layer split as in ``decode``)."""
        if self.n_experts == 1:
            mean, std = self.decode(r, query_phase, task_params)
            return mean[:, None], std[:, None]
        q, k = self.decoders, self.n_experts
        if hasattr(self, "trunk"):  # shared hidden layers (first layer split as in ``decode``), then each expert's
            h = self._first_layer(self.trunk[0], r, query_phase, task_params)
            h = F.relu(run_mlp(self.trunk, h, start=1))  # [B, M, H]
            b, m, width = h.shape
            out = q(h.reshape(1, b * m, width).expand(k, -1, -1))
        else:
            t_dim = 1 + 2 * self.frequencies.numel()
            w0, b0 = q.weights[0], q.biases[0]  # [K, H, in], [K, H]
            per_episode = self._inputs([], [r[:, None, :]], task_params, 1)[:, 0]  # [B, G + R]
            per_episode = torch.einsum("bi,khi->kbh", per_episode, w0[:, :, t_dim:]) + b0[:, None, :]  # [K, B, H]
            per_query = torch.einsum("bmi,khi->kbmh", self.phase_features(query_phase), w0[:, :, :t_dim])
            h = per_episode[:, :, None, :] + per_query  # [K, B, M, H]
            _, b, m, width = h.shape
            out = q(h.reshape(k, b * m, width), start=1)
        mean, raw = out.reshape(k, b, m, 2 * self.sm_dim).transpose(0, 1).split(self.sm_dim, dim=-1)
        return mean, self.min_std + F.softplus(raw)

    def condition(self, context: Context) -> Tensor:
        """The representation r of a context (encode + aggregate)."""
        return self.aggregate(self.encode(context), context.valid)

    def forward(self, context: Context, query_phase: Tensor) -> tuple[Tensor, Tensor]:
        return self.decode(self.condition(context), query_phase, context.task_params)

    def mixture(self, context: Context, query_phase: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Every expert's prediction and probability: μ_k, σ_k [B, K, M, D] and π [B, K] (K = 1: π = 1)."""
        r = self.condition(context)
        means, stds = self.decode_experts(r, query_phase, context.task_params)
        return means, stds, self.gate_probs(r)

    @staticmethod
    def nll(mean: Tensor, std: Tensor, targets: Targets, beta: float = 0.0, dim_weights: Tensor | None = None) -> Tensor:
        """Eq. 1: -log N(SM(t_q) | μ_q, σ_q), summed over SM dims, averaged over the valid queries. With
        ``beta`` > 0, the β-NLL: each dim's term weighted by stop_gradient(σ^(2β)); ``dim_weights`` [D]: each
        dim's term weighted by it (``commanded_loss_weight``)."""
        per_dim = 0.5 * ((targets.values - mean) / std) ** 2 + std.log() + 0.5 * np.log(2 * np.pi)
        if beta:
            per_dim = per_dim * std.detach() ** (2.0 * beta)
        if dim_weights is not None:
            per_dim = per_dim * dim_weights
        per_query = per_dim.sum(dim=-1)
        w = targets.valid.to(per_query.dtype)
        return (per_query * w).sum() / w.sum().clamp(min=1.0)

    @staticmethod
    def nll_per_expert(means: Tensor, stds: Tensor, targets: Targets) -> Tensor:
        """NLL_bk: Eq. 1 of expert k on episode b, summed over SM dims and averaged over its valid queries, [B, K]."""
        y = targets.values[:, None]
        per_dim = 0.5 * ((y - means) / stds) ** 2 + stds.log() + 0.5 * np.log(2 * np.pi)
        w = targets.valid[:, None, :].to(per_dim.dtype)
        return (per_dim.sum(dim=-1) * w).sum(dim=-1) / w.sum(dim=-1).clamp(min=1.0)

    @torch.no_grad()
    def expert_similarity(self, r: Tensor, task_params: Tensor | None = None, n_phases: int = 21) -> Tensor:
        """s_bkl = exp(-max_t mean_d (μ_bk(t) - μ_bl(t))² / (σ_bk(t)² + σ_bl(t)²)), [B, K, K], without gradient:
        1 where experts k and l predict the same trajectory for context b (within their σ, on average over the
        SM dims, at every phase of a fixed grid of ``n_phases`` in [0, 1]), near 0 where they predict different
        modes anywhere. (A sum over the D dims instead of the mean made s ≈ 0 for every pair on the 11-dim
        weights task, so the term never acted.)"""
        grid = torch.linspace(0.0, 1.0, n_phases, dtype=r.dtype, device=r.device).expand(r.shape[0], -1)
        means, stds = self.decode_experts(r, grid, task_params)  # [B, K, T, D]
        diff = (means[:, :, None] - means[:, None, :]) ** 2  # [B, K, K, T, D]
        var = stds[:, :, None] ** 2 + stds[:, None, :] ** 2
        return torch.exp(-(diff / var).mean(dim=-1).amax(dim=-1))

    def mixture_loss(self, nll_bk: Tensor, probs: Tensor, n_queries: Tensor,
                     similarity: Tensor | None = None, prior: tuple[Tensor, ...] | None = None
                     ) -> tuple[Tensor, dict]:
        """The mixture's loss from each expert's Eq. 1 NLL_bk on each episode b [B, K] (``nll_per_expert``),
        the gate's π_b [B, K] and each episode's number of valid queries n_b [B] (``prior``, for
        ``"assigned"``: the empty context's NLL⁰ [E, K], π⁰ [E, K] and number of queries n⁰ [E], E = B, or one
        row per episode of B / E draws with ``assignment_draws``, ρ then repeated over the episode's draws):

            L = NLL_mix
                + gate_entropy_coef  · mean_b c_b H(π_b) / log K  -- low per-episode entropy: commit to one expert
                - batch_entropy_coef · H(mean_b π_b) / log K      -- high batch entropy: use every expert

        with c_b = 1 (``gate_commit="always"``) or c_b = 1 - H(π_b) / log K, without gradient
        (``"where_decided"``): the commitment is asked in proportion to how decided the gate already is, so a
        context the gate spreads over several modes (≈ 1/4 each for four zones) is left to the likelihood,
        which keeps π a posterior there, while a context the gate leans on keeps being pushed to one expert
        (the likelihood alone is indifferent between experts that fit a decided context equally well).
        ``gate_commit="redundant"`` replaces the entropy by the gate's mass split between experts that predict
        the same trajectory for the context, s_bkl from ``expert_similarity`` [B, K, K] (required then):

            + gate_entropy_coef · mean_b Σ_{k≠l} π_bk π_bl s_bkl / (1 - 1/K)   -- 1 for a uniform gate over
                                                                               K identical experts

        so splitting π over experts that say the same thing (a decided context: after the lift, every
        expert that fits it) is penalized, and splitting it over experts that predict different modes (a
        context shared by modes: before the grasp) costs nothing: that part of π stays the likelihood's
        posterior. Unlike ``"where_decided"`` it reads the experts' predictions, not the gate, so a gate that
        leans does not push itself further.

        with NLL_mix, by ``mixture_nll``:

        * ``"cnep"`` (CNEP's ``models/cnep.py``, yildirimyigit/cnep): mean_b Σ_k π_bk NLL_bk, the expected NLL
          under the gate. Its gradient moves the gate's whole mass to the expert that explains the episode
          best (a hard choice, what execution commits to) and trains each expert on the episodes the gate
          gives it. Where the context does not decide the mode it still commits (π is not a posterior).
        * ``"likelihood"``: -mean_b (1/n_b) log Σ_k π_bk Π_q N(y_bq | μ_bkq, σ_bkq), the mixture likelihood of
          the episode's queries (one mode per episode, so the product over queries sits inside the sum).
          Each expert is trained with the posterior responsibility of the episode; π is calibrated: a
          context shared by M modes gets π ≈ 1/M on them (the weights task before the grasp). The
          responsibility is re-made for every context, and where the context decides the mode nothing ties
          it to the mode's expert: one expert can cover two modes (told apart through r) while another stays
          idle and π splits between them (weights task: π > 0.9 after the lift on 47.5-75 % of the masses on
          5 training seeds of 6).
        * ``"assigned"``: the episode's expert is decided from its queries (the context's points among them
          with ``context_in_targets``) by the mixture on the *empty* context (r = 0: the experts'
          unconditional predictions μ⁰_k, σ⁰_k and gate π⁰ = π(0); γ kept), the same for whatever context is
          drawn from the episode, and the context's experts and gate are trained on that expert:

              NLL_mix = -c mean_b (1/n_b) log Σ_k π⁰_k Π_q N(y_bq | μ⁰_bkq, σ⁰_bkq)  -- the unconditional mixture
                        + mean_b Σ_k ρ_bk (NLL_bk - log π_bk)                          -- the context's experts, gate

          with ρ_bk = π⁰_k Π_q N⁰_bkq / Σ_l π⁰_l Π_q N⁰_blq (no gradient; ``revive_starving`` gives an idle
          expert an episode) and c = ``unconditional_nll_coef``. The gate's cross-entropy to ρ counts once per
          episode, one label each, not divided by n_b as the likelihood's log π is: so divided, the gate
          learned too slowly. The modes are
          the clusters of the unconditional mixture; a context that decides the mode gets π ≈ one-hot on its
          episode's expert, one shared by modes the share of its episodes among them (≈ 1/4 each before the
          weights task's grasp). The batch entropy then acts on the
          unconditional mixture's per-query posterior softmax_k(log π⁰_k - NLL⁰_bk), which keeps a gradient
          where the whole episode's posterior is one-hot. One more pass of the decoder per step (with
          ``assignment_draws`` = p: each episode's first p draws only, their rows in the context's pass).

        Entropies are divided by log K (1 for a uniform gate). CNEP's coefficients: its loss is
        16.81·(K/2)·(1/K)·Σ_k π_k NLL_k - 10.672·(log 2/log K)·H_batch + 7.553·(log 2/log K)·H_ind
        (``scale_coefs``, mean over decoders); divided by its NLL weight 8.405 this is the form above with
        7.553·log 2/8.405 = 0.62 and 10.672·log 2/8.405 = 0.88, for any K. (CNEP averages its NLL over SM
        dims, Eq. 1 here sums them: with D > 1 dims the entropy terms weigh relatively D times less.) The
        defaults, ``"assigned"`` with gate_entropy_coef 0.2 and CNEP's 0.88, meet the sine, weights and
        shared-obstacle bars of README "Mixture decoder"; the likelihood meets the training-cost bar, which
        ``"assigned"`` misses (on demos without modes) unless its unconditional term is weighted down
        (``unconditional_nll_coef`` 0.25, with ``assignment_draws`` 1 and the whole trunk shared: all four bars)."""
        log_k = float(np.log(self.n_experts))
        with torch.no_grad():  # reported; the loss of "cnep" (recomputed there with its gradient)
            expected = (probs * nll_bk).sum(dim=-1).mean()
        n = n_queries.to(nll_bk.dtype).clamp(min=1.0)
        batch_probs = probs
        extra = {}
        if self.mixture_nll == "cnep":
            nll = (probs * nll_bk).sum(dim=-1).mean()
        elif self.mixture_nll == "likelihood":
            log_lik = torch.logsumexp(probs.clamp(min=1e-12).log() - nll_bk * n[:, None], dim=-1)  # log Σ π Π N
            nll = -(log_lik / n).mean()
        else:  # "assigned"
            if prior is None:
                raise ValueError("mixture_nll='assigned' needs the experts' NLLs and gate on the empty context (prior)")
            prior_nll_bk, prior_probs, n0 = prior
            n0 = n0.to(nll_bk.dtype).clamp(min=1.0)
            log_joint = prior_probs.clamp(min=1e-12).log() - prior_nll_bk * n0[:, None]  # log π⁰_k Π N⁰_k
            prior_nll = -(torch.logsumexp(log_joint, dim=-1) / n0).mean()
            rho = torch.softmax(self.revive_starving(log_joint.detach()), dim=-1)
            if rho.shape[0] != nll_bk.shape[0]:  # one assignment per episode, shared by its draws
                rho = rho.repeat_interleave(nll_bk.shape[0] // rho.shape[0], dim=0)
            assigned = (rho * (nll_bk - probs.clamp(min=1e-12).log())).sum(dim=-1).mean()
            nll = self.unconditional_nll_coef * prior_nll + assigned
            batch_probs = torch.softmax(prior_probs.clamp(min=1e-12).log() - prior_nll_bk, dim=-1)
            extra = {"prior_nll": prior_nll.item(), "assigned_nll": assigned.item(),
                     "min_expert_share": rho.mean(dim=0).min().item()}
        h = entropy(probs)
        commit = (1.0 - h / log_k).clamp(min=0.0).detach() if self.gate_commit == "where_decided" else None
        if self.gate_commit == "redundant":
            if similarity is None:
                raise ValueError("gate_commit='redundant' needs the experts' similarity (CNMP.expert_similarity)")
            off_diag = similarity * (1.0 - torch.eye(self.n_experts, dtype=probs.dtype, device=probs.device))
            split = torch.einsum("bk,bkl,bl->b", probs, off_diag, probs) / (1.0 - 1.0 / self.n_experts)
            ind_entropy = split.mean()
        else:
            ind_entropy = (h.mean() if commit is None else (commit * h).mean()) / log_k
        batch_entropy = entropy(batch_probs.mean(dim=0)) / log_k
        loss = nll + self.gate_entropy_coef * ind_entropy - self.batch_entropy_coef * batch_entropy
        info = {"nll": nll.item(), "expected_nll": expected.item(), "gate_entropy": ind_entropy.item(),
                "batch_entropy": batch_entropy.item(), **extra}
        if commit is not None:
            info["gate_commit_weight"] = commit.mean().item()
        return loss, info

    @torch.no_grad()
    def revive_starving(self, log_joint: Tensor, momentum: float = 0.99) -> Tensor:
        """The assignment scores log π⁰_k Π_q N⁰_bk [B, K] with k-means' remedy for an empty cluster: in training,
        each expert's share of the episodes is tracked (a running mean of the hard assignments, ``momentum``
        per call: one per ``training_loss``, two per step with ``feedback_draw_weight`` > 0); an expert whose
        share falls below 1 / (4K) is given, in this batch, the episode it fits least badly relative to that
        episode's expert (the smallest gap max_l s_bl - s_bk). Trained on it,
        it takes that mode over or drops it. Without this an expert that loses every episode early (the hard
        posterior of a whole episode leaves it no gradient) stays idle while another covers two modes."""
        if not self.training:
            return log_joint
        k = self.n_experts
        hard = F.one_hot(log_joint.argmax(dim=-1), k).to(self.expert_share.dtype).mean(dim=0)
        self.expert_share.mul_(momentum).add_((1.0 - momentum) * hard)
        starving = (self.expert_share < 1.0 / (4 * k)).nonzero().flatten().tolist()
        if not starving:
            return log_joint
        out, taken = log_joint.clone(), torch.zeros(log_joint.shape[0], dtype=torch.bool, device=log_joint.device)
        gap = log_joint.amax(dim=-1, keepdim=True) - log_joint  # [B, K], 0 for the episode's own expert
        for e in starving:
            b = int(gap[:, e].masked_fill(taken, float("inf")).argmin())
            if not taken[b]:
                out[b] = float("-inf")
                out[b, e] = 0.0
                taken[b] = True
        return out

    def training_loss(self, context: Context, targets: Targets, draws: int = 1) -> tuple[Tensor, dict]:
        """One training step's loss on a drawn (context, targets) pair, with monitoring figures. ``draws``: rows
        b * draws .. b * draws + draws - 1 are draws of one episode (``assignment_draws``)."""
        if self.n_experts > 1:
            r = self.condition(context)
            similarity = self.expert_similarity(r, context.task_params) if self.gate_commit == "redundant" else None
            prior = None
            if self.mixture_nll == "assigned" and self.assignment_draws:
                # each episode's expert from the queries of its first p draws, decided by the experts and gate on
                # the empty context (r = 0), whose rows join the context's in one decoder pass
                nll_bk, means, stds, probs, prior = self._with_episode_prior(r, context.task_params, targets, draws)
            else:
                means, stds = self.decode_experts(r, targets.phase, context.task_params)
                probs, nll_bk = self.gate_probs(r), self.nll_per_expert(means, stds, targets)
                if self.mixture_nll == "assigned":  # each draw's expert from its own queries
                    means0, stds0, probs0 = self.unconditional(targets.phase, context.task_params)
                    prior = (self.nll_per_expert(means0, stds0, targets), probs0, targets.valid.sum(-1))
            loss, info = self.mixture_loss(nll_bk, probs, targets.valid.sum(-1), similarity, prior)
            with torch.no_grad():  # for the monitoring figures only
                mean, std = pick_expert(means, stds, probs.argmax(dim=-1))
        else:
            mean, std = self(context, targets.phase)
            loss = self.nll(mean, std, targets, self.nll_beta, self.dim_weights)
            info = {"nll": loss.item()}
        with torch.no_grad():
            w = targets.valid[..., None].to(mean.dtype)
            mae = ((mean - targets.values).abs() * w).sum() / (w.sum() * mean.shape[-1]).clamp(min=1.0)
            mean_std = (std * w).sum() / (w.sum() * mean.shape[-1]).clamp(min=1.0)
        return loss, {**info, "mae": mae.item(), "std": mean_std.item()}

    def _with_episode_prior(self, r: Tensor, task_params: Tensor | None, targets: Targets, draws: int
                            ) -> tuple[Tensor, Tensor, Tensor, Tensor, tuple[Tensor, Tensor, Tensor]]:
        """The context's NLL_bk [B, K], μ_k and σ_k [B, K, M, D] and gate π [B, K], and the ``prior`` of
        ``mixture_loss`` with ``assignment_draws`` = p: the empty-context experts' NLL per episode (per query,
        over the queries of its first p of ``draws`` draws) [E, K], the empty-context gate [E, K] and the number
        of those queries [E]. The empty context's rows (r = 0) go through the decoder with the context's."""
        b = targets.phase.shape[0]
        if b % draws:
            raise ValueError(f"{b} draws are not a whole number of episodes of {draws} draws each")
        p = min(self.assignment_draws, draws)
        rows = torch.arange(b, device=targets.phase.device).reshape(b // draws, draws)[:, :p].reshape(-1)
        r_all = torch.cat([r, r.new_zeros(rows.numel(), r.shape[1])])
        every = Targets(*(torch.cat([x, x[rows]]) for x in (targets.phase, targets.values, targets.valid)))
        gamma = None if task_params is None else torch.cat([task_params, task_params[rows]])
        means, stds = self.decode_experts(r_all, every.phase, gamma)
        nll_all, probs_all = self.nll_per_expert(means, stds, every), self.gate_probs(r_all)
        n_row = every.valid[b:].sum(-1).to(nll_all.dtype)
        total = (nll_all[b:] * n_row[:, None]).reshape(b // draws, p, -1).sum(1)
        n_ep = n_row.reshape(b // draws, p).sum(1)
        prior = (total / n_ep.clamp(min=1.0)[:, None], probs_all[b::p], n_ep)
        return nll_all[:b], means[:b], stds[:b], probs_all[:b], prior

    def unconditional(self, query_phase: Tensor, task_params: Tensor | None) -> tuple[Tensor, Tensor, Tensor]:
        """The unconditional mixture: the experts μ⁰_k, σ⁰_k [B, K, M, D] and gate π⁰ [B, K] on the empty context
        (r = 0; γ kept)."""
        r0 = query_phase.new_zeros(query_phase.shape[0], self.gate.in_features)
        means0, stds0 = self.decode_experts(r0, query_phase, task_params)
        return means0, stds0, self.gate_probs(r0)


def entropy(p: Tensor) -> Tensor:
    """H(p) = -Σ_k p_k log p_k over the last dim (0 log 0 = 0)."""
    return -(p * p.clamp(min=1e-12).log()).sum(dim=-1)


def pick_expert(means: Tensor, stds: Tensor, k: Tensor) -> tuple[Tensor, Tensor]:
    """Expert ``k[b]``'s (μ, σ) of each episode b: [B, K, M, D] -> [B, M, D] each."""
    idx = k.long()[:, None, None, None].expand(-1, 1, *means.shape[2:])
    return means.gather(1, idx)[:, 0], stds.gather(1, idx)[:, 0]


class NumpyCNMP:
    """A frozen numpy copy of a :class:`CNMP` for execution on CPU: the same inference equations (encode,
    masked-mean aggregate, decode with Q's first layer split) on the same weights.

    A batch-1 control step is ~25 small ops; torch spends several µs of dispatch on each, numpy about one,
    so this runs a control step 2-4x faster on CPU. Training stays in torch; the policy rebuilds this copy
    whenever the weights change. ``tests/test_model.py`` checks it against :class:`CNMP`."""

    def __init__(self, model: CNMP):
        if model.n_experts != 1:
            raise ValueError(f"NumpyCNMP copies a single-decoder CNMP; this one has {model.n_experts} experts "
                             "(a mixture executes with the torch model)")

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
        self._ready_key: tuple | None = None  # the buffers' identity and versions that `ready` last read
        self._ready = False

    @property
    def ready(self) -> bool:
        # checked every control step: the answer is kept until a buffer changes (in place, loaded or moved)
        key = (self.sm_std.data_ptr(), self.sm_std._version, self.task_std.data_ptr(), self.task_std._version)
        if self._ready_key != key:
            self._ready = bool(torch.isfinite(self.sm_std).all()) and bool(torch.isfinite(self.task_std).all())
            self._ready_key = key
        return self._ready

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
    (:class:`~lerobot_cnmp.data.bank.EpisodeBank`, read from the dataset when LeRobot builds the policy with
    ``dataset_meta``, or given by the in-memory API). One sampler and one loss serve both paths.

    Execution (``select_action``, ``predict_action_chunk``, ``reset``) is forwarded to
    :class:`~lerobot_cnmp.execution.executor.CNMPExecutor` (``self.executor``), which holds the execution state and its
    own settings (``config.execution``): the paper's loop of Sec. III / Fig. 3, chunks and RTC. The user's
    conditions: ``config.conditions`` (``--policy.conditions``) or :meth:`set_conditions`.
    With a mixture (``n_experts`` > 1) the executor follows the expert that
    :class:`~lerobot_cnmp.execution.modes.ModeSelector` picks: chosen at the first step, switched only when
    re-conditioning makes another expert more probable by ``mode_switch_margin``.
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
            n_experts=config.n_experts,
            gate_entropy_coef=config.gate_entropy_coef,
            batch_entropy_coef=config.batch_entropy_coef,
            mixture_nll=config.mixture_nll,
            nll_beta=config.nll_beta,
            gate_commit=config.gate_commit,
            shared_decoder_layers=config.shared_decoder_layers,
            assignment_draws=config.assignment_draws,
            unconditional_nll_coef=config.unconditional_nll_coef,
        )
        self.normalizer = SMNormalizer(config.sm_dim, config.task_dim)
        spec = config.spec
        if config.commanded_loss_weight != 1.0 and not spec.tied:
            weights = torch.ones(config.sm_dim)
            weights[list(spec.commanded)] = config.commanded_loss_weight
            self.model.dim_weights = weights
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
        self._numpy_model: NumpyCNMP | None = None  # execution copy of self.model, see network()
        self._numpy_key: tuple | None = None
        self._numpy_params: tuple | None = None  # (model, its parameters): what the numpy copy's key reads
        self.executor = CNMPExecutor(self)  # the execution loop and its state (validates the user's conditions)

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
        """The model card (``lerobot-train --policy.push_to_hub=true``, ``lerobot-cnmp-push``):
        :func:`lerobot_cnmp.hub.model_card`."""
        from lerobot_cnmp.policy.card import model_card

        return model_card(self.config, dataset_repo_id, license=license, tags=tags, cfg=cfg, eval_info=eval_info,
                          repo_id=repo_id)

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
        loss, info = self.model.training_loss(context, targets, c.draws_per_sample)
        w = c.feedback_draw_weight
        if w > 0:
            fb_draws = self.feedback_draws(batch["episode_index"], generator, inputs=episodes.task_params)
            fb_loss, fb_info = self.model.training_loss(*fb_draws, c.draws_per_sample)
            info = {**info, "nll_random": info["nll"], "nll_feedback": fb_info["nll"]}
            loss = (1.0 - w) * loss + w * fb_loss
            info["nll"] = loss.item()
        return loss, info

    def feedback_draws(self, episode_index: Tensor, generator: torch.Generator | None = None,
                       inputs: Tensor | None = None) -> tuple[Context, Targets]:
        """Execution-shaped draws (``feedback_draw_weight``), ``draws_per_sample`` per named episode: the
        context is the sensed dims at the episode's first frame (with ``condition_on_start``) and at a uniform
        frame j; the queries are j, j + 1 and ``feedback_draw_queries`` (default ``m_max_targets``) uniform frames.
        ``inputs``: the episode-level
        input already computed for these draws (``episodes_for``'s ``task_params``); None computes it."""
        c = self.config
        dev = self.normalizer.sm_std.device
        episode_index = episode_index.reshape(-1)
        if inputs is None:
            inputs = self._training_inputs(episode_index, c.draws_per_sample)
        m = c.m_max_targets if c.feedback_draw_queries is None else int(c.feedback_draw_queries)
        values, phase = self.bank.draw_feedback(episode_index.repeat_interleave(c.draws_per_sample), m, generator)
        values, phase = self.normalizer.sm(values.to(dev)), phase.to(dev)
        first = 0 if c.execution.condition_on_start else 1
        n_ctx = 2 - first
        b = values.shape[0]
        mask = self.sensed_only_mask[None, None, :].expand(b, n_ctx, -1)
        context = Context(phase[:, first:2], values[:, first:2], mask,
                          torch.ones(b, n_ctx, dtype=torch.bool, device=dev), inputs)
        targets = Targets(phase[:, 1:], values[:, 1:], torch.ones(b, phase.shape[1] - 1, dtype=torch.bool, device=dev))
        return context, targets

    def get_optim_params(self) -> dict:
        return self.parameters()

    # ---- execution (lerobot_cnmp.execution.executor) ---------------------------------------------------------------

    def reset(self) -> None:
        """Restart every env's execution state (called by lerobot-eval / lerobot-rollout at each episode start);
        the user's conditions stay."""
        if getattr(self, "executor", None) is not None:
            self.executor.reset()

    def network(self):
        """The network that execution runs: the numpy copy on CPU (``execution.numpy_execution``, rebuilt
        whenever a weight changes), else the torch model."""
        if (not self.config.execution.numpy_execution or self.training or self.model.frequencies.device.type != "cpu"
                or self.model.n_experts > 1):
            return self.model
        if self._numpy_params is None or self._numpy_params[0] is not self.model:  # module traversal once
            self._numpy_params = (self.model, list(self.model.parameters()))
        key = tuple((p.data_ptr(), p._version) for p in self._numpy_params[1])
        if self._numpy_key != key:
            self._numpy_model, self._numpy_key = NumpyCNMP(self.model), key
        return self._numpy_model

    def task_params(self, batch: dict[str, Tensor]) -> Tensor | None:
        """γ read from the observation (raw units), [B, G]; None when the CNMP has no task features."""
        parts = []
        for key, size in self.config.spec.task_features:
            if key not in batch:
                raise KeyError(f"this CNMP is conditioned on task parameters: the observation needs {key!r}; it has "
                               f"{sorted(batch)}")
            g = batch[key]
            g = g.reshape(g.shape[0], -1) if g.ndim != 3 else g[:, 0]
            if g.shape[-1] != size:
                raise ValueError(f"task feature {key!r} has {g.shape[-1]} values, the CNMP was trained with {size}")
            check_finite(key, g)
            parts.append(g.float())
        return torch.cat(parts, dim=-1) if parts else None

    def episode_inputs(self, batch: dict[str, Tensor]) -> Tensor | None:
        """The episode-level input of E and Q read at the first step of the episode: γ and the embedding of
        each image feature, [B, episode_dim]; None when there is neither."""
        c = self.config
        gamma = self.task_params(batch)
        parts = [] if gamma is None else [self.normalizer.task(gamma)]
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

    def set_conditions(self, conditions) -> None:
        """Give (or change, mid-episode: the next action is planned with them) the user's conditions, in the
        dataset's units and dim names: see :meth:`lerobot_cnmp.execution.executor.CNMPExecutor.set_conditions`."""
        self.executor.set_conditions(conditions)

    def supports_rtc(self) -> bool:
        """CNMP does Real-Time Chunking natively: it conditions the new chunk on the leftover actions."""
        return True

    @torch.no_grad()
    def predict_action_chunk(self, batch: dict[str, Tensor], inference_delay: int = 0,
                             prev_chunk_left_over: Tensor | None = None, n_steps: int | None = None,
                             return_std: bool = False, timestep: int | None = None, **kwargs):
        """The planned actions from the current phase over the next ``execution.n_action_steps`` (or
        ``n_steps``), [B, n, A] in the dataset's units (the predicted mean; σ with ``return_std=True``, and
        always in ``policy.executor.last_std``); the phase clock moves to the chunk's last step. RTC:
        ``prev_chunk_left_over`` [T, A] and ``inference_delay``; async: ``timestep`` of the observation (see
        :mod:`lerobot_cnmp.execution.executor`)."""
        actions, std = self.executor.chunk(batch, n_steps, inference_delay, prev_chunk_left_over, timestep)
        return (actions, std) if return_std else actions

    @torch.no_grad()
    def select_action(self, batch: dict[str, Tensor], **kwargs) -> Tensor:
        """One step of the execution loop for every env of the batch (:meth:`CNMPExecutor.step`)."""
        return self.executor.step(batch)


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

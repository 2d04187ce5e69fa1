"""Conditional Neural Movement Primitives (Seker, Imre, Piater, Ugur, RSS 2019), pure torch.

    r_i = E([t_i, γ, SM_i ⊙ mask_i, mask_i])          ``encode``
    r   = mean_i r_i                                   ``average``
    (μ_q, σ_q) = Q([t_q, γ, r])                        ``decode``
    μ_q += A(t_q)·γ,  A(t) = Σ_k φ_k(t) A_k            ``task_gain`` (optional: ProMP's linear map from γ)
    loss = -log N(SM(t_q) | μ_q, σ_q)                  ``nll`` (Eq. 1), ``training_loss``

Everything works on padded batches with validity masks; padded entries never change an output. A subclass
changes the query network by overriding ``build_decoder``, ``decode`` and ``training_loss``
(:class:`lerobot_cnmp.model.mixture.MixtureCNMP`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F  # noqa: N812
from torch import Tensor, nn


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
    """Queries to predict: SM ``values`` at ``phase``."""

    phase: Tensor  # [B, M]
    values: Tensor  # [B, M, D]
    valid: Tensor  # [B, M] bool


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
    (the paper: 8, 16, 32, 64), then a linear layer to ``embed_dim`` from the flattened map, or with
    ``keypoints`` from the spatial softmax's expected (x, y) per channel of the last map (not pooled). With
    ``downsample`` > 1 the image is first average-pooled by that factor; with ``center`` the buffer
    ``mean_image`` (set from the training demos' first frames, saved with the weights) is subtracted first."""

    def __init__(self, in_shape: tuple[int, int, int], channels: tuple[int, ...], embed_dim: int,
                 keypoints: bool = False, downsample: int = 1, center: bool = False):
        super().__init__()
        c, h, w = in_shape
        self.register_buffer("mean_image", torch.zeros(in_shape) if center else None)
        layers: list[nn.Module] = []
        if downsample > 1:
            layers.append(nn.AvgPool2d(downsample))
            h, w = h // downsample, w // downsample
        for i, width in enumerate(channels):
            layers += [nn.Conv2d(c, width, 3, padding=1), nn.ReLU()]
            c = width
            if not (keypoints and i == len(channels) - 1):
                layers.append(nn.MaxPool2d(2))
                h, w = h // 2, w // 2
        self.conv = nn.Sequential(*layers)
        self.keypoints = keypoints
        if keypoints:  # pixel-centre coordinates in [-1, 1] of the last map
            self.register_buffer("grid_x", torch.linspace(-1, 1, w).repeat(h), persistent=False)
            self.register_buffer("grid_y", torch.linspace(-1, 1, h).repeat_interleave(w), persistent=False)
        self.project = nn.Linear(2 * c if keypoints else c * h * w, embed_dim)

    def forward(self, images: Tensor, shift: int = 0, generator: torch.Generator | None = None) -> Tensor:
        """[B, E] from images [B, C, H, W] in [0, 1]; ``shift`` > 0: randomly shifted first (training)."""
        if self.mean_image is not None:
            images = images - self.mean_image
        maps = self.conv(random_shift(images, shift, generator))
        if not self.keypoints:
            return self.project(maps.flatten(1))
        attention = maps.flatten(2).softmax(dim=-1)  # [B, C, h w]: where each channel fires
        xy = torch.cat([attention @ self.grid_x, attention @ self.grid_y], dim=-1)  # [B, 2 C]
        return self.project(xy)


def random_shift(images: Tensor, pad: int, generator: torch.Generator | None = None) -> Tensor:
    """Each image of [B, C, H, W] padded by ``pad`` pixels (edges repeated) and cropped back to H x W at a
    random offset (DrQ's augmentation)."""
    if pad <= 0:
        return images
    b, _, h, w = images.shape
    padded = F.pad(images, (pad, pad, pad, pad), mode="replicate")
    offsets = torch.randint(0, 2 * pad + 1, (b, 2), generator=generator)
    return torch.stack([padded[i, :, y:y + h, x:x + w] for i, (y, x) in enumerate(offsets.tolist())])


def fit_figures(mean: Tensor, std: Tensor, targets: Targets) -> dict[str, float]:
    """Monitoring figures of a prediction at the valid queries: mean |μ - y| and mean σ over queries and dims."""
    with torch.no_grad():
        w = targets.valid[..., None].to(mean.dtype)
        mae = ((mean - targets.values).abs() * w).sum() / (w.sum() * mean.shape[-1]).clamp(min=1.0)
        mean_std = (std * w).sum() / (w.sum() * mean.shape[-1]).clamp(min=1.0)
    return {"mae": mae.item(), "std": mean_std.item()}


class CNMP(nn.Module):
    """Encoder E -> mean aggregation -> query network Q with a Gaussian output (pure torch).

    ``nll_beta`` > 0 trains with the β-NLL; ``dim_weights`` (a buffer, [D] or None) weights each SM dim's
    NLL term. ``linear_task_term`` adds to μ a term linear in γ, A(t)·γ with A(t) = Σ_k φ_k(t) A_k over the
    phase basis φ(t) = [1, t, sin kπt, cos kπt] (the parameter ``task_gain`` = [A_k], zero at the start): the
    contextual ProMP's map from γ, which the MLP then corrects. ``build_decoder``, ``decode`` and
    ``training_loss`` are the points a subclass overrides."""

    def __init__(
        self,
        sm_dim: int,
        task_dim: int = 0,
        encoder_layers: tuple[int, ...] = (128, 128, 128),
        decoder_layers: tuple[int, ...] = (128, 128, 128),
        min_std: float = 0.01,
        phase_frequencies: int = 0,
        nll_beta: float = 0.0,
        linear_task_term: bool = False,
    ):
        super().__init__()
        if linear_task_term and not task_dim:
            raise ValueError("linear_task_term needs task parameters γ (task_dim > 0): the term is linear in γ")
        self.sm_dim, self.task_dim, self.min_std, self.nll_beta = sm_dim, task_dim, min_std, nll_beta
        self.register_buffer("dim_weights", None, persistent=False)  # [D] NLL weights; None: all 1 (Eq. 1)
        self.register_buffer(
            "frequencies", torch.pi * torch.arange(1, phase_frequencies + 1, dtype=torch.float32), persistent=False
        )
        t_dim = 1 + 2 * phase_frequencies
        self.encoder = mlp(t_dim + task_dim + 2 * sm_dim, tuple(encoder_layers))
        self.build_decoder(t_dim + task_dim + encoder_layers[-1], (*decoder_layers, 2 * sm_dim))
        # [D, (1 + t_dim) G]: the A_k of A(t)·γ; zeros (no RNG draw), so the MLP's initialization is unchanged
        self.task_gain = nn.Parameter(torch.zeros(sm_dim, (1 + t_dim) * task_dim)) if linear_task_term else None

    def build_decoder(self, in_dim: int, widths: tuple[int, ...]) -> None:
        """Q: an MLP from [t_q, γ, r] (``in_dim``) through ``widths`` (the hidden layers, then 2 D: μ and σ's
        pre-activation)."""
        self.decoder = mlp(in_dim, widths)

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
    def average(r_i: Tensor, valid: Tensor) -> Tensor:
        """The aggregation r = mean of the valid r_i, [B, R] (order- and padding-invariant)."""
        w = valid.to(r_i.dtype)
        return torch.bmm(w[:, None, :], r_i)[:, 0] / w.sum(dim=1, keepdim=True).clamp(min=1.0)

    def condition(self, context: Context) -> Tensor:
        """The representation r of a context (``encode``, then ``average``)."""
        return self.average(self.encode(context), context.valid)

    def decode(self, r: Tensor, query_phase: Tensor, task_params: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """(μ, σ) = Q(t_q, γ, r) for every query phase, each [B, M, D]; σ = min_std + softplus(.).

        Q's first layer is linear in its input [t_q, γ, r], so it is computed as W_t·t_q + (W_γr·[γ, r] + b):
        the second term once per episode, not once per query (a 200-query trajectory costs little more than
        its last layers)."""
        out = run_mlp(self.decoder, self._first_layer(self.decoder[0], r, query_phase, task_params), start=1)
        mean, raw = out.split(self.sm_dim, dim=-1)
        if self.task_gain is not None:
            mean = mean + self.linear_in_task(query_phase, task_params)
        return mean, self.min_std + F.softplus(raw)

    def linear_in_task(self, query_phase: Tensor, task_params: Tensor) -> Tensor:
        """A(t_q)·γ = Σ_k φ_k(t_q) A_k γ for every query, [B, M, D]; φ = [1, ``phase_features``]."""
        phi = torch.cat([torch.ones_like(query_phase)[..., None], self.phase_features(query_phase)], dim=-1)
        return F.linear((phi[..., :, None] * task_params[:, None, None, :]).flatten(-2), self.task_gain)

    def _first_layer(self, first: nn.Linear, r: Tensor, query_phase: Tensor, task_params: Tensor | None) -> Tensor:
        """A query network's first layer on [t_q, γ, r], [B, M, H]: W_t·t_q + (W_γr·[γ, r] + b), the second
        term once per episode (see ``decode``)."""
        t_dim = 1 + 2 * self.frequencies.numel()
        per_episode = self._inputs([], [r[:, None, :]], task_params, 1)  # [B, 1, G + R]
        return F.linear(per_episode, first.weight[:, t_dim:], first.bias) + F.linear(
            self.phase_features(query_phase), first.weight[:, :t_dim])

    def forward(self, context: Context, query_phase: Tensor) -> tuple[Tensor, Tensor]:
        """(μ, σ) of the SM at ``query_phase`` [B, M] given ``context``, each [B, M, D]."""
        return self.decode(self.condition(context), query_phase, context.task_params)

    @staticmethod
    def nll(mean: Tensor, std: Tensor, targets: Targets, beta: float = 0.0, dim_weights: Tensor | None = None) -> Tensor:
        """Eq. 1: -log N(SM(t_q) | μ_q, σ_q), summed over SM dims, averaged over the valid queries. With
        ``beta`` > 0, the β-NLL: each dim's term weighted by stop_gradient(σ^(2β)); ``dim_weights`` [D]: each
        dim's term weighted by it."""
        per_dim = 0.5 * ((targets.values - mean) / std) ** 2 + std.log() + 0.5 * np.log(2 * np.pi)
        if beta:
            per_dim = per_dim * std.detach() ** (2.0 * beta)
        if dim_weights is not None:
            per_dim = per_dim * dim_weights
        per_query = per_dim.sum(dim=-1)
        w = targets.valid.to(per_query.dtype)
        return (per_query * w).sum() / w.sum().clamp(min=1.0)

    def training_loss(self, context: Context, targets: Targets, draws: int = 1) -> tuple[Tensor, dict]:
        """One training step's loss on a drawn (context, targets) pair, with monitoring figures. ``draws``: rows
        b * draws .. b * draws + draws - 1 are draws of one episode (unused here; a subclass may group by it)."""
        mean, std = self(context, targets.phase)
        loss = self.nll(mean, std, targets, self.nll_beta, self.dim_weights)
        return loss, {"nll": loss.item(), **fit_figures(mean, std, targets)}

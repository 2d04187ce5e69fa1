"""The mixture decoder (CNEP: Yildirim & Ugur, "Conditional Neural Expert Processes", arXiv 2402.08424).

:class:`MixtureCNMP` keeps CNMP's encoder E and aggregation and replaces its one query network Q by K query
networks ("experts") Q_1..Q_K over the same representation r and a gate π(r) = softmax(W_g r + b_g) over them.
Each expert predicts (μ_k, σ_k); the gate says which of them the context r belongs to. ``forward`` / ``decode``
return the most probable expert's (μ, σ); ``mixture`` returns all of them with π. Its training loss is the
``assigned`` NLL with the gate's entropy terms (``mixture_loss``).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F  # noqa: N812
from torch import Tensor, nn

from lerobot_cnmp.model.cnmp import CNMP, Context, Targets, fit_figures, mlp, run_mlp


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


def entropy(p: Tensor) -> Tensor:
    """H(p) = -Σ_k p_k log p_k over the last dim (0 log 0 = 0)."""
    return -(p * p.clamp(min=1e-12).log()).sum(dim=-1)


def pick_expert(means: Tensor, stds: Tensor, k: Tensor) -> tuple[Tensor, Tensor]:
    """Expert ``k[b]``'s (μ, σ) of each episode b: [B, K, M, D] -> [B, M, D] each."""
    idx = k.long()[:, None, None, None].expand(-1, 1, *means.shape[2:])
    return means.gather(1, idx)[:, 0], stds.gather(1, idx)[:, 0]


def check_mixture_settings(n_experts, n_hidden: int, shared_decoder_layers=0, assignment_draws=0,
                           unconditional_nll_coef=1.0, gate_entropy_coef=0.0, batch_entropy_coef=0.0) -> None:
    """Raise ValueError naming the first setting of a K-expert mixture that is out of range (``n_hidden``: the
    number of hidden layers of the query network)."""
    if isinstance(n_experts, bool) or not float(n_experts).is_integer() or n_experts < 2:  # NaN and inf included
        raise ValueError(f"n_experts (the number of decoders K) of a mixture must be an integer >= 2, got {n_experts}")
    if not 0 <= shared_decoder_layers <= n_hidden:
        raise ValueError(f"shared_decoder_layers must be between 0 and the {n_hidden} hidden layers of "
                         f"decoder_layers, got {shared_decoder_layers}")
    if isinstance(assignment_draws, bool) or not float(assignment_draws).is_integer() or assignment_draws < 0:
        raise ValueError(f"assignment_draws must be an integer >= 0, got {assignment_draws}")
    if not 0.0 < unconditional_nll_coef < float("inf"):  # NaN included
        raise ValueError(f"unconditional_nll_coef must be a finite number > 0, got {unconditional_nll_coef}")
    if not (gate_entropy_coef >= 0 and batch_entropy_coef >= 0):
        raise ValueError(f"gate_entropy_coef and batch_entropy_coef must be >= 0, got {gate_entropy_coef}, "
                         f"{batch_entropy_coef}")


class MixtureCNMP(CNMP):
    """CNMP with K query networks and a gate (see the module's docstring). Parameters: ``encoder.*`` as CNMP;
    ``trunk.*`` (the ``shared_decoder_layers`` first hidden layers of Q, shared by the experts; absent with 0),
    ``decoders.weights/biases.*`` (each expert's own layers, stacked) and ``gate.*``."""

    def __init__(
        self,
        sm_dim: int,
        task_dim: int = 0,
        encoder_layers: tuple[int, ...] = (128, 128, 128),
        decoder_layers: tuple[int, ...] = (128, 128, 128),
        min_std: float = 0.01,
        phase_frequencies: int = 0,
        n_experts: int = 2,
        gate_entropy_coef: float = 0.2,
        batch_entropy_coef: float = 0.88,
        shared_decoder_layers: int = 0,
        assignment_draws: int = 0,
        unconditional_nll_coef: float = 1.0,
    ):
        check_mixture_settings(n_experts, len(decoder_layers), shared_decoder_layers, assignment_draws,
                               unconditional_nll_coef, gate_entropy_coef, batch_entropy_coef)
        # read by build_decoder, which CNMP.__init__ calls (plain values may be set before nn.Module.__init__)
        self.n_experts, self.shared_decoder_layers = int(n_experts), int(shared_decoder_layers)
        super().__init__(sm_dim, task_dim, encoder_layers, decoder_layers, min_std, phase_frequencies)
        self.gate_entropy_coef, self.batch_entropy_coef = gate_entropy_coef, batch_entropy_coef
        self.assignment_draws, self.unconditional_nll_coef = int(assignment_draws), float(unconditional_nll_coef)
        # each expert's running share of the episodes (revive_starving's training state, not saved)
        self.register_buffer("expert_share", torch.full((self.n_experts,), 1.0 / self.n_experts), persistent=False)

    def build_decoder(self, in_dim: int, widths: tuple[int, ...]) -> None:
        """The experts (after a shared trunk of ``shared_decoder_layers`` hidden layers) and the gate on r."""
        n_shared = self.shared_decoder_layers
        if n_shared:
            self.trunk = mlp(in_dim, widths[:n_shared])
            in_dim, widths = widths[n_shared - 1], widths[n_shared:]
        self.decoders = ExpertMLPs(self.n_experts, in_dim, widths)
        self.gate = nn.Linear(self.encoder[-1].out_features, self.n_experts)

    def gate_probs(self, r: Tensor) -> Tensor:
        """π(r) = softmax(W_g r + b_g): each expert's probability of being the context's mode, [B, K]."""
        return torch.softmax(self.gate(r), dim=-1)

    def decode(self, r: Tensor, query_phase: Tensor, task_params: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """The most probable expert's (μ_k*, σ_k*), k* = argmax_k π_k(r), each [B, M, D]."""
        means, stds = self.decode_experts(r, query_phase, task_params)
        return pick_expert(means, stds, self.gate_probs(r).argmax(dim=-1))

    def decode_experts(self, r: Tensor, query_phase: Tensor, task_params: Tensor | None = None
                       ) -> tuple[Tensor, Tensor]:
        """(μ_k, σ_k) = Q_k(t_q, γ, r) of every expert k, each [B, K, M, D] (Q's first layer split as in
        :meth:`CNMP.decode`: the [γ, r] term once per episode)."""
        q, k = self.decoders, self.n_experts
        if hasattr(self, "trunk"):  # shared hidden layers, then each expert's own
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

    def mixture(self, context: Context, query_phase: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Every expert's prediction and probability: μ_k, σ_k [B, K, M, D] and π [B, K]."""
        r = self.condition(context)
        means, stds = self.decode_experts(r, query_phase, context.task_params)
        return means, stds, self.gate_probs(r)

    def unconditional(self, query_phase: Tensor, task_params: Tensor | None) -> tuple[Tensor, Tensor, Tensor]:
        """The unconditional mixture: the experts μ⁰_k, σ⁰_k [B, K, M, D] and gate π⁰ [B, K] on the empty context
        (r = 0; γ kept)."""
        r0 = query_phase.new_zeros(query_phase.shape[0], self.gate.in_features)
        means0, stds0 = self.decode_experts(r0, query_phase, task_params)
        return means0, stds0, self.gate_probs(r0)

    @staticmethod
    def nll_per_expert(means: Tensor, stds: Tensor, targets: Targets) -> Tensor:
        """NLL_bk: Eq. 1 of expert k on episode b, summed over SM dims and averaged over its valid queries, [B, K]."""
        y = targets.values[:, None]
        per_dim = 0.5 * ((y - means) / stds) ** 2 + stds.log() + 0.5 * np.log(2 * np.pi)
        w = targets.valid[:, None, :].to(per_dim.dtype)
        return (per_dim.sum(dim=-1) * w).sum(dim=-1) / w.sum(dim=-1).clamp(min=1.0)

    def training_loss(self, context: Context, targets: Targets, draws: int = 1) -> tuple[Tensor, dict]:
        """One training step's loss (``mixture_loss``) on a drawn (context, targets) pair, with monitoring
        figures. ``draws``: rows b * draws .. b * draws + draws - 1 are draws of one episode."""
        r = self.condition(context)
        if self.assignment_draws:
            # each episode's expert from the queries of its first p draws, decided by the experts and gate on the
            # empty context (r = 0), whose rows join the context's in one decoder pass
            nll_bk, means, stds, probs, prior = self._with_episode_prior(r, context.task_params, targets, draws)
        else:  # each draw's expert from its own queries
            means, stds = self.decode_experts(r, targets.phase, context.task_params)
            probs, nll_bk = self.gate_probs(r), self.nll_per_expert(means, stds, targets)
            means0, stds0, probs0 = self.unconditional(targets.phase, context.task_params)
            prior = (self.nll_per_expert(means0, stds0, targets), probs0, targets.valid.sum(-1))
        loss, info = self.mixture_loss(nll_bk, probs, prior)
        with torch.no_grad():  # for the monitoring figures only
            mean, std = pick_expert(means, stds, probs.argmax(dim=-1))
        return loss, {**info, **fit_figures(mean, std, targets)}

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

    def mixture_loss(self, nll_bk: Tensor, probs: Tensor, prior: tuple[Tensor, Tensor, Tensor]) -> tuple[Tensor, dict]:
        """The mixture's loss from each expert's Eq. 1 NLL_bk on each episode b [B, K] (``nll_per_expert``), the
        gate's π_b [B, K] and the ``prior``: the empty context's NLL⁰ [E, K], π⁰ [E, K] and number of queries
        n⁰ [E] (E = B, or one row per episode of B / E draws with ``assignment_draws``, ρ then repeated over the
        episode's draws):

            L = NLL_mix
                + gate_entropy_coef  · mean_b H(π_b) / log K   -- low per-episode entropy: commit to one expert
                - batch_entropy_coef · H(mean_b π⁰_b) / log K  -- high batch entropy: use every expert

            NLL_mix = -c mean_b (1/n⁰_b) log Σ_k π⁰_k Π_q N(y_bq | μ⁰_bkq, σ⁰_bkq)  -- the unconditional mixture
                      + mean_b Σ_k ρ_bk (NLL_bk - log π_bk)                           -- the context's experts, gate

        The episode's expert is decided from its queries by the mixture on the *empty* context (r = 0: the
        experts' unconditional predictions μ⁰_k, σ⁰_k and gate π⁰ = π(0); γ kept), the same for whatever context
        is drawn from the episode, and the context's experts and gate are trained on that expert:
        ρ_bk = π⁰_k Π_q N⁰_bkq / Σ_l π⁰_l Π_q N⁰_blq (no gradient; ``revive_starving`` gives an idle expert an
        episode), c = ``unconditional_nll_coef``. The gate's cross-entropy to ρ counts once per episode. A
        context that decides the mode gets π ≈ one-hot on its episode's expert, one shared by modes the share of
        its episodes among them. The batch entropy acts on the unconditional mixture's per-query posterior
        π⁰_b = softmax_k(log π⁰_k - NLL⁰_bk), which keeps a gradient where the whole episode's posterior is
        one-hot. Entropies are divided by log K (1 for a uniform gate); CNEP's coefficients for them, divided by
        its NLL weight, are 0.62 and 0.88 for any K."""
        log_k = float(np.log(self.n_experts))
        with torch.no_grad():  # reported: the NLL expected under the gate
            expected = (probs * nll_bk).sum(dim=-1).mean()
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
        ind_entropy = entropy(probs).mean() / log_k
        batch_entropy = entropy(batch_probs.mean(dim=0)) / log_k
        loss = nll + self.gate_entropy_coef * ind_entropy - self.batch_entropy_coef * batch_entropy
        return loss, {"nll": nll.item(), "expected_nll": expected.item(), "gate_entropy": ind_entropy.item(),
                      "batch_entropy": batch_entropy.item(), "prior_nll": prior_nll.item(),
                      "assigned_nll": assigned.item(), "min_expert_share": rho.mean(dim=0).min().item()}

    @torch.no_grad()
    def revive_starving(self, log_joint: Tensor, momentum: float = 0.99) -> Tensor:
        """The assignment scores log π⁰_k Π_q N⁰_bk [B, K] with k-means' remedy for an empty cluster: in training,
        each expert's share of the episodes is tracked (a running mean of the hard assignments, ``momentum`` per
        call: one per ``training_loss``, two per step with the policy's feedback draws); an expert whose share
        falls below 1 / (4K) is given, in this batch, the episode it fits least badly relative to that episode's
        expert (the smallest gap max_l s_bl - s_bk). Trained on it, it takes that mode over or drops it. Without
        this an expert that loses every episode early (the hard posterior of a whole episode leaves it no
        gradient) stays idle while another covers two modes."""
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


def n_experts(model: CNMP) -> int:
    """K, the number of query networks of any CNMP (1 for the plain CNMP)."""
    return model.n_experts if isinstance(model, MixtureCNMP) else 1


def mixture_of(model: CNMP, context: Context, query_phase: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """μ_k, σ_k [B, K, M, D] and π [B, K] of any CNMP: a MixtureCNMP's experts and gate; a plain CNMP is the
    mixture of one expert of probability 1."""
    if isinstance(model, MixtureCNMP):
        return model.mixture(context, query_phase)
    mean, std = model(context, query_phase)
    return mean[:, None], std[:, None], mean.new_ones(mean.shape[0], 1)

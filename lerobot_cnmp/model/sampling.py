"""The training step's draw (paper Sec. III-B): from each demonstration in the batch, n ~ U{1..n_max}
observations (t_i, SM(t_i)) to condition on and m ~ U{1..m_max} queries (t_q, SM(t_q)) to predict."""

from __future__ import annotations

import torch
import torch.nn.functional as F  # noqa: N812
from torch import Tensor

from lerobot_cnmp.model.cnmp import Context, Episodes, Targets


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

"""Which expert (mode) of a mixture CNMP execution follows, step by step (pure torch).

The rule, per env of a batch, given the gate's probabilities π_t [K] after re-conditioning at step t:

* first step after ``reset``: c = argmax_k π_k (``"most_probable"``) or c ~ Categorical(π) (``"sample"``);
* every later step: keep c while it stays consistent with the fed-back SM, i.e. while no expert is clearly
  more probable: switch to k* = argmax_k π_k only when π_k* - π_c > ``margin``.

The margin is a hysteresis: when two modes are about equally probable (before the weight is felt, at a
crossing of two modes) the followed one does not flicker; when the fed-back SM makes another mode clearly
more probable (the paper's weight switch), the policy changes mode in one step.
"""

from __future__ import annotations

import torch
from torch import Tensor


class ModeSelector:
    """Per-env choice of the followed expert under the rule of this module."""

    def __init__(self, margin: float = 0.3, selection: str = "most_probable",
                 generator: torch.Generator | None = None):
        if not 0.0 <= margin < 1.0:
            raise ValueError(f"the mode switch margin must be in [0, 1), got {margin}")
        if selection not in ("most_probable", "sample"):
            raise ValueError(f"selection must be 'most_probable' or 'sample', got {selection!r}")
        self.margin, self.selection, self.generator = margin, selection, generator
        self.reset()

    def reset(self) -> None:
        self.current: Tensor | None = None  # [B] long: the followed expert per env
        self.switches: Tensor | None = None  # [B] long: mode changes since the first step

    def first_choice(self, probs: Tensor) -> Tensor:
        if self.selection == "sample":
            return torch.multinomial(probs.float().cpu(), 1, generator=self.generator)[:, 0].to(probs.device)
        return probs.argmax(dim=-1)

    def __call__(self, probs: Tensor) -> Tensor:
        """The expert to follow now, per env, [B] long, from the gate's probabilities ``probs`` [B, K]."""
        if probs.ndim != 2:
            raise ValueError(f"gate probabilities must be [envs, experts], got shape {tuple(probs.shape)}")
        if not bool(torch.isfinite(probs).all()) or bool((probs < 0).any()):
            raise ValueError("gate probabilities must be finite and non-negative")
        if self.current is None or self.current.shape[0] != probs.shape[0]:
            self.current = self.first_choice(probs)
            self.switches = torch.zeros_like(self.current)
            return self.current.clone()
        best = probs.argmax(dim=-1)
        lead = probs.gather(1, best[:, None])[:, 0] - probs.gather(1, self.current[:, None])[:, 0]
        switch = lead > self.margin
        self.switches = self.switches + switch.long()
        self.current = torch.where(switch, best, self.current)
        return self.current.clone()

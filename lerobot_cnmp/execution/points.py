"""The context points execution conditions on, as normalized tensors per env of a batch.

A group of points is a tuple (phase [B, K], values [B, K, D], mask [B, K, D], valid [B, K]). The points that
stay while an episode runs -- the ``environment_state`` slots, the user's conditions, the state sensed at the
first step -- are built once and reused while their source is unchanged (an env writes the same slots every
step); :meth:`ContextPoints.static` joins them, rebuilt only when a group changes.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from lerobot_cnmp.execution.conditions import Condition, check_points, decode_conditions

Group = tuple[Tensor, Tensor, Tensor, Tensor]


class ContextPoints:
    """The static context points of one executor: the user's conditions (:class:`Condition`, SM units), the
    ``environment_state`` slots and the start point, normalized with ``normalizer``."""

    def __init__(self, normalizer, sm_dim: int):
        self.normalizer, self.sm_dim = normalizer, sm_dim
        self.user: list[Condition] = []
        self._user_tensors: tuple | None = None
        self._user_group: tuple | None = None  # (the _user_tensors it expands, n, the group of n envs)
        self._slots_cache: tuple | None = None
        self.reset()

    def reset(self) -> None:
        """Forget the episode's points (the user's conditions stay)."""
        self.start: Tensor | None = None  # sensed SM at the first step (condition_on_start), normalized
        self._start_cache: tuple | None = None  # (start, its context point)
        self._static_cache: tuple | None = None  # (groups, their concatenation, every env has a valid point)

    def set_user(self, conditions: list[Condition]) -> None:
        self.user = list(conditions)
        self._user_tensors = None

    def _normalizer_key(self) -> tuple:
        """Changes whenever the SM statistics do (cached normalized conditions are then rebuilt)."""
        n = self.normalizer
        return (n.sm_mean.data_ptr(), n.sm_mean._version, n.sm_std.data_ptr(), n.sm_std._version)

    def user_points(self, n: int, device) -> Group | None:
        """The user's conditions for ``n`` envs; None without any."""
        if not self.user:
            return None
        key = self._normalizer_key()
        if self._user_tensors is None or self._user_tensors[0].device != torch.device(device) or \
                self._user_tensors[3] != key:
            norm = self.normalizer
            norm.require()
            phase = torch.tensor([u.phase for u in self.user], dtype=torch.float32, device=device)
            raw = torch.from_numpy(np.array([u.values for u in self.user], dtype=np.float32)).to(device)
            mask = torch.from_numpy(np.stack([u.mask() for u in self.user])).to(device)
            values = torch.where(mask > 0.5, norm.sm(torch.nan_to_num(raw)), torch.zeros_like(raw))
            self._user_tensors = (phase, values, mask, key)
        cached = self._user_group  # the batch-sized group, kept while the conditions and n stay
        if cached is None or cached[0] is not self._user_tensors or cached[1] != n:
            phase, values, mask, _ = self._user_tensors
            k = phase.shape[0]
            group = (phase[None].expand(n, k), values[None].expand(n, -1, -1), mask[None].expand(n, -1, -1),
                     torch.ones(n, k, dtype=torch.bool, device=device))
            self._user_group = cached = (self._user_tensors, n, group)
        return cached[2]

    def slot_points(self, env: Tensor) -> Group:
        """The ``environment_state`` slots as context points; the last decoding is reused while they are equal."""
        cached, key = self._slots_cache, self._normalizer_key()
        if cached is not None and cached[2] == key and cached[0].shape == env.shape and \
                cached[0].device == env.device and torch.equal(cached[0], env):
            return cached[1]
        out = self._decode_slots(env)
        self._slots_cache = (env.clone(), out, key)
        return out

    def _decode_slots(self, env: Tensor) -> Group:
        present, c_phase, c_values, c_mask = decode_conditions(env, self.sm_dim)
        host = [x.detach().cpu().numpy() for x in (c_phase, c_values, c_mask, present)]
        check_points(*host, source="observation.environment_state condition")
        given = present > 0.5
        used = given[..., None] & (c_mask > 0.5)
        values = torch.where(used, self.normalizer.sm(torch.nan_to_num(c_values.float())), torch.zeros_like(c_values))
        return c_phase, values, c_mask.float(), given & (c_mask.sum(-1) > 0)

    def start_point(self, sensed: Tensor, mask: Tensor) -> Group:
        """The sensed SM at the episode's first step as a context point at t = 0 (kept for the episode);
        ``mask`` [D]: the dims it constrains."""
        if self.start is None or self.start.shape[0] != sensed.shape[0]:
            self.start = sensed.clone()
        cached = self._start_cache
        if cached is None or cached[0] is not self.start:
            start = self.start
            n = start.shape[0]
            group = (torch.zeros(n, 1, device=start.device), start[:, None, :], mask.expand_as(start)[:, None, :],
                     torch.ones(n, 1, dtype=torch.bool, device=start.device))
            self._start_cache = cached = (start, group)
        return cached[1]

    def static(self, groups: list[Group]) -> tuple[Group | None, bool]:
        """(the groups concatenated, whether every env has a valid point among them), rebuilt only when one of
        the groups is a new object; (None, False) without groups."""
        if not groups:
            return None, False
        cached = self._static_cache
        if cached is None or len(cached[0]) != len(groups) or any(a is not b for a, b in zip(cached[0], groups)):
            joined = tuple(torch.cat(x, 1) if len(groups) > 1 else x[0] for x in zip(*groups, strict=True))
            self._static_cache = cached = (list(groups), joined, bool(joined[3].any(dim=1).all()))
        return cached[1], cached[2]

"""Sensing: the live observation as a normalized SM vector, and 0/1 masks over SM dims.

:class:`Sensing` reads the sensed SM dims out of an observation (``spec.sensed_features``), checks that the
observation's features are the ones the CNMP was trained on (a checkpoint run on another env/robot stops with
an error naming both), subtracts the episode's task-frame origins (dims declared in the frame of γ) and
normalizes with the SM statistics. Index tensors and masks are built once per shape and device.
"""

from __future__ import annotations

import math
from typing import Callable

import torch
from torch import Tensor


def check_finite(name: str, x: Tensor) -> None:
    """Raise a ``ValueError`` naming ``name`` when ``x`` holds a NaN or an infinity."""
    # one reduction instead of isfinite + all: a NaN or ±inf anywhere makes the sum non-finite (so would values
    # near float32's limit, which no robot sends)
    if not math.isfinite(float(x.sum())):
        raise ValueError(f"{name} contains NaN or infinite values")


class Sensing:
    """The sensed SM of a batch of observations, given the SM ``spec``, the ``normalizer``, the widths of the
    features the CNMP was trained on (``feature_widths``: name -> dims; None: not checked) and ``task_params``
    (batch -> raw γ [B, G], for the task-frame origins)."""

    def __init__(self, spec, normalizer, feature_widths: dict[str, int] | None,
                 task_params: Callable[[dict], Tensor | None]):
        self.spec, self.normalizer, self.feature_widths, self.task_params = spec, normalizer, feature_widths, task_params
        self._cache: dict = {}
        self.origin: Tensor | None = None  # raw γ of the task-frame dims at the episode's first step (SM layout)

    def reset(self) -> None:
        self.origin = None

    def dims_mask(self, like: Tensor, dims) -> Tensor:
        """A 0/1 mask shaped like ``like`` with ones at SM ``dims`` (None: all); built once per shape and device
        (read only: callers never write into it)."""
        key = ("mask", None if dims is None else tuple(dims), tuple(like.shape), like.device, like.dtype)
        mask = self._cache.get(key)
        if mask is None:
            if dims is None:
                mask = torch.ones_like(like)
            else:
                mask = torch.zeros_like(like)
                mask[..., list(dims)] = 1.0
            self._cache[key] = mask
        return mask

    def _check_width(self, feature: str, x: Tensor) -> None:
        key = ("top", feature)
        top = self._cache.get(key)
        if top is None:
            top = self._cache[key] = max(k for _, k in self.spec.sensed_features[feature])
        trained = None if self.feature_widths is None else self.feature_widths.get(feature)
        if x.shape[-1] <= top or (trained is not None and x.shape[-1] != trained):
            raise ValueError(
                f"the observation's {feature!r} has {x.shape[-1]} dims, but this checkpoint was trained on "
                f"{trained if trained is not None else f'at least {top + 1}'} and its SM reads dims "
                f"{sorted(k for _, k in self.spec.sensed_features[feature])} of it (SM {list(self.spec.names)}): the "
                "checkpoint's SM does not match this env/robot's features; run it on the env/robot it was trained for")
        if self.spec.tied and x.shape[-1] != self.spec.size:
            raise ValueError(f"{feature!r} has {x.shape[-1]} dims, the SM has {self.spec.size}")

    def sensed_sm(self, batch: dict[str, Tensor]) -> Tensor | None:
        """The live observation's sensed dims as a normalized SM vector [B, D] (other dims 0)."""
        spec = self.spec
        out = None
        for feature, pairs in spec.sensed_features.items():
            if feature not in batch:
                raise KeyError(f"the CNMP feeds back {feature!r}: the observation needs it; it has {sorted(batch)}")
            x = batch[feature]
            x = x.reshape(x.shape[0], -1) if x.ndim != 2 else x
            self._check_width(feature, x)
            if len(spec.sensed_features) == 1 and x.shape[-1] == spec.size and self._identity(feature):
                out = x.float()  # the feature is the SM itself, dim for dim
                check_finite(feature, out)
                break
            if out is None:
                out = torch.zeros(x.shape[0], spec.size, dtype=torch.float32, device=x.device)
            key = (feature, x.device)
            if key not in self._cache:  # (SM index, feature index) tensors, built once per device
                self._cache[key] = (torch.tensor([i for i, _ in pairs], device=x.device),
                                    torch.tensor([k for _, k in pairs], device=x.device))
            idx, src = self._cache[key]
            vals = x[:, src].float()
            check_finite(feature, vals)
            out[:, idx] = vals
        if out is None:
            return None
        if spec.origins:  # task frames: minus the γ this episode started with
            if self.origin is None or self.origin.shape[0] != out.shape[0]:
                gamma = self.task_params(batch)
                sm_idx, g_idx = zip(*spec.origins, strict=True)
                self.origin = torch.zeros_like(out)
                self.origin[:, list(sm_idx)] = gamma[:, list(g_idx)].to(out)
            out = out - self.origin
        full = self.normalizer.sm(out)
        if spec.tied:  # every SM dim is sensed
            return full
        return full * self.dims_mask(full[0], spec.sensed)

    def _identity(self, feature: str) -> bool:
        """Whether ``feature``'s dim k is SM dim k for every SM dim (a state that is the SM)."""
        key = ("identity", feature)
        if key not in self._cache:
            pairs = self.spec.sensed_features[feature]
            self._cache[key] = sorted(pairs) == [(i, i) for i in range(self.spec.size)]
        return self._cache[key]

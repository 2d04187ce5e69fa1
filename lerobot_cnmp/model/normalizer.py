"""The SM's and γ's normalization statistics, saved with the weights."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor, nn


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

"""The execution twin of :class:`~lerobot_cnmp.model.cnmp.CNMP` in numpy."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor, nn

from lerobot_cnmp.model.cnmp import CNMP, Context


class NumpyCNMP:
    """A frozen numpy copy of a :class:`CNMP` for execution on CPU: the same inference equations (encode,
    masked-mean aggregate, decode with Q's first layer split) on the same weights.

    A batch-1 control step is ~25 small ops; torch spends several µs of dispatch on each, numpy about one,
    so this runs a control step 2-4x faster on CPU. Training stays in torch; the policy rebuilds this copy
    whenever the weights change. ``tests/test_model.py`` checks it against :class:`CNMP`."""

    def __init__(self, model: CNMP):
        if not isinstance(getattr(model, "decoder", None), nn.Sequential):
            raise ValueError(f"NumpyCNMP copies a single-decoder CNMP; this {type(model).__name__} has several "
                             "query networks (experts): a mixture executes with the torch model")

        def layers(seq: nn.Sequential) -> list[tuple[np.ndarray, np.ndarray]]:
            return [(m.weight.detach().cpu().numpy().T.copy(), m.bias.detach().cpu().numpy().copy())
                    for m in seq if isinstance(m, nn.Linear)]

        self.encoder, decoder = layers(model.encoder), layers(model.decoder)
        self.frequencies = model.frequencies.cpu().numpy()
        self.sm_dim, self.task_dim, self.min_std = model.sm_dim, model.task_dim, model.min_std
        t_dim = 1 + 2 * self.frequencies.size
        (w, b), self.decoder = decoder[0], decoder[1:]
        self.decoder_t, self.decoder_rest, self.decoder_bias = w[:t_dim], w[t_dim:], b
        gain = getattr(model, "task_gain", None)
        self.task_gain = None if gain is None else gain.detach().cpu().numpy().T.copy()  # [(1 + t_dim) G, D]

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
        if self.task_gain is not None:  # A(t_q)·γ (CNMP.linear_in_task)
            qp = query_phase.numpy()
            phi = np.concatenate([np.ones((*qp.shape, 1), np.float32), self.phase_features(qp)], axis=-1)
            mean = mean + (phi[..., :, None] * gamma[:, None, None, :]).reshape(*qp.shape, -1) @ self.task_gain
        return torch.from_numpy(np.ascontiguousarray(mean)), torch.from_numpy(self.min_std + np.logaddexp(0.0, raw))


class NumpyTwin:
    """The :class:`NumpyCNMP` of a model, rebuilt whenever one of its weights changes (in place, loaded or moved)."""

    def __init__(self):
        self._twin: NumpyCNMP | None = None
        self._key: tuple | None = None
        self._params: tuple | None = None  # (model, its parameters): what the key reads

    def __call__(self, model: CNMP) -> NumpyCNMP:
        if self._params is None or self._params[0] is not model:  # module traversal once per model
            self._params = (model, list(model.parameters()))
        key = tuple((p.data_ptr(), p._version) for p in self._params[1])
        if self._key != key:
            self._twin, self._key = NumpyCNMP(model), key
        return self._twin

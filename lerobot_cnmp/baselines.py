"""Baselines from the `movement_primitives` library behind the same interface as ``CNMPModel``.

Only the adapter is ours: the algorithms (ProMP learning by EM, Gaussian conditioning) are the library's.
``predict(phases, conditions)`` returns mean and σ ``[M, D]`` exactly like ``CNMPModel.predict``.
"""

from __future__ import annotations

import numpy as np

from lerobot_cnmp.api import pad_demos
from lerobot_cnmp.conditions import Condition

FREE_DIM_VARIANCE = 1e6
"""Variance given to SM dims a condition does not constrain (ProMP conditions whole positions)."""
GRID_POINTS = 1001


class ProMPBaseline:
    """Probabilistic Movement Primitive (Paraschos et al. 2013) from ``movement_primitives.promp``.

    Args:
        n_weights_per_dim: RBF weights per SM dimension (the paper's comparison used 31).
        condition_std: σ of a condition point (0 would make the Gaussian conditioning singular).
    """

    def __init__(self, n_weights_per_dim: int = 31, condition_std: float = 1e-3):
        self.n_weights_per_dim = n_weights_per_dim
        self.condition_std = condition_std
        self.promp = None

    def fit(self, demos) -> ProMPBaseline:
        from movement_primitives.promp import ProMP

        values, valid, phase = pad_demos(demos)
        d = values.shape[-1]
        self.promp = ProMP(n_dims=d, n_weights_per_dim=self.n_weights_per_dim)
        ts = [phase[i, valid[i]] for i in range(len(values))]
        ys = [values[i, valid[i]] for i in range(len(values))]
        self.promp.imitate(ts, ys)
        self.sm_dim = d
        return self

    def conditioned(self, conditions: list[Condition]):
        if self.promp is None:
            raise RuntimeError("the baseline is not fitted: call fit(demos) first")
        promp = self.promp
        for k, c in enumerate(conditions):
            if len(c.values) != self.sm_dim:
                raise ValueError(f"condition {k} has {len(c.values)} values; the SM has {self.sm_dim} dims")
            if not 0.0 <= c.phase <= 1.0:
                raise ValueError(f"condition {k} has phase {c.phase}, outside [0, 1]")
            mask = c.mask()
            cov = np.diag(np.where(mask > 0, self.condition_std**2, FREE_DIM_VARIANCE))
            y = np.nan_to_num(np.asarray(c.values, dtype=float))
            promp = promp.condition_position(y, y_cov=cov, t=c.phase, t_max=1.0)
        return promp

    def predict(self, phases, conditions: list[Condition]) -> tuple[np.ndarray, np.ndarray]:
        q = np.asarray(phases, dtype=float).reshape(-1)
        if q.size == 0 or not np.isfinite(q).all() or q.min() < 0 or q.max() > 1:
            raise ValueError("query phases must be a non-empty set of finite values in [0, 1]")
        promp = self.conditioned(conditions)
        # The library rescales the query times by their maximum (T / max T), so it is always evaluated on
        # the whole [0, 1] grid and interpolated at the requested phases.
        grid = np.linspace(0.0, 1.0, GRID_POINTS)
        mean_g, var_g = promp.mean_trajectory(grid), promp.var_trajectory(grid)
        mean = np.stack([np.interp(q, grid, mean_g[:, d]) for d in range(self.sm_dim)], axis=1)
        var = np.stack([np.interp(q, grid, var_g[:, d]) for d in range(self.sm_dim)], axis=1)
        return mean.astype(np.float32), np.sqrt(np.maximum(var, 0.0)).astype(np.float32)

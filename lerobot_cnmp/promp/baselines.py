"""Baselines from the `movement_primitives` library behind the same interface as ``CNMPModel``.

Only the adapter is ours: the algorithms (ProMP learning by EM, Gaussian conditioning) are the library's.
``predict(phases, conditions)`` returns mean and σ ``[M, D]`` exactly like ``CNMPModel.predict``.
"""

from __future__ import annotations

import numpy as np

from lerobot_cnmp.data.demos import pad_demos, query_phases
from lerobot_cnmp.execution.conditions import Condition

FREE_DIM_VARIANCE = 1e6
"""Variance given to SM dims a condition does not constrain (ProMP conditions whole positions)."""
GRID_POINTS = 1001


class ProMPBaseline:
    """Probabilistic Movement Primitive (Paraschos et al. 2013) from ``movement_primitives.promp``.

    Task parameters γ (a contextual ProMP): ``fit(demos, task_params=...)`` also fits a joint Gaussian over
    each demo's weights (the library's per-demo regression, ``ProMP.weights``) and its γ (standardized);
    ``predict(..., task_params=γ)`` starts from the weight distribution conditioned on γ (the Gaussian's
    conditional: mean ``μ_w + Σ_wγ (Σ_γγ + λI)⁻¹ (γ - μ_γ)``, covariance its Schur complement), then applies
    the SM conditions as usual. With fewer demos than γ dims Σ_γγ is singular: the ridge λ keeps it solvable.

    Args:
        n_weights_per_dim: RBF weights per SM dimension (the paper's comparison used 31).
        condition_std: σ of a condition point (0 would make the Gaussian conditioning singular).
        context_ridge: λ added to the standardized γ's covariance in the conditioning on γ.
    """

    def __init__(self, n_weights_per_dim: int = 31, condition_std: float = 1e-3, context_ridge: float = 0.1):
        if context_ridge <= 0:
            raise ValueError(f"context_ridge must be > 0, got {context_ridge}")
        self.n_weights_per_dim = n_weights_per_dim
        self.condition_std = condition_std
        self.context_ridge = context_ridge
        self.promp = None
        self.context = None

    def fit(self, demos, task_params=None) -> ProMPBaseline:
        from movement_primitives.promp import ProMP

        values, valid, phase = pad_demos(demos)
        d = values.shape[-1]
        self.promp = ProMP(n_dims=d, n_weights_per_dim=self.n_weights_per_dim)
        ts = [phase[i, valid[i]] for i in range(len(values))]
        ys = [values[i, valid[i]] for i in range(len(values))]
        self.promp.imitate(ts, ys)
        self.sm_dim = d
        self.context = None
        if task_params is not None:
            gamma = np.asarray(task_params, dtype=float)
            if gamma.ndim != 2 or len(gamma) != len(ys):
                raise ValueError(f"task_params must be [n_demos, G] with one row per demo ({len(ys)}), "
                                 f"got shape {gamma.shape}")
            if not np.isfinite(gamma).all():
                raise ValueError("task_params contain NaN or inf")
            w = np.stack([self.promp.weights(t, y) for t, y in zip(ts, ys)])
            mu_g, sd_g = gamma.mean(0), gamma.std(0)
            sd_g = np.where(sd_g > 1e-9, sd_g, 1.0)
            z = (gamma - mu_g) / sd_g
            mu_w = w.mean(0)
            dw = w - mu_w
            n = max(len(ys) - 1, 1)
            cov_wz = dw.T @ z / n
            cov_zz = z.T @ z / n + self.context_ridge * np.eye(z.shape[1])
            gain = np.linalg.solve(cov_zz, cov_wz.T).T  # Σ_wz Σ_zz⁻¹
            cov = dw.T @ dw / n - gain @ cov_wz.T  # the conditional covariance does not depend on γ's value
            cov = 0.5 * (cov + cov.T) + 1e-8 * np.eye(len(mu_w))
            self.context = {"mu_g": mu_g, "sd_g": sd_g, "mu_w": mu_w, "gain": gain, "cov": cov}
        return self

    def to_arrays(self) -> dict[str, np.ndarray]:
        """The fitted distribution as named arrays (what ``from_arrays`` rebuilds; the ProMP policy saves them)."""
        if self.promp is None:
            raise RuntimeError("the baseline is not fitted: call fit(demos) first")
        out = {"weight_mean": self.promp.weight_mean, "weight_cov": self.promp.weight_cov}
        if self.context is not None:
            out.update({f"context_{k}": v for k, v in self.context.items()})
        return {k: np.asarray(v, dtype=np.float64) for k, v in out.items()}

    @classmethod
    def from_arrays(cls, arrays: dict, sm_dim: int, n_weights_per_dim: int, **kwargs) -> ProMPBaseline:
        """Inverse of ``to_arrays``: the same distribution, hence the same predictions."""
        from movement_primitives.promp import ProMP

        self = cls(n_weights_per_dim=n_weights_per_dim, **kwargs)
        a = {k: np.asarray(v, dtype=np.float64) for k, v in arrays.items()}
        n = sm_dim * n_weights_per_dim
        if a["weight_mean"].shape != (n,) or a["weight_cov"].shape != (n, n):
            raise ValueError(f"weight_mean / weight_cov of shapes {a['weight_mean'].shape} / {a['weight_cov'].shape} "
                             f"do not fit {sm_dim} dims x {n_weights_per_dim} weights")
        self.promp = ProMP(sm_dim, n_weights_per_dim).from_weight_distribution(a["weight_mean"], a["weight_cov"])
        self.sm_dim = sm_dim
        ctx = {k.removeprefix("context_"): v for k, v in a.items() if k.startswith("context_")}
        self.context = ctx or None
        return self

    def given_task_params(self, task_params):
        """The library's ProMP with the weight distribution conditioned on γ (see the class docstring); a new
        object, as the library's own ``condition_position`` returns one."""
        from movement_primitives.promp import ProMP

        c = self.context
        g = np.asarray(task_params, dtype=float).reshape(-1)
        if g.shape != c["mu_g"].shape or not np.isfinite(g).all():
            raise ValueError(f"task_params must be {c['mu_g'].size} finite values, got {g.tolist()}")
        mean = c["mu_w"] + c["gain"] @ ((g - c["mu_g"]) / c["sd_g"])
        return ProMP(self.promp.n_dims, self.promp.n_weights_per_dim).from_weight_distribution(mean, c["cov"])

    def conditioned(self, conditions: list[Condition], task_params=None):
        if self.promp is None:
            raise RuntimeError("the baseline is not fitted: call fit(demos) first")
        if self.context is not None and task_params is None:
            raise ValueError("this baseline was fitted with task_params: give the episode's task_params (γ)")
        if self.context is None and task_params is not None:
            raise ValueError("this baseline was fitted without task_params: fit(demos, task_params=...) first")
        promp = self.promp if task_params is None else self.given_task_params(task_params)
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

    def predict(self, phases, conditions: list[Condition], task_params=None) -> tuple[np.ndarray, np.ndarray]:
        q = query_phases(phases)
        promp = self.conditioned(conditions, task_params)
        # The library rescales the query times by their maximum (T / max T), so it is always evaluated on
        # the whole [0, 1] grid and interpolated at the requested phases.
        grid = np.linspace(0.0, 1.0, GRID_POINTS)
        mean_g, var_g = promp.mean_trajectory(grid), promp.var_trajectory(grid)
        mean = np.stack([np.interp(q, grid, mean_g[:, d]) for d in range(self.sm_dim)], axis=1)
        var = np.stack([np.interp(q, grid, var_g[:, d]) for d in range(self.sm_dim)], axis=1)
        return mean.astype(np.float32), np.sqrt(np.maximum(var, 0.0)).astype(np.float32)


class DMPBaseline:
    """Dynamical Movement Primitive (Ijspeert et al. 2013) from ``movement_primitives.dmp``.

    A DMP reproduces one movement shape; it is fitted on the demonstrations' mean (all demos resampled to
    a common phase grid), as a single DMP learned from a set of demonstrations is. It generalizes to a new
    start (phase 0) and goal (phase 1) through its dynamics, and cannot be conditioned on anything else:
    :meth:`applies` tells whether a condition set is of that kind. Its prediction has no σ (zeros).
    """

    def __init__(self, n_weights_per_dim: int = 31):
        self.n_weights_per_dim = n_weights_per_dim
        self.dmp = None

    def fit(self, demos) -> DMPBaseline:
        from movement_primitives.dmp import DMP

        values, valid, phase = pad_demos(demos)
        self.grid = np.linspace(0.0, 1.0, values.shape[1])
        resampled = [
            np.stack([np.interp(self.grid, phase[i, valid[i]], values[i, valid[i], d]) for d in range(values.shape[2])], 1)
            for i in range(len(values))
        ]
        self.mean_demo = np.mean(resampled, axis=0)
        self.sm_dim = values.shape[2]
        self.dmp = DMP(n_dims=self.sm_dim, execution_time=1.0, dt=1.0 / (len(self.grid) - 1),
                       n_weights_per_dim=self.n_weights_per_dim)
        self.dmp.imitate(self.grid, self.mean_demo)
        return self

    @staticmethod
    def applies(conditions: list[Condition]) -> bool:
        """True if every condition fixes all SM dims at the start (phase 0) or at the goal (phase 1)."""
        return bool(conditions) and all(c.phase in (0.0, 1.0) and c.dims is None for c in conditions)

    def predict(self, phases, conditions: list[Condition]) -> tuple[np.ndarray, np.ndarray]:
        if self.dmp is None:
            raise RuntimeError("the baseline is not fitted: call fit(demos) first")
        q = query_phases(phases)
        if not self.applies(conditions):
            raise ValueError(
                "a DMP is conditioned only on its start (phase 0) and goal (phase 1), on all SM dims; got "
                + ", ".join(f"phase {c.phase} dims {c.dims or 'all'}" for c in conditions)
            )
        start, goal = self.mean_demo[0].copy(), self.mean_demo[-1].copy()
        for k, c in enumerate(conditions):
            if len(c.values) != self.sm_dim:
                raise ValueError(f"condition {k} has {len(c.values)} values; the SM has {self.sm_dim} dims")
            (start if c.phase == 0.0 else goal)[:] = c.values
        self.dmp.configure(start_y=start, goal_y=goal)
        t, y = self.dmp.open_loop()
        mean = np.stack([np.interp(q, t, y[:, d]) for d in range(self.sm_dim)], axis=1)
        return mean.astype(np.float32), np.zeros_like(mean, dtype=np.float32)

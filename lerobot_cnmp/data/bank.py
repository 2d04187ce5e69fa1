"""The demonstrations a CNMP trains on, held in memory as one flat SM table, and the training step's draw.

Both training paths use it: ``lerobot-train`` (the policy reads the dataset's numeric columns once, from its
parquet files, when LeRobot builds it with the dataset's metadata) and the in-memory API (arrays). A
training sample is an episode id; the draw takes ``k`` frames of that episode, each uniform over the *whole*
episode (independently, so a draw costs O(k) whatever the episode's length), with their phases. Per-item
loading in LeRobot's data loader then only has to deliver the episode id of a uniformly drawn frame: an
episode is drawn with probability proportional to its length, in both paths.

Phases come from the data: frame ``j`` of an episode has phase (timestamp_j - timestamp_0) /
(timestamp_last - timestamp_0), i.e. j / (T - 1) at a constant frame rate.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from lerobot_cnmp.data.sm_spec import SMSpec

STD_FLOOR = 1e-2
"""An SM dim's normalization std is at least this fraction of the median SM dim's std."""

TASK_STD_FLOOR = 0.1
"""A γ dim's normalization std is at least this fraction of the median γ dim's std. Higher than the SM's floor:
γ is one vector per episode that every prediction of the episode is conditioned on, so with few demos the
network fits whatever varies in it. A γ dim that varies ~30x less than the others is a fixed quantity read
with noise (coffee-push-v3: the mug's and the machine's resting height, std 0.6 mm against 12-72 mm for the
positions); scaled to unit variance, its noise was as loud as the real conditions, and CNMP with 10 demos
succeeded 74 % of the time against 84.7 % with this floor (docs/fewdemo.md, section 10). A dim within 10x of
the median keeps unit variance."""


def floored_std(std, fraction: float = STD_FLOOR) -> np.ndarray:
    """The normalization std: a dim that barely moves (e.g. a wrist held at one angle, whose std is IK round-off)
    would otherwise be scaled up to unit variance, and its noise, far below the model's σ floor, would dominate
    the NLL. The median, not the largest, sets the floor (``fraction`` times it): SM dims may mix units (metres,
    newtons). A dim that never moves at all in any dim's scale (all stds zero) keeps std 1."""
    std = np.asarray(std, dtype=np.float64).reshape(-1)
    med = float(np.median(std)) if std.size else 0.0
    floor = fraction * med if med > 0 else 0.0
    out = np.maximum(std, floor)
    out[out <= 1e-12] = 1.0
    return out.astype(np.float32)


class EpisodeBank:
    """Flat SM values ``[N, D]`` with per-frame phases, per-episode offsets/lengths and γ (first frame)."""

    def __init__(self, values: np.ndarray, phase: np.ndarray, starts: np.ndarray, lengths: np.ndarray,
                 episode_ids: np.ndarray, task_params: np.ndarray | None = None, durations_s: np.ndarray | None = None):
        self.values = torch.from_numpy(np.ascontiguousarray(values, dtype=np.float32))
        self.phase = torch.from_numpy(np.ascontiguousarray(phase, dtype=np.float32))
        self.episode_ids = np.asarray(episode_ids, dtype=np.int64)
        size = int(self.episode_ids.max()) + 1 if self.episode_ids.size else 0
        # dataset episode index -> row in this bank (-1: not loaded)
        self.row_of = torch.full((size,), -1, dtype=torch.long)
        self.row_of[torch.from_numpy(self.episode_ids)] = torch.arange(len(self.episode_ids))
        self.starts = torch.from_numpy(np.asarray(starts, dtype=np.int64))
        self.lengths = torch.from_numpy(np.asarray(lengths, dtype=np.int64))
        self.task_params = None if task_params is None else torch.from_numpy(np.asarray(task_params, np.float32))
        self.durations_s = None if durations_s is None else np.asarray(durations_s, np.float64)

    @property
    def n_episodes(self) -> int:
        return len(self.episode_ids)

    # ---- construction ----------------------------------------------------------------------------------

    @classmethod
    def from_arrays(cls, demos: list[np.ndarray], task_params: np.ndarray | None = None,
                    fps: float | None = None) -> EpisodeBank:
        """Demonstrations as a list of ``[T_i, D]`` arrays (checked by the caller) at ``fps`` (None: phase
        j / (T - 1), durations in frames)."""
        lengths = np.array([len(d) for d in demos], dtype=np.int64)
        starts = np.concatenate([[0], np.cumsum(lengths)[:-1]])
        phase = np.concatenate([np.arange(n) / (n - 1) for n in lengths])
        durations = (lengths - 1) / (fps or 1.0)
        return cls(np.concatenate(demos, 0), phase, starts, lengths, np.arange(len(demos)), task_params, durations)

    @classmethod
    def from_dataset(cls, root: str | Path, spec: SMSpec, episodes: list[int] | None = None) -> EpisodeBank:
        """Read the SM dims and γ of every episode from a local LeRobotDataset's parquet files (the numeric
        columns only: no images, no video decoding)."""
        import pyarrow as pa
        import pyarrow.parquet as pq

        root = Path(root)
        files = sorted((root / "data").glob("**/*.parquet"))
        if not files:
            raise FileNotFoundError(
                f"CNMP reads its demonstrations' numeric columns from the dataset's parquet files, and {root / 'data'} "
                "has none (a streaming dataset whose files are not local? CNMP needs them: download the dataset, "
                "or train without --dataset.streaming)")
        sm_cols = sorted({d.feature for d in spec.dims})
        task_cols = [k for k, _ in spec.task_features]
        cols = ["episode_index", "frame_index", "timestamp", *sm_cols, *[c for c in task_cols if c not in sm_cols]]
        table = pa.concat_tables([pq.read_table(f, columns=cols) for f in files])

        def column(name: str) -> np.ndarray:
            col = table.column(name).combine_chunks()
            if pa.types.is_list(col.type) or pa.types.is_fixed_size_list(col.type) or pa.types.is_large_list(col.type):
                flat = np.asarray(col.flatten().to_numpy(zero_copy_only=False), dtype=np.float64)
                return flat.reshape(len(col), -1)
            return np.asarray(col.to_numpy(zero_copy_only=False), dtype=np.float64).reshape(len(col), -1)

        ep = column("episode_index")[:, 0].astype(np.int64)
        frame = column("frame_index")[:, 0].astype(np.int64)
        ts = column("timestamp")[:, 0]
        order = np.lexsort((frame, ep))
        ep, frame, ts = ep[order], frame[order], ts[order]
        feats = {c: column(c)[order] for c in set(sm_cols) | set(task_cols)}
        values = np.stack([feats[d.feature][:, d.index] for d in spec.dims], axis=1)
        keep = np.ones(len(ep), dtype=bool) if episodes is None else np.isin(ep, np.asarray(episodes))
        ep, frame, ts, values = ep[keep], frame[keep], ts[keep], values[keep]
        feats = {k: v[keep] for k, v in feats.items()}
        ids, starts, lengths = np.unique(ep, return_index=True, return_counts=True)
        if not len(ids):
            raise ValueError(f"the dataset at {root} has no frames for the selected episodes")
        short = ids[lengths < 2]
        if short.size:
            raise ValueError(f"episode(s) {short.tolist()[:10]} have fewer than 2 frames: at least 2 define a phase")
        bad = ~np.isfinite(values)
        if bad.any():
            row, dim = np.argwhere(bad)[0]
            d = spec.dims[dim]
            raise ValueError(f"SM feature {d.feature!r} (dim {d.name!r}) holds NaN or inf in episode {int(ep[row])}, "
                             f"frame {int(frame[row])} ({int(bad.sum())} values in all)")
        t0 = ts[starts]
        t1 = ts[starts + lengths - 1]
        durations = t1 - t0
        if (durations <= 0).any():
            raise ValueError(f"episode {int(ids[np.argmax(durations <= 0)])} has non-increasing timestamps")
        rep = np.repeat(np.arange(len(ids)), lengths)
        phase = np.clip((ts - t0[rep]) / durations[rep], 0.0, 1.0)
        gamma = None
        if task_cols:
            gamma = np.concatenate([feats[c][starts] for c in task_cols], axis=1)
            if not np.isfinite(gamma).all():
                e = ids[np.argwhere(~np.isfinite(gamma))[0][0]]
                raise ValueError(f"task features {task_cols} hold NaN or inf at the first frame of episode {int(e)}")
            for i, g in spec.origins:  # task frames: the sensed dim minus the episode's γ dim
                values[:, i] -= gamma[rep, g]
        return cls(values.astype(np.float32), phase, starts, lengths, ids, gamma, durations)

    # ---- statistics ------------------------------------------------------------------------------------

    def sm_stats(self) -> tuple[np.ndarray, np.ndarray]:
        v = self.values.double()
        return v.mean(0).float().numpy(), floored_std(v.std(0, unbiased=False).numpy())

    def task_stats(self) -> tuple[np.ndarray, np.ndarray] | None:
        if self.task_params is None:
            return None
        g = self.task_params.double()
        return g.mean(0).float().numpy(), floored_std(g.std(0, unbiased=False).numpy(), TASK_STD_FLOOR)

    def median_duration_s(self) -> float:
        return float(np.median(self.durations_s))

    # ---- sampling --------------------------------------------------------------------------------------

    def rows(self, episode_index: Tensor) -> Tensor:
        ep = episode_index.long().reshape(-1).cpu()
        known = (ep >= 0) & (ep < len(self.row_of))
        rows = torch.where(known, self.row_of[ep.clamp(0, max(len(self.row_of) - 1, 0))], -1)
        if bool((rows < 0).any()):
            raise KeyError(f"episode index(es) {ep.tolist()[:8]} are not in the CNMP's demonstrations")
        return rows

    def task_params_of(self, episode_index: Tensor) -> Tensor | None:
        """γ of each named episode (its first frame), [B, G] raw units; None without task parameters."""
        return None if self.task_params is None else self.task_params[self.rows(episode_index)]

    def points_of(self, episode_index: Tensor, phases: tuple[float, ...]) -> Tensor:
        """The SM points at ``phases`` (frame round(phase * (length - 1))) of each named episode, [B, P, D] raw."""
        rows = self.rows(episode_index)
        offsets = torch.round(torch.tensor(phases, dtype=torch.float64)[None] * (self.lengths[rows, None] - 1))
        return self.values[self.starts[rows, None] + offsets.long()]

    def sample_episodes(self, n: int, generator: torch.Generator | None = None) -> Tensor:
        """``n`` dataset episode ids, each drawn with probability ∝ its length (as a uniform frame's episode)."""
        frames = torch.randint(int(self.lengths.sum()), (n,), generator=generator)
        rows = torch.searchsorted(self.starts, frames, right=True) - 1  # the episodes are stored back to back
        return torch.from_numpy(self.episode_ids)[rows]

    def draw(self, episode_index: Tensor, k: int, generator: torch.Generator | None = None):
        """``k`` frames of each episode, uniform over its whole length: (values [B, k, D], phase [B, k]), raw
        units, on the CPU."""
        rows = self.rows(episode_index)
        idx = self.starts[rows, None] + self._uniform_offsets(rows, k, generator)
        return self.values[idx], self.phase[idx]

    def _uniform_offsets(self, rows: Tensor, k: int, generator: torch.Generator | None) -> Tensor:
        """``k`` frame offsets per episode row, uniform over its length, [B, k]."""
        u = torch.rand((len(rows), k), generator=generator)
        return (u * self.lengths[rows, None]).long().clamp(max=(self.lengths[rows, None] - 1))

    def draw_feedback(self, episode_index: Tensor, m: int, generator: torch.Generator | None = None):
        """Per episode: its first frame, a uniform frame j, frame j + 1 (the last frame stays itself) and ``m``
        uniform frames, in that order: (values [B, 3 + m, D], phase [B, 3 + m]), raw units, on the CPU. The
        shape of execution's context (the start and the current sensed state) and its queries (now, next)."""
        rows = self.rows(episode_index)
        offs = self._uniform_offsets(rows, 1 + m, generator)
        j = offs[:, :1]
        nxt = (j + 1).clamp(max=self.lengths[rows, None] - 1)
        offs = torch.cat([torch.zeros_like(j), j, nxt, offs[:, 1:]], dim=1)
        idx = self.starts[rows, None] + offs
        return self.values[idx], self.phase[idx]

"""Demonstrations as arrays (numpy at the edges): padded into one batch, or read out of a LeRobotDataset."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lerobot_cnmp.data.sm_spec import TASK_PARAMS


def pad_demos(demos) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Demonstrations ``[N, T, D]`` or a list of ``[T_i, D]`` -> (values, valid, phase), padded to max T."""
    seqs = [np.asarray(d, dtype=np.float32) for d in (demos if isinstance(demos, (list, tuple)) else list(demos))]
    if not seqs:
        raise ValueError("no demonstrations given")
    for i, s in enumerate(seqs):
        if s.ndim != 2:
            raise ValueError(f"demonstration {i} must be [T, D] (frames, SM dims); got shape {s.shape}")
        if s.shape[0] < 2:
            raise ValueError(f"demonstration {i} has {s.shape[0]} frame(s); at least 2 define a phase")
        if not np.isfinite(s).all():
            raise ValueError(f"demonstration {i} contains NaN or infinite values")
    dims = {s.shape[1] for s in seqs}
    if len(dims) != 1:
        raise ValueError(f"demonstrations disagree on the SM dimension: {sorted(dims)}")
    t_max, d = max(s.shape[0] for s in seqs), dims.pop()
    values = np.zeros((len(seqs), t_max, d), dtype=np.float32)
    valid = np.zeros((len(seqs), t_max), dtype=bool)
    phase = np.zeros((len(seqs), t_max), dtype=np.float32)
    for i, s in enumerate(seqs):
        values[i, : len(s)], valid[i, : len(s)] = s, True
        phase[i, : len(s)] = np.arange(len(s)) / (len(s) - 1)
    return values, valid, phase


def query_phases(phases, dtype=np.float64) -> np.ndarray:
    """The phases a prediction is asked at, as a flat array of ``dtype``: non-empty, finite, in [0, 1]."""
    q = np.asarray(phases, dtype=dtype).reshape(-1)
    if q.size == 0 or not np.isfinite(q).all() or q.min() < 0 or q.max() > 1:
        raise ValueError("query phases must be a non-empty set of finite values in [0, 1]")
    return q


def load_demos(root: str | Path, repo_id: str | None = None) -> dict:
    """Every episode's ``action`` sequence (the SM trajectory) from a local LeRobotDataset.

    Returns ``{"demos": [array [T_i, D]], "task_params": [N, G] or None, "env_state": [N, E] or None,
    "episode_index": [N]}``; env_state / task_params are each episode's first frame."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    root = Path(root)
    if not (root / "meta" / "info.json").is_file():
        raise FileNotFoundError(f"{root} is not a LeRobotDataset folder (no meta/info.json)")
    ds = LeRobotDataset(repo_id or f"local/{root.name}", root=root)
    if "action" not in ds.features:
        raise KeyError(f"dataset {root} has no 'action' feature; features: {sorted(ds.features)}")
    cols = [c for c in ("action", "episode_index", "observation.environment_state", TASK_PARAMS) if c in ds.features]
    table = ds.hf_dataset.select_columns(cols).with_format("numpy")[:]
    ep = np.asarray(table["episode_index"]).reshape(-1)
    out: dict = {"demos": [], "episode_index": np.unique(ep), "task_params": None, "env_state": None}
    firsts = []
    for e in out["episode_index"]:
        rows = np.flatnonzero(ep == e)
        out["demos"].append(np.stack(table["action"][rows]).astype(np.float32))
        firsts.append(rows[0])
    for key, name in (("observation.environment_state", "env_state"), (TASK_PARAMS, "task_params")):
        if key in table:
            out[name] = np.stack([np.asarray(table[key][i], dtype=np.float32) for i in firsts])
    return out

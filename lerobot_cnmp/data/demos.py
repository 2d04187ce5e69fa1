"""Demonstrations out of a LeRobotDataset, as arrays (numpy at the edges)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lerobot_cnmp.policy.configuration_cnmp import TASK_PARAMS


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

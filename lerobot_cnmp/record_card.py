"""The dataset card (``README.md``) the recorder writes beside a recorded dataset: the sim's prose, the episodes
with their reset seeds and labels, the features, and the command that regenerates it."""

from __future__ import annotations

import collections
import os
from pathlib import Path

import numpy as np

from lerobot_cnmp.sims.registry import SIMS, SimSpec


def record_command(sim: str, root: Path, n_episodes: int, seed: int, repo_id: str, conditions: str,
             action_noise: str | None = None, max_failed: int = 0, demo_length: int | None = None,
             cameras: list[str] | None = None, camera_size: int | None = None) -> str:
    cmd = f"lerobot-cnmp-record --sim {sim} --root {root} --n_episodes {n_episodes} --seed {seed}"
    if cameras:
        cmd += " --cameras " + " ".join(cameras) + (f" --camera_size {camera_size}" if camera_size else "")
    if demo_length is not None and demo_length != SIMS[sim].demo_length:
        cmd += f" --demo_length {demo_length}"
    if action_noise is not None:
        cmd += f" --action_noise {action_noise}"
    if max_failed:
        cmd += f" --max_failed {max_failed}"
    if repo_id != f"lerobot-cnmp/{sim}":
        cmd += f" --repo_id {repo_id}"
    spec = SIMS[sim]
    if conditions != spec.default_conditions:
        cmd += f" --conditions {conditions}"
    return cmd


def _noise_note(action_noise: np.ndarray | None) -> str:
    if action_noise is None:
        return ""
    return (f"\nRecorded with injected execution noise (DART, Laskey et al. 2017): the env executed the expert's "
            f"action plus Gaussian noise of std {np.round(action_noise, 4).tolist()} per action dim (clipped to the "
            f"action space), while `action` holds the expert's own, noise-free action at the state reached. The "
            f"demos thus show how the expert recovers from deviations.\n")


def _dropped_note(dropped: list[int] | None) -> str:
    if not dropped:
        return ""
    return (f"\n{len(dropped)} demo(s) failed and were dropped (the next seed was recorded instead): reset seeds "
            f"{dropped}.\n")


def write_card(
    path: Path,
    *,
    sim: str,
    spec: SimSpec,
    cfg,
    features: dict,
    repo_id: str,
    n_episodes: int,
    seed: int,
    conditions: str,
    labels: list[str],
    kinds: list[str],
    command: str,
    elapsed_s: float,
    action_noise: np.ndarray | None = None,
    seeds: list[int] | None = None,
    dropped: list[int] | None = None,
) -> None:
    counts = collections.Counter(labels)
    feat_rows = "\n".join(
        f"| `{k}` | {v['dtype']} | {list(v['shape'])} | {', '.join(v['names'][:6])}"
        f"{', ...' if len(v['names']) > 6 else ''} |"
        for k, v in features.items()
    )
    seeds = seeds if seeds is not None else [seed + i for i in range(len(labels))]
    ep_rows = "\n".join(f"| {i} | {sd} | {lab} | {kind} |" for i, (sd, lab, kind) in enumerate(zip(seeds, labels, kinds)))
    count_rows = "\n".join(f"| {lab} | {n} |" for lab, n in sorted(counts.items()))
    card = f"""---
license: apache-2.0
task_categories:
- robotics
tags:
- LeRobot
- cnmp
- movement-primitives
- mujoco
configs:
- config_name: default
  data_files: data/*/*.parquet
---

# {repo_id}

Scripted demonstrations of the `{sim}` sim of
lerobot-cnmp (Conditional Neural Movement Primitives, Seker et al., RSS 2019),
in LeRobotDataset v3 format.

## Sim and task family

{spec.description}

Conditions used while recording: `{conditions}`.

## Episodes

{n_episodes} episodes of {spec.demo_length} frames each at {cfg.fps} fps
({spec.demo_length / cfg.fps:.2f} s per episode), every one checked to succeed in the sim (its
`info["is_success"]`, see above).

| episode label | episodes |
|---|---|
{count_rows}

| episode | reset seed | label | conditions |
|---|---|---|---|
{ep_rows}

## Features

| key | dtype | shape | names |
|---|---|---|---|
{feat_rows}

Each frame holds the observation *before* the action and the action commanded at that step (the
position-servo target). {spec.features_note}
{_noise_note(action_noise)}{_dropped_note(dropped)}
## Regenerate

```bash
{command}
```

Seed {seed}: episode i is reset with the seed in its row above (seed {seed} + i unless demos were dropped), so the same command gives identical data.
Generating it took {elapsed_s:.1f} s ({elapsed_s / n_episodes:.3f} s per episode) on a machine with
{os.cpu_count()} CPU cores.

## License

Apache-2.0.
"""
    path.write_text(card)

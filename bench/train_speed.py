"""Training throughput: the stock ``lerobot-train`` path against the in-memory API, same model, batch and
sampling, on the config's dataset and on a copy of it resampled to long episodes (1000 frames by default).

    python -m bench.train_speed [--config configs/cnmp_obstacle2d.json] [--batch_size 8] [--steps 400]
                                [--long_frames 1000] [--long_episodes 16]

- API: ``CNMPModel.fit`` on the dataset's demos held in memory (no loader), with the config's model,
  sampling (draws per sample included) and optimizer.
- lerobot-train: the real CLI with the config (its workers and model), run as a subprocess; steps/s =
  1 / (update time + data wait) from its own log lines, skipping the first (start-up) interval.
Both draw each sample's observations and queries from its whole episode through the same
``EpisodeBank`` and ``CNMPPolicy.forward``; the long-episode run shows that the per-sample cost does not
grow with the episode length (``--long_frames 0`` skips it).
Both sides run with the same number of torch threads: ``--threads``, else ``OMP_NUM_THREADS``, else one per
CPU core (the lerobot-train subprocess gets it as its ``OMP_NUM_THREADS``); the JSON's ``threads`` says which.
- ``train_step_ms_batch1_api``: the API at batch 1 with one draw per step (the paper's training setting).
With an image config (``--config configs/cnmp_room.json``, ``use_images``) only lerobot-train is measured: the
in-memory API takes SM trajectories, not images. Last line: one JSON object with ``train_steps_per_s_api``
(null for images) and ``train_steps_per_s_lerobot``.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.common import CONFIG, REPO, add_threads_argument, api_model, child_environment, torch_threads


def dataset_root(cfg: dict) -> Path:
    return REPO / cfg["dataset"]["root"]


def median_rate(model, demos, batch_size: int, steps: int, task_params=None) -> float:
    model.fit(demos, task_params=task_params, steps=20, batch_size=batch_size, progress=False)  # warm-up
    rates = []
    for _ in range(3):  # the median of 3 runs, so a moment of load on a shared machine does not decide it
        t0 = time.perf_counter()
        model.fit(demos, task_params=task_params, steps=max(steps // 3, 1), batch_size=batch_size, progress=False)
        rates.append(max(steps // 3, 1) / (time.perf_counter() - t0))
    return float(np.median(rates))


def lerobot_steps_per_s(config: Path, dataset: Path, batch_size: int, steps: int, extra: list[str],
                        threads: int) -> dict:
    log_freq = max(steps // 8, 10)
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [
            str(Path(sys.executable).parent / "lerobot-train"), f"--config_path={config}",
            f"--dataset.root={dataset}", f"--steps={steps}",
            f"--batch_size={batch_size}", f"--log_freq={log_freq}", "--save_checkpoint=false",
            "--policy.device=cpu", f"--output_dir={Path(tmp) / 'out'}", *extra,
        ]
        t0 = time.perf_counter()
        out = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp, env=child_environment(threads))
        wall = time.perf_counter() - t0
    if out.returncode != 0:
        raise RuntimeError(f"lerobot-train failed:\n{out.stderr[-3000:]}")
    rows = re.findall(r"updt_s:([0-9.]+) data_s:([0-9.]+)", out.stdout + out.stderr)
    if len(rows) < 2:
        raise RuntimeError("could not read lerobot-train's step timings from its log")
    updt, data = (np.array([float(r[i]) for r in rows[1:]]) for i in (0, 1))
    return {"steps_per_s": float(1.0 / (updt + data).mean()), "update_s": float(updt.mean()),
            "data_wait_s": float(data.mean()), "wall_s_incl_startup": wall}


def resampled_dataset(src: Path, dst: Path, frames: int, episodes: int) -> Path:
    """A copy of ``src`` (first ``episodes`` episodes) with every vector feature resampled to ``frames`` frames
    per episode (linear interpolation over phase), written as a LeRobotDataset at the same fps."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset("bench/src", root=src)
    keys = [k for k, f in ds.features.items() if f["dtype"] == "float32" and k not in ("timestamp",)]
    table = ds.hf_dataset.select_columns(["episode_index", *keys]).with_format("numpy")[:]
    ep = np.asarray(table["episode_index"]).reshape(-1)
    features = {k: {"dtype": "float32", "shape": tuple(ds.features[k]["shape"]), "names": ds.features[k]["names"]}
                for k in keys}
    out = LeRobotDataset.create("bench/long", fps=ds.fps, root=dst, features=features, use_videos=False)
    for e in np.unique(ep)[:episodes]:
        rows = np.flatnonzero(ep == e)
        t_old = np.linspace(0, 1, len(rows))
        t_new = np.linspace(0, 1, frames)
        cols = {k: np.stack(table[k][rows]).astype(np.float32) for k in keys}
        res = {k: np.stack([np.interp(t_new, t_old, v[:, j]) for j in range(v.shape[1])], 1).astype(np.float32)
               for k, v in cols.items()}
        for i in range(frames):
            out.add_frame({**{k: res[k][i] for k in keys}, "task": "long"})
        out.save_episode()
    out.finalize()
    return dst


def measure(config: Path, cfg: dict, dataset: Path, batch_size: int, steps: int, extra: list[str],
            threads: int) -> dict:
    from lerobot_cnmp.data.demos import load_demos

    demos = load_demos(dataset)
    model = api_model(cfg)
    api = median_rate(model, demos["demos"], batch_size, steps, demos["task_params"])
    stock = lerobot_steps_per_s(config, dataset, batch_size, steps, extra, threads)
    return {"api": api, **stock, "frames_per_episode": int(np.median([len(d) for d in demos["demos"]]))}


def main() -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--config", type=Path, default=CONFIG, help="a lerobot-train config of configs/")
    p.add_argument("--batch_size", type=int, default=None, help="(default: the config's)")
    p.add_argument("--steps", type=int, default=400)
    p.add_argument("--long_frames", type=int, default=1000, help="frames per episode of the long-episode run (0: skip)")
    p.add_argument("--long_episodes", type=int, default=16)
    p.add_argument("--lerobot_args", default="", help="extra lerobot-train overrides in one string, e.g. \"--num_workers=1\"")
    add_threads_argument(p)
    args = p.parse_args()
    config = args.config.resolve()
    cfg = json.loads(config.read_text())
    if not (dataset_root(cfg) / "meta" / "info.json").is_file():
        p.error(f"no dataset at {dataset_root(cfg)}: record it with lerobot-cnmp-record first")
    if args.batch_size is None:
        args.batch_size = cfg["batch_size"]
    try:
        threads, threads_from = torch_threads(args.threads)
    except ValueError as e:
        p.error(str(e))
    import torch

    torch.set_num_threads(threads)
    images = bool(cfg["policy"].get("use_images"))
    extra = args.lerobot_args.split()
    runs: dict[str, dict] = {}
    step_ms_batch1 = None
    if images:  # the in-memory API takes SM trajectories, not images
        runs["dataset"] = {"api": None, **lerobot_steps_per_s(config, dataset_root(cfg), args.batch_size, args.steps, extra,
                                                             threads)}
    else:
        runs["dataset"] = measure(config, cfg, dataset_root(cfg), args.batch_size, args.steps, extra, threads)
        # The paper's setting (one demo, one draw per step), to set beside the original code's ~1.5 ms/step.
        batch1 = {**cfg, "policy": {**cfg["policy"], "draws_per_sample": 1}}
        from lerobot_cnmp.data.demos import load_demos

        step_ms_batch1 = 1e3 / median_rate(api_model(batch1), load_demos(dataset_root(cfg))["demos"], 1, args.steps)
        if args.long_frames:
            with tempfile.TemporaryDirectory() as tmp:
                long_root = resampled_dataset(dataset_root(cfg), Path(tmp) / "long", args.long_frames, args.long_episodes)
                runs["long"] = measure(config, cfg, long_root, args.batch_size, args.steps, extra, threads)
    main_run = runs["dataset"]
    ratio = lambda r: None if r["api"] is None else round(r["api"] / r["steps_per_s"], 2)  # noqa: E731
    res = {
        "config": str(config.relative_to(REPO)) if config.is_relative_to(REPO) else str(config),
        "train_steps_per_s_api": None if images else round(main_run["api"], 2),
        "train_steps_per_s_lerobot": round(main_run["steps_per_s"], 2),
        "api_over_lerobot": ratio(main_run),
        "train_step_ms_batch1_api": None if step_ms_batch1 is None else round(step_ms_batch1, 3),
        "lerobot_update_s": round(main_run["update_s"], 4),
        "lerobot_data_wait_s": round(main_run["data_wait_s"], 4),
        "batch_size": args.batch_size,
        "draws_per_sample": cfg["policy"].get("draws_per_sample", 1),
        "num_workers": cfg.get("num_workers"),
        "lerobot_overrides": args.lerobot_args,
        "cpus": os.cpu_count(),
        "threads": threads,
        "threads_from": threads_from,
    }
    if "long" in runs:
        r = runs["long"]
        res.update({"long_frames_per_episode": r["frames_per_episode"], "long_steps_per_s_api": round(r["api"], 2),
                    "long_steps_per_s_lerobot": round(r["steps_per_s"], 2), "long_api_over_lerobot": ratio(r),
                    "long_lerobot_data_wait_s": round(r["data_wait_s"], 4)})
    print(f"both sides: {threads} torch thread(s) (from {threads_from})")
    print(f"{'dataset':<10}{'frames/ep':>10}{'path':>16}{'batch':>6}{'steps/s':>10}")
    for name, r in runs.items():
        frames = r.get("frames_per_episode", "")
        if r["api"] is not None:
            print(f"{name:<10}{frames:>10}{'in-memory API':>16}{args.batch_size:>6}{r['api']:>10.1f}")
        print(f"{name:<10}{frames:>10}{'lerobot-train':>16}{args.batch_size:>6}{r['steps_per_s']:>10.1f}"
              f"   (update {r['update_s'] * 1e3:.1f} ms + data wait {r['data_wait_s'] * 1e3:.1f} ms)")
        if r["api"] is not None:
            print(f"{'':<10}{'':>10}  API / lerobot-train = {ratio(r):.2f}x")
    if step_ms_batch1 is not None:
        print(f"in-memory API, batch 1, 1 draw (the paper's setting): {step_ms_batch1:.2f} ms/step")
    print(json.dumps(res))
    return res


if __name__ == "__main__":
    main()

"""Training throughput: the stock ``lerobot-train`` path against the in-memory API, same batch size.

    python bench/train_speed.py [--config configs/cnmp_obstacle2d.json] [--batch_size 8] [--steps 400]

- API: ``CNMPModel.fit`` on the dataset's demos held in memory (whole episodes, no loader), with the
  config's model, sampling (draws per sample included) and optimizer.
- lerobot-train: the real CLI with ``configs/cnmp_obstacle2d.json`` (its window, workers and model), run
  as a subprocess; steps/s = 1 / (update time + data wait) from its own log lines, skipping the first
  (start-up) interval. Both use the config's model and sampling settings.
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

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import CONFIG, REPO, api_model  # noqa: E402


def dataset_root(cfg: dict) -> Path:
    return REPO / cfg["dataset"]["root"]


def api_steps_per_s(cfg: dict, batch_size: int, steps: int) -> float:
    from lerobot_cnmp.data import load_demos

    demos = load_demos(dataset_root(cfg))["demos"]
    model = api_model(cfg)
    return median_rate(model, demos, batch_size, steps)


def median_rate(model, demos, batch_size: int, steps: int) -> float:
    model.fit(demos, steps=20, batch_size=batch_size, progress=False)  # warm-up
    rates = []
    for _ in range(3):  # the median of 3 runs, so a moment of load on a shared machine does not decide it
        t0 = time.perf_counter()
        model.fit(demos, steps=max(steps // 3, 1), batch_size=batch_size, progress=False)
        rates.append(max(steps // 3, 1) / (time.perf_counter() - t0))
    return float(np.median(rates))


def lerobot_steps_per_s(config: Path, dataset: Path, batch_size: int, steps: int, extra: list[str]) -> dict:
    log_freq = max(steps // 8, 10)
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [
            str(Path(sys.executable).parent / "lerobot-train"), f"--config_path={config}",
            f"--dataset.root={dataset}", f"--steps={steps}",
            f"--batch_size={batch_size}", f"--log_freq={log_freq}", "--save_checkpoint=false",
            "--policy.device=cpu", f"--output_dir={Path(tmp) / 'out'}", *extra,
        ]
        t0 = time.perf_counter()
        out = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp,
                             env={**os.environ, "HF_HUB_OFFLINE": "1"})
        wall = time.perf_counter() - t0
    if out.returncode != 0:
        raise RuntimeError(f"lerobot-train failed:\n{out.stderr[-3000:]}")
    rows = re.findall(r"updt_s:([0-9.]+) data_s:([0-9.]+)", out.stdout + out.stderr)
    if len(rows) < 2:
        raise RuntimeError("could not read lerobot-train's step timings from its log")
    updt, data = (np.array([float(r[i]) for r in rows[1:]]) for i in (0, 1))
    return {"steps_per_s": float(1.0 / (updt + data).mean()), "update_s": float(updt.mean()),
            "data_wait_s": float(data.mean()), "wall_s_incl_startup": wall}


def main() -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--config", type=Path, default=CONFIG, help="a lerobot-train config of configs/")
    pre, _ = p.parse_known_args()
    config = pre.config.resolve()
    cfg = json.loads(config.read_text())
    if not (dataset_root(cfg) / "meta" / "info.json").is_file():
        p.error(f"no dataset at {dataset_root(cfg)}: record it with lerobot-cnmp-record first")
    p.add_argument("--batch_size", type=int, default=cfg["batch_size"])
    p.add_argument("--steps", type=int, default=400)
    p.add_argument("--lerobot_args", default="", help="extra lerobot-train overrides in one string, e.g. \"--num_workers=1\"")
    args = p.parse_args()
    import torch

    torch.set_num_threads(min(2, os.cpu_count() or 1))
    images = bool(cfg["policy"].get("use_images"))
    api = step_ms_batch1 = None
    if not images:
        api = api_steps_per_s(cfg, args.batch_size, args.steps)
        # The paper's setting (one demo, one draw per step), to set beside the original code's ~1.5 ms/step.
        batch1 = {**cfg, "policy": {**cfg["policy"], "draws_per_sample": 1}}
        from lerobot_cnmp.data import load_demos

        step_ms_batch1 = 1e3 / median_rate(api_model(batch1), load_demos(dataset_root(cfg))["demos"], 1, args.steps)
    stock = lerobot_steps_per_s(config, dataset_root(cfg), args.batch_size, args.steps, args.lerobot_args.split())
    res = {
        "config": str(config.relative_to(REPO)) if config.is_relative_to(REPO) else str(config),
        "train_steps_per_s_api": None if images else round(api, 2),
        "train_steps_per_s_lerobot": round(stock["steps_per_s"], 2),
        "api_over_lerobot": None if images else round(api / stock["steps_per_s"], 2),
        "train_step_ms_batch1_api": None if images else round(step_ms_batch1, 3),
        "lerobot_update_s": round(stock["update_s"], 4),
        "lerobot_data_wait_s": round(stock["data_wait_s"], 4),
        "batch_size": args.batch_size,
        "window_size": cfg["policy"].get("window_size"),
        "num_workers": cfg.get("num_workers"),
        "lerobot_overrides": args.lerobot_args,
        "cpus": os.cpu_count(),
    }
    print(f"{'path':<16}{'batch':>6}{'steps/s':>10}")
    if not images:
        print(f"{'in-memory API':<16}{args.batch_size:>6}{api:>10.1f}")
        print(f"{'in-memory API':<16}{1:>6}{1e3 / step_ms_batch1:>10.1f}   ({step_ms_batch1:.2f} ms/step; 1 draw, "
              "the paper's setting)")
    print(f"{'lerobot-train':<16}{args.batch_size:>6}{stock['steps_per_s']:>10.1f}"
          f"   (update {stock['update_s'] * 1e3:.1f} ms + data wait {stock['data_wait_s'] * 1e3:.1f} ms)")
    if not images:
        print(f"API / lerobot-train = {res['api_over_lerobot']:.2f}x")
    print(json.dumps(res))
    return res


if __name__ == "__main__":
    main()

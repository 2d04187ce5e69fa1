"""Training time to a fixed validation error, in-memory API vs ``lerobot-train``, on the 2D obstacle task.

    python -m bench.time_to_error [--steps 3000] [--every 250] [--threshold 0.03]

Both paths train the model and sampling of ``configs/cnmp_obstacle2d.json`` (batch size, draws, n_max,
m_max, learning rate and its cosine decay) for ``--steps`` steps, the decay spread over that run. Every
``--every`` steps the model is scored on validation tasks that are not in the dataset (fresh tasks of the
sim, both modes): given the start and one via point, the mean distance between the predicted 200-step
trajectory and the task's true path. Reported: the training time (start-up excluded) until the error
first drops to ``--threshold``, for each path.
- API: ``CNMPModel.fit`` with a callback; scoring time is excluded.
- lerobot-train: the CLI saving a checkpoint every ``--every`` steps; a checkpoint's time is its save
  time minus the time the training loop started (from LeRobot's log), so checkpoint writing is included.
Both run with the same number of torch threads (``--threads``, else ``OMP_NUM_THREADS``, else one per CPU core).
Last line: one JSON object.
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import tempfile
import time
from datetime import datetime
from pathlib import Path

import numpy as np

from bench.common import CONFIG, DATASET, add_threads_argument, api_model, child_environment, torch_threads

PHASES = np.linspace(0.0, 1.0, 200)


def validation_set(n: int, seed: int):
    """``n`` fresh tasks: (conditions: start + a via point, true path [200, 2])."""
    from lerobot_cnmp.execution.conditions import Condition
    from lerobot_cnmp.sims.obstacle2d.task import Obstacle2DTask

    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        task = Obstacle2DTask.sample(rng)
        t = float(rng.uniform(0.3, 0.7))
        conds = [Condition(0.0, tuple(float(v) for v in task.start)), Condition(t, tuple(float(v) for v in task.position(t)))]
        out.append((conds, task.position(PHASES)))
    return out


def validation_error(model, val) -> float:
    return float(np.mean([np.linalg.norm(model.predict(PHASES, c)[0] - path, axis=1).mean() for c, path in val]))


def first_below(points: list[tuple[int, float, float]], threshold: float):
    """(steps, seconds) of the first (steps, seconds, error) with error <= threshold, else (None, None)."""
    for steps, seconds, err in points:
        if err <= threshold:
            return steps, seconds
    return None, None


def run_api(cfg: dict, steps: int, every: int, val) -> list[tuple[int, float, float]]:
    from lerobot_cnmp.data.demos import load_demos

    demos = load_demos(DATASET)["demos"]
    model = api_model(cfg)
    points, clock = [], {"train": 0.0, "since": time.perf_counter()}

    def callback(done, m):
        clock["train"] += time.perf_counter() - clock["since"]
        points.append((done, clock["train"], validation_error(m, val)))
        clock["since"] = time.perf_counter()

    model.fit(demos, steps=steps, batch_size=cfg["batch_size"], seed=cfg.get("seed", 0), progress=False,
              callback=callback, callback_every=every)
    return points


def run_lerobot(cfg: dict, steps: int, every: int, val, threads: int) -> list[tuple[int, float, float]]:
    from lerobot_cnmp.api import CNMPModel

    with tempfile.TemporaryDirectory() as tmp:
        out_dir = Path(tmp) / "out"
        cmd = [
            str(Path(sys.executable).parent / "lerobot-train"), f"--config_path={CONFIG}",
            f"--dataset.root={DATASET}", f"--steps={steps}", f"--save_freq={every}", f"--log_freq={every}",
            "--policy.device=cpu", f"--output_dir={out_dir}",
        ]
        proc = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp, env=child_environment(threads))
        log = proc.stdout + proc.stderr
        if proc.returncode != 0:
            raise RuntimeError(f"lerobot-train failed:\n{log[-3000:]}")
        started = re.search(r"(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d).*Start offline training", log)
        if started is None:
            raise RuntimeError("could not find the start of the training loop in lerobot-train's log")
        t0 = datetime.strptime(started.group(1), "%Y-%m-%d %H:%M:%S").timestamp()
        points = []
        for ckpt in sorted((out_dir / "checkpoints").glob("[0-9]*")):
            pretrained = ckpt / "pretrained_model"
            seconds = (pretrained / "model.safetensors").stat().st_mtime - t0
            points.append((int(ckpt.name), seconds, validation_error(CNMPModel.load(pretrained), val)))
    return points


def main() -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--steps", type=int, default=3000)
    p.add_argument("--every", type=int, default=250)
    p.add_argument("--threshold", type=float, default=0.03)
    p.add_argument("--validation", type=int, default=40, help="validation tasks")
    p.add_argument("--seed", type=int, default=500000)
    add_threads_argument(p)
    args = p.parse_args()
    try:
        threads, threads_from = torch_threads(args.threads)
    except ValueError as e:
        p.error(str(e))
    import torch

    torch.set_num_threads(threads)
    cfg = json.loads(CONFIG.read_text())
    val = validation_set(args.validation, args.seed)
    curves = {"api": run_api(cfg, args.steps, args.every, val),
              "lerobot": run_lerobot(cfg, args.steps, args.every, val, threads)}
    res: dict = {"threshold": args.threshold, "steps": args.steps, "batch_size": cfg["batch_size"],
                 "threads": threads, "threads_from": threads_from}
    print(f"both paths: {threads} torch thread(s) (from {threads_from})")
    print(f"validation error (mean distance to the true path) every {args.every} steps")
    print(f"{'steps':>6}" + "".join(f"{k + ' s':>12}{k + ' err':>12}" for k in curves))
    for row in zip(*curves.values(), strict=False):
        print(f"{row[0][0]:>6}" + "".join(f"{s:>12.1f}{e:>12.4f}" for _, s, e in row))
    for k, pts in curves.items():
        steps, seconds = first_below(pts, args.threshold)
        res[f"time_to_error_s_{k}"] = None if seconds is None else round(seconds, 1)
        res[f"steps_to_error_{k}"] = steps
        res[f"final_validation_error_{k}"] = round(pts[-1][2], 4)
        got = "not reached" if seconds is None else f"{seconds:.1f} s ({steps} steps)"
        print(f"time to error <= {args.threshold}: {k:<8} {got}")
    print(json.dumps(res))
    return res


if __name__ == "__main__":
    main()

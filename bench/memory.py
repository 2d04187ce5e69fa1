"""Peak resident memory (RSS) of training and of inference, each in a fresh process.

    python -m bench.memory [--checkpoint CKPT] [--train_steps 200]

- ``peak_rss_train_mb``: ``lerobot-train`` with ``configs/cnmp_obstacle2d.json`` (the stock path);
- ``peak_rss_train_api_mb``: the in-memory ``CNMPModel.fit`` on the same demos and settings;
- ``peak_rss_inference_mb``: ``lerobot-eval`` of a checkpoint in the sim (2 episodes, LeRobot's rollout
  and video writing included);
- ``peak_rss_inference_api_mb``: loading a checkpoint with ``CNMPModel.load`` and predicting trajectories.
Each figure is the process's own ``ru_maxrss`` (Linux: KiB), read when it ends; imports (torch, LeRobot)
are part of it, as they are for a user; ``rss_imports_only_mb`` is that part alone. Without ``--checkpoint`` a small model is fitted and saved first.
Last line: one JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from bench.common import CONFIG, DATASET, REPO

# Runs a module as __main__ (as its console script does) and reports the process's peak RSS at the end.
RUN_MODULE = """
import resource, runpy, sys
module = sys.argv[1]
sys.argv = [module, *sys.argv[2:]]
try:
    runpy.run_module(module, run_name="__main__", alter_sys=True)
finally:
    print(f"PEAK_RSS_KB={resource.getrusage(resource.RUSAGE_SELF).ru_maxrss}", file=sys.stderr, flush=True)
"""

RUN_CODE = """
import resource, sys
try:
    exec(sys.argv[1])
finally:
    print(f"PEAK_RSS_KB={resource.getrusage(resource.RUSAGE_SELF).ru_maxrss}", file=sys.stderr, flush=True)
"""

# run with the repository root as the working directory, where `bench` is importable
API_TRAIN = """
from bench.common import DATASET, api_model, config
from lerobot_cnmp.data.demos import load_demos
cfg = config()
model = api_model(cfg)
model.fit(load_demos(DATASET)["demos"], steps={steps}, batch_size=cfg["batch_size"], progress=False)
"""

API_INFER = """
import numpy as np
from lerobot_cnmp.api import CNMPModel, Condition
model = CNMPModel.load({checkpoint!r})
for t in np.linspace(0.3, 0.7, 50):
    model.predict(np.linspace(0, 1, 200), [Condition(0.0, (0.0, 0.2)), Condition(float(t), (float(t), 0.5))])
"""


def peak_rss_mb(argv: list[str], cwd: str) -> float:
    proc = subprocess.run([sys.executable, *argv], capture_output=True, text=True, cwd=cwd,
                          env={**os.environ, "HF_HUB_OFFLINE": "1", "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")})
    if proc.returncode != 0:
        raise RuntimeError(f"{argv[:3]} failed:\n{(proc.stdout + proc.stderr)[-3000:]}")
    for line in reversed(proc.stderr.splitlines()):
        if line.startswith("PEAK_RSS_KB="):
            return int(line.split("=")[1]) / 1024
    raise RuntimeError("the process did not report its peak RSS")


def main() -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", default=None)
    p.add_argument("--train_steps", type=int, default=200)
    args = p.parse_args()
    res: dict = {}
    with tempfile.TemporaryDirectory() as tmp:
        ckpt = args.checkpoint
        if ckpt is not None:
            from bench.common import provenance

            res_ckpt = provenance(ckpt)
        else:
            res_ckpt = {"path": None, "step": 20, "trained_by": "this bench (RSS does not depend on the weights)",
                        "training_command": "CNMPModel.fit(<cnmp_obstacle2d demos>, steps=20) in a child process"}
            ckpt = str(Path(tmp) / "ckpt")
            code = API_TRAIN.format(steps=20) + f"\nmodel.save({ckpt!r})\n"
            peak_rss_mb(["-c", RUN_CODE, code], str(REPO))
        res["peak_rss_train_mb"] = peak_rss_mb(
            ["-c", RUN_MODULE, "lerobot.scripts.lerobot_train", f"--config_path={CONFIG}", f"--dataset.root={DATASET}",
             f"--steps={args.train_steps}", f"--log_freq={args.train_steps}", "--save_checkpoint=false",
             "--policy.device=cpu", f"--output_dir={Path(tmp) / 'train'}"], tmp)
        res["peak_rss_train_api_mb"] = peak_rss_mb(
            ["-c", RUN_CODE, API_TRAIN.format(steps=args.train_steps)], str(REPO))
        res["peak_rss_inference_mb"] = peak_rss_mb(
            ["-c", RUN_MODULE, "lerobot.scripts.lerobot_eval", f"--policy.path={ckpt}", "--env.type=cnmp_obstacle2d",
             "--eval.n_episodes=2", "--eval.batch_size=2", "--policy.device=cpu", f"--output_dir={Path(tmp) / 'eval'}"],
            tmp)
        res["peak_rss_inference_api_mb"] = peak_rss_mb(["-c", RUN_CODE, API_INFER.format(checkpoint=ckpt)], tmp)
        res["rss_imports_only_mb"] = peak_rss_mb(
            ["-c", RUN_CODE, "import lerobot_cnmp.api, lerobot_cnmp.data, lerobot.datasets.lerobot_dataset"], tmp)
    res = {k: round(v, 1) for k, v in res.items()}
    res_full = {**res, "checkpoint": res_ckpt}
    labels = {"peak_rss_train_mb": "train, lerobot-train", "peak_rss_train_api_mb": "train, in-memory API",
              "peak_rss_inference_mb": "inference, lerobot-eval", "peak_rss_inference_api_mb": "inference, API",
              "rss_imports_only_mb": "(imports alone: torch, LeRobot)"}
    print(f"{'process':<28}{'peak RSS (MB)':>14}")
    for k, label in labels.items():
        print(f"{label:<28}{res[k]:>14.1f}")
    print(json.dumps(res_full))
    return res_full


if __name__ == "__main__":
    main()

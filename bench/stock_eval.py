"""Stock ``lerobot-train`` + ``lerobot-eval`` success of every sim's committed config: the figures the README's
results table quotes, re-run in one command.

    python -m bench.stock_eval                       # every cell, one after the other (~45 min on 2 cores)
    python -m bench.stock_eval --cells obstacle2d weights --out outputs/stock

Per cell: ``lerobot-train --config_path=configs/<config>.json --policy.device=cpu`` (its steps and seed), then
``lerobot-eval`` on the cell's env(s) with the README's episodes and seed. A cell whose dataset is not on disk
(cnmp_room: ``bash run.sh room`` records it) is an error, not a skip. Each finished cell is written to
``<out>/<cell>.json`` at once (a long run keeps what it measured); the last line is one JSON object with the
commit, date, commands, training time and pc_success of every cell run.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from datetime import date
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
EVAL = ["--eval.batch_size=10", "--policy.device=cpu"]

CELLS: dict[str, tuple[str, list[tuple[str, list[str]]]]] = {
    # cell: (config, [(eval label, lerobot-eval options)])
    "obstacle2d": ("cnmp_obstacle2d", [("stock", ["--env.type=cnmp_obstacle2d", "--eval.n_episodes=50", "--seed=100000"])]),
    "pickplace": ("cnmp_pickplace", [("stock", ["--env.type=cnmp_pickplace", "--eval.n_episodes=30"])]),
    "weights": ("cnmp_weights", [
        ("stock", ["--env.type=cnmp_weights", "--eval.n_episodes=50", "--seed=100000"]),
        ("weight_switch", ["--env.type=cnmp_weights", "--env.perturbation=weight_switch", "--eval.n_episodes=50",
                           "--seed=100000"]),
    ]),
    "room": ("cnmp_room", [
        (c, ["--env.type=cnmp_room", f"--env.condition={c}", "--eval.n_episodes=50", "--seed=100000"])
        for c in ("start_end", "via_end", "via")
    ]),
    "so101": ("cnmp_so101", [("stock", ["--env.type=cnmp_so101", "--eval.n_episodes=50", "--seed=100000"])]),
    **{f"metaworld_{t}": (f"cnmp_metaworld_{t}", [
        ("stock", ["--env.type=cnmp_metaworld", f"--env.task={task}", "--eval.n_episodes=50", "--seed=100000"])])
       for t, task in (("reach", "reach-v3"), ("push", "push-v3"), ("pickplace", "pick-place-v3"))},
}


def run(cmd: list[str], log: Path) -> None:
    with log.open("w") as f:
        proc = subprocess.run(cmd, cwd=REPO, stdout=f, stderr=subprocess.STDOUT)
    if proc.returncode:
        raise RuntimeError(f"{' '.join(cmd)} failed (exit {proc.returncode}); its output: {log}")


def cell(name: str, out: Path) -> dict:
    config, evals = CELLS[name]
    raw = json.loads((REPO / "configs" / f"{config}.json").read_text())
    root = REPO / raw["dataset"]["root"]
    if not (root / "meta" / "info.json").is_file():
        raise FileNotFoundError(f"cell {name}: its dataset {root} is not on disk (cnmp_room: `bash run.sh room` "
                                "records it)")
    folder = out / name
    train = [str(BIN / "lerobot-train"), f"--config_path=configs/{config}.json", "--policy.device=cpu",
             f"--output_dir={folder / 'train'}"]
    subprocess.run(["rm", "-rf", str(folder)], check=True)
    folder.mkdir(parents=True)
    t0 = time.perf_counter()
    run(train, folder / "train.log")
    train_s = time.perf_counter() - t0
    ckpt = folder / "train" / "checkpoints" / "last" / "pretrained_model"
    result = {"cell": name, "config": f"configs/{config}.json", "train_command": " ".join(train[1:]),
              "train_s": round(train_s, 1), "steps": raw["steps"], "evals": {}}
    for label, opts in evals:
        cmd = [str(BIN / "lerobot-eval"), f"--policy.path={ckpt}", *opts, *EVAL, f"--output_dir={folder / label}"]
        run(cmd, folder / f"eval_{label}.log")
        info = json.loads((folder / label / "eval_info.json").read_text())
        agg = info.get("overall", info.get("aggregated", info))
        result["evals"][label] = {"pc_success": agg["pc_success"], "command": " ".join(cmd[1:])}
        print(f"{name:>20} {label:>14}: pc_success {agg['pc_success']:.1f}  (training {train_s:.0f} s)", flush=True)
    (out / f"{name}.json").write_text(json.dumps(result, indent=1))
    return result


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cells", nargs="+", choices=sorted(CELLS), default=sorted(set(CELLS) - {"room"}),
                    help="cells to run (default: all but room, whose 1000-room dataset is recorded by `bash run.sh room`)")
    ap.add_argument("--out", type=Path, default=REPO / "outputs" / "stock_eval")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True).stdout.strip()
    results = [cell(c, args.out) for c in args.cells]
    print(json.dumps({"bench": "stock_eval", "date": date.today().isoformat(), "commit": commit,
                      "omp_num_threads": os.environ.get("OMP_NUM_THREADS"), "cells": results}))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The whole benchmark suite in one run: accuracy (obstacle, sines, Table I), speed, time to error, memory.

    python -m bench.run [--out outputs/bench]

Runs each bench (``python -m bench.<name>``) in its own process, in sequence (one at a time, so timings do not
compete for the 2 cores), keeps each one's full output under ``--out`` and merges the JSON objects they
print last. Prints a table of the headline figures (markdown, ready for the README) and, as its last line,
one JSON object, whose ``checkpoints`` names, per script, the checkpoint its figures come from (path, step,
training command). About 8 min on 2 CPU cores with trained checkpoints; without them pass ``--train``
(11 min): a missing checkpoint is otherwise an error.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from datetime import date
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

SCRIPTS = [
    ("latency", []),
    ("sine_benchmark", []),
    ("obstacle_accuracy", ["--train?"]),
    ("train_speed", []),
    ("time_to_error", []),
    ("memory", []),
    ("table1", ["--train?"]),
]

HEADLINE = [
    # key, label, unit, bar
    ("obstacle_paper_collision_free_cnmp", "CNMP collision-free, paper's 3 conditions", "%", "100"),
    ("obstacle_paper_collision_free_promp", "ProMP collision-free, paper's 3 conditions", "%", ""),
    ("obstacle_collision_free_cnmp", "CNMP collision-free, all condition sets", "%", ""),
    ("obstacle_collision_free_promp", "ProMP collision-free, all condition sets", "%", ""),
    ("obstacle_collision_free_dmp", "DMP collision-free, start + goal sets", "%", ""),
    ("obstacle_random_off_demo_distance_cnmp", "CNMP off-demo distance, random sets", "", ""),
    ("obstacle_random_off_demo_distance_promp", "ProMP off-demo distance, random sets", "", ""),
    ("sine_error_cnmp", "Sine benchmark error, CNMP (published CNMP 0.112)", "", "≤ 0.05"),
    ("sine_error_promp", "Sine benchmark error, ProMP mean (published ProMP 0.181)", "", ""),
    ("sine_error_promp_sample", "Sine benchmark error, 1 ProMP sample", "", ""),
    ("control_step_p50_ms", "Control step p50, network alone (the policy's numpy executor, no processors)", "ms", "≤ 0.15"),
    ("trajectory_200_ms", "200-step trajectory with σ, p50, network alone (numpy executor)", "ms", "≤ 0.5"),
    ("control_step_torch_p50_ms", "Control step p50, network alone, torch model (1 thread)", "ms", ""),
    ("trajectory_200_torch_ms", "200-step trajectory with σ, network alone, torch model", "ms", ""),
    ("select_action_p50_ms", "Whole lerobot-eval step p50: preprocessor + select_action + postprocessor", "ms", "≤ 1"),
    ("train_steps_per_s_api", "Training steps/s, in-memory API", "1/s", ""),
    ("train_steps_per_s_lerobot", "Training steps/s, lerobot-train", "1/s", ""),
    ("train_step_ms_batch1_api", "Training step at batch 1, 1 draw (the paper's setting), API", "ms", ""),
    ("time_to_error_s_api", "Time to validation error ≤ 0.03, API", "s", ""),
    ("time_to_error_s_lerobot", "Time to validation error ≤ 0.03, lerobot-train", "s", ""),
    ("peak_rss_train_mb", "Peak RSS, lerobot-train", "MB", ""),
    ("peak_rss_train_api_mb", "Peak RSS, API training", "MB", ""),
    ("peak_rss_inference_mb", "Peak RSS, lerobot-eval", "MB", ""),
    ("peak_rss_inference_api_mb", "Peak RSS, API inference", "MB", ""),
    ("rss_imports_only_mb", "RSS of the imports alone (torch, LeRobot)", "MB", ""),
    ("interp_max_err_deg", "Pick and place: worst joint error, interpolation γ (paper 0.28)", "deg", "≤ 0.28"),
    ("extrap_7_9_max_err_deg", "Pick and place: worst joint error, γ = (7, 9) (paper 3.69)", "deg", "≤ 2"),
    ("interp_success_pct", "Pick and place: executed, random interpolation γ", "%", "100"),
]

REQUIRED = ("control_step_p50_ms", "trajectory_200_ms", "sine_error_cnmp", "sine_error_promp",
            "obstacle_collision_free_cnmp", "obstacle_collision_free_promp", "train_steps_per_s_api",
            "train_steps_per_s_lerobot", "peak_rss_train_mb")


def run_script(name: str, args: list[str], out: Path) -> tuple[dict, float]:
    t0 = time.perf_counter()
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    proc = subprocess.run([sys.executable, "-m", f"bench.{name}", *args], capture_output=True, text=True, cwd=REPO,
                          env=env)
    seconds = time.perf_counter() - t0
    (out / f"{name}.log").write_text(proc.stdout + "\n--- stderr ---\n" + proc.stderr)
    if proc.returncode != 0:
        raise RuntimeError(f"python -m bench.{name} failed (exit {proc.returncode}); see {out / (name + '.log')}:\n"
                           f"{proc.stderr[-2000:]}")
    lines = [line for line in proc.stdout.splitlines() if line.strip()]
    return json.loads(lines[-1]), seconds


def main() -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", default=str(REPO / "outputs" / "bench"))
    p.add_argument("--train", action="store_true",
                   help="let the scripts that need a trained checkpoint fit one with the API when it is missing "
                        "(without it a missing checkpoint stops the suite)")
    args = p.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results: dict = {}
    seconds: dict = {}
    checkpoints: dict = {}
    start = time.perf_counter()
    for name, extra in SCRIPTS:
        print(f"== python -m bench.{name}", flush=True)
        extra = [a.rstrip("?") for a in extra if not a.endswith("?") or args.train]
        figures, seconds[name] = run_script(name, extra, out)
        checkpoints[name] = figures.pop("checkpoint", None)
        print(f"   done in {seconds[name]:.0f} s", flush=True)
        results.update(figures)
    missing = [k for k in REQUIRED if k not in results]
    if missing:
        raise RuntimeError(f"the suite did not produce {missing}")
    import torch

    machine = f"{platform.machine()}, {os.cpu_count()} CPU cores, no GPU used, torch {torch.__version__}"
    results.update({"date": date.today().isoformat(), "machine": machine,
                    "suite_minutes": round((time.perf_counter() - start) / 60, 1),
                    "script_seconds": {k: round(v, 1) for k, v in seconds.items()},
                    "checkpoints": checkpoints})
    (out / "results.json").write_text(json.dumps(results, indent=2))
    print(f"\nFigures of {results['date']} on {machine}; suite took {results['suite_minutes']} min.\n")
    print("| figure | value | bar |\n|---|---:|---|")
    for key, label, unit, bar in HEADLINE:
        value = results.get(key)
        shown = "n/a" if value is None else f"{value:g}{(' ' + unit) if unit else ''}"
        print(f"| {label} | {shown} | {bar} |")
    print(json.dumps(results))
    return results


if __name__ == "__main__":
    main()

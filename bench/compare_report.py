"""The comparison's report, read from the seed records: per cell the best success (the best checkpoint's
held-out evaluation, mean and min-max over training seeds), the training time to reach 90 % of the curve's best,
and the curve; one plot per task (success vs training-loop seconds, log x, a line per method) and one of best
success vs demos.

Definitions (per training seed, then mean / min / max over the cell's seeds):

- curve: (training-loop seconds, pc_success on CURVE_EPISODES episodes from CURVE_SEED) of each kept checkpoint;
- best: pc_success of the curve's best checkpoint (highest, earliest on a tie) on the held-out 50 episodes from
  SEED: the checkpoint is chosen on other seeds than the ones that score it, so the figure is not the max of
  noisy draws;
- time to 90 %: loop seconds of the first curve point at >= 90 % of the curve's own maximum (None when the
  curve never leaves 0);
- the 2-minute point: the curve's value at its checkpoint nearest 120 s of measured training loop, if one lies
  within 80-180 s (a mark's nominal time is what the probe predicted; the measured time is what happened).
"""

from __future__ import annotations

import json
import statistics
from pathlib import Path

from bench.compare_cells import CURVE_EPISODES, CURVE_SEED, HELDOUT_EPISODES, METHODS, PROMP_LABEL, PROMP_NOTE, SEED, TASKS


def load_records(out: Path) -> list[dict]:
    """Every seed record under ``out`` (``<task>/<method>_<N>demos/seed<S>.json``), ok, running or error."""
    recs = []
    for f in sorted(Path(out).glob("*/*_*demos/seed*.json")):
        rec = json.loads(f.read_text())
        rec["_file"] = str(f)
        recs.append(rec)
    return recs


def seed_summary(rec: dict) -> dict:
    """One seed's best (held-out), curve maximum, time to 90 % of it and 2-minute point."""
    pts = sorted((p for p in rec.get("points", []) if p.get("loop_s") is not None), key=lambda p: p["step"])
    top = max((p["pc_success"] for p in pts), default=None)
    t90 = next((p["loop_s"] for p in pts if top and p["pc_success"] >= 0.9 * top), None)
    near = min(pts, key=lambda p: abs(p["loop_s"] - 120), default=None)
    at_2min = near["pc_success"] if near and 80 <= near["loop_s"] <= 180 else None
    loop, cap = rec.get("train", {}).get("loop_s"), rec.get("schedule", {}).get("cap_s")
    return {"seed": rec["seed"], "loop_s": loop, "cap_s": cap, "best": rec.get("heldout", {}).get("pc_success"), "best_step": rec.get("heldout", {}).get("step"),
            "best_loop_s": rec.get("heldout", {}).get("loop_s"), "curve_max": top, "t90_s": t90, "at_2min": at_2min,
            "curve": [[p["loop_s"], p["pc_success"]] for p in pts]}


def spread(values: list) -> dict | None:
    """Mean, min and max of the values that are not None (None when there are none)."""
    vals = [v for v in values if v is not None]
    if not vals:
        return None
    return {"mean": statistics.fmean(vals), "min": min(vals), "max": max(vals), "n": len(vals)}


def mean_curve(seeds: list[dict]) -> list[list[float]]:
    """The seeds' curves averaged point by point (the i-th kept checkpoint of each: the same mark), over the
    seeds that reached it: [mean loop s, mean pc_success, min, max]."""
    out = []
    for i in range(max((len(s["curve"]) for s in seeds), default=0)):
        col = [s["curve"][i] for s in seeds if len(s["curve"]) > i]
        ys = [y for _, y in col]
        out.append([statistics.fmean(x for x, _ in col), statistics.fmean(ys), min(ys), max(ys)])
    return out


def cell_summaries(recs: list[dict]) -> list[dict]:
    """One summary per (task, method, N) over its finished seeds (seed records with status ok)."""
    cells: dict[tuple, list[dict]] = {}
    for r in recs:
        cells.setdefault((r["task"], r["method"], r["n_demos"]), []).append(r)
    order, morder = {t: i for i, t in enumerate(TASKS)}, {m: i for i, m in enumerate(METHODS)}
    out = []
    for (task, method, n), rs in sorted(cells.items(), key=lambda kv: (order.get(kv[0][0], 99), kv[0][0], kv[0][2],
                                                                       morder.get(kv[0][1], 99))):
        ok = [seed_summary(r) for r in sorted(rs, key=lambda r: r["seed"]) if r.get("status") == "ok"]
        out.append({"task": task, "method": method, "n_demos": n, "n_seeds": len(ok),
                    "seeds": [s["seed"] for s in ok], "not_finished": sorted(r["seed"] for r in rs if r.get("status") != "ok"),
                    "errors": [str(r.get("error", "")).splitlines()[0][:120] for r in rs if r.get("status") == "error"],
                    "best": spread([s["best"] for s in ok]), "t90_s": spread([s["t90_s"] for s in ok]),
                    "at_2min": spread([s["at_2min"] for s in ok]), "loop_s": spread([s["loop_s"] for s in ok]),
                    "cap_s": max((s["cap_s"] or 0 for s in ok), default=None) or None,
                    "per_seed": ok, "mean_curve": mean_curve(ok)})
    return out


def _ms(s: dict | None, nd: int = 0) -> str:
    if s is None:
        return "–"
    if s["n"] == 1 or s["min"] == s["max"]:
        return f"{s['mean']:.{nd}f}"
    return f"{s['mean']:.{nd}f} [{s['min']:.{nd}f}–{s['max']:.{nd}f}]"


def summary_table(cells: list[dict]) -> str:
    """A row per task and demos, a column per method: best success mean [min–max] (seeds), time to 90 %."""
    methods = [m for m in METHODS if any(c["method"] == m for c in cells)]
    by = {(c["task"], c["n_demos"], c["method"]): c for c in cells}
    keys = list(dict.fromkeys((c["task"], c["n_demos"]) for c in cells))
    lines = ["| task | demos | " + " | ".join(m + (" (open loop)" if m == "promp" else "") for m in methods) + " |",
             "|---|---:|" + "---:|" * len(methods)]
    for task, n in keys:
        vals = []
        for m in methods:
            c = by.get((task, n, m))
            if c is None:
                vals.append("–")
            elif not c["n_seeds"]:
                vals.append("err" if c["errors"] else "running")
            else:
                vals.append(f"{_ms(c['best'])} ({c['n_seeds']} seed{'s' * (c['n_seeds'] > 1)}) · "
                            f"{_ms(c['t90_s'])} s")
        lines.append(f"| {task} | {n} | " + " | ".join(vals) + " |")
    return "\n".join(lines)


def cell_table(cells: list[dict]) -> str:
    """Every cell: seeds, best, time to 90 %, the 2-minute point, and what did not finish."""
    lines = ["| task | method | demos | seeds | best (held-out) | time to 90 % (s) | 2-min point | training loop "
             "(s) / cap | curve points | not finished |", "|---|---|---:|---|---:|---:|---:|---:|---:|---|"]
    for c in cells:
        cap = f" / {c['cap_s']}" if c.get("cap_s") else ""
        lines.append(f"| {c['task']} | {c['method']} | {c['n_demos']} | {','.join(map(str, c['seeds'])) or '–'} | "
                     f"{_ms(c['best'])} | {_ms(c['t90_s'])} | {_ms(c['at_2min'])} | {_ms(c.get('loop_s'))}{cap} | "
                     f"{len(c['mean_curve'])} | "
                     f"{', '.join(map(str, c['not_finished'])) or ''}"
                     f"{(': ' + c['errors'][0].replace('|', '/')) if c['errors'] else ''} |")
    return "\n".join(lines)


def plot_curves(cells: list[dict], task: str, path: Path) -> Path:
    """Success vs training-loop seconds (log x) of one task: a panel per number of demos, a line per method
    (mean over seeds, the band min–max)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    mine = [c for c in cells if c["task"] == task and c["mean_curve"]]
    ns = sorted({c["n_demos"] for c in mine})
    fig, axes = plt.subplots(1, max(1, len(ns)), figsize=(4.4 * max(1, len(ns)), 3.8), squeeze=False)
    color = {m: f"C{i}" for i, m in enumerate(METHODS)}
    for ax, n in zip(axes[0], ns, strict=False):
        for c in (c for c in mine if c["n_demos"] == n):
            x, y, lo, hi = zip(*c["mean_curve"], strict=True)
            x = [max(v, 0.5) for v in x]  # ProMP's fit can take under a second
            label = f"{c['method']} ({c['n_seeds']} seed{'s' * (c['n_seeds'] > 1)})"
            ax.plot(x, y, marker="o", color=color.get(c["method"]), label=label,
                    linestyle=":" if c["method"] == "promp" else "-")
            if c["n_seeds"] > 1:
                ax.fill_between(x, lo, hi, color=color.get(c["method"]), alpha=0.15)
        ax.set_xscale("log")
        ax.set_title(f"{task}, {n} demos", fontsize=10)
        ax.set_xlabel("training loop (s)")
        ax.set_ylim(-3, 103)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    axes[0][0].set_ylabel("pc_success (curve evaluation)")
    fig.tight_layout()
    from lerobot_cnmp.plot import save_figure

    return save_figure(fig, path, dpi=110)


def plot_demos(cells: list[dict], path: Path) -> Path:
    """Best success (held-out, mean over seeds, bars min–max) vs number of demos: a panel per task."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    done = [c for c in cells if c["best"]]
    tasks = list(dict.fromkeys(c["task"] for c in done))
    if not tasks:
        raise ValueError("no finished cell to plot")
    ncol = min(4, len(tasks))
    nrow = -(-len(tasks) // ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(4.4 * ncol, 3.6 * nrow), squeeze=False)
    for ax in list(axes.flat)[len(tasks):]:
        ax.set_visible(False)
    for ax, task in zip(axes.flat, tasks, strict=False):
        for i, m in enumerate(METHODS):
            pts = sorted((c["n_demos"], c["best"]) for c in done if c["task"] == task and c["method"] == m)
            if pts:
                xs = [n for n, _ in pts]
                ys = [b["mean"] for _, b in pts]
                err = [[b["mean"] - b["min"] for _, b in pts], [b["max"] - b["mean"] for _, b in pts]]
                ax.errorbar(xs, ys, yerr=err, marker="o", capsize=3, color=f"C{i}", label=m,
                            linestyle=":" if m == "promp" else "-")
        ax.set_title(task, fontsize=10)
        ax.set_xlabel("demonstrations")
        ax.set_ylim(-3, 103)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    for row in axes:
        row[0].set_ylabel("best pc_success (held-out)")
    fig.tight_layout()
    from lerobot_cnmp.plot import save_figure

    return save_figure(fig, path, dpi=110)


def report(out: Path, plot: Path) -> str:
    """Write ``out/report.md``, ``out/curves.json``, the plots (``plot`` and ``plot``'s folder /
    ``compare_curves_<task>.png``) and the markdown beside ``plot``; return the markdown."""
    recs = load_records(out)
    if not recs:
        raise SystemExit(f"no seed records under {out} (<task>/<method>_<N>demos/seed<S>.json)")
    cells = cell_summaries(recs)
    (Path(out) / "curves.json").write_text(json.dumps({"cells": cells}, indent=1))
    seeds = {m: sorted({c["n_seeds"] for c in cells if c["method"] == m and c["n_seeds"]}) for m in METHODS}
    seeds_line = "; ".join(f"{m}: {'/'.join(map(str, v))}" for m, v in seeds.items() if v)
    ok = [r for r in recs if r.get("status") == "ok"]
    held = "/".join(map(str, sorted({r["heldout"]["n_episodes"] for r in ok}))) or str(HELDOUT_EPISODES)
    curve = "/".join(map(str, sorted({p["n_episodes"] for r in ok for p in r["points"]}))) or str(CURVE_EPISODES)
    text = (f"# Policy comparison: learning curves\n\nBest success (pc_success of the best checkpoint on {held} "
            f"held-out episodes, --seed={SEED}), mean [min–max] over training seeds, and the training-loop seconds to "
            f"reach 90 % of the curve's best (curve: {curve} episodes per checkpoint, --seed={CURVE_SEED}). "
            f"Training seeds per cell: {seeds_line}."
            + (f" {PROMP_NOTE}." if seeds.get("promp") else "") + f"\n\n{summary_table(cells)}\n\nEvery cell:\n\n"
            f"{cell_table(cells)}\n\n"
            + (f"† promp: {PROMP_LABEL}\n\n" if seeds.get("promp") else "")
            + f"Curves (per seed and mean) in curves.json; each seed record's provenance (commit, command, date) "
            f"under {out}.\n")
    (Path(out) / "report.md").write_text(text)
    plot.parent.mkdir(parents=True, exist_ok=True)
    plot.with_suffix(".md").write_text(text)  # beside the plot, committed with it
    for task in dict.fromkeys(c["task"] for c in cells if c["mean_curve"]):
        plot_curves(cells, task, plot.parent / f"compare_curves_{task}.png")
    if any(c["best"] for c in cells):
        plot_demos(cells, plot)
    return text

"""Training cost of the mixture decoder (issue 17): time to the single-decoder CNMP's validation NLL on the
2D obstacle data.

    python -m bench.mixture_cost [--experts 4] [--gate_entropy_coef G] [--batch_entropy_coef B]
                                 [--shared_decoder_layers S] [--assignment_draws P] [--unconditional_nll_coef C]
                                 [--steps 3000] [--mixture_steps N] [--every 250] [--seed 0 | --seeds 0 1 2 3 4]

Both models (``n_experts`` = 1 and K) train the model, sampling and learning-rate schedule of
``configs/cnmp_obstacle2d.json`` on ``datasets/cnmp_obstacle2d`` with the in-memory API, same steps, batch
and seed (``--mixture_steps`` gives the mixture another number of steps, its cosine decay spread over them;
``--gate_entropy_coef`` / ``--batch_entropy_coef`` its entropy weights instead of the config's defaults). Every ``--every`` steps each is scored on validation tasks that are not in the dataset (fresh tasks
of the sim, both modes; as ``time_to_error.py``): given the start and one via point, the NLL of the task's
true 200-step path under the predicted density, per point, in the data's units: -log N(y | μ, σ) for K = 1,
-log Σ_k π_k N(y | μ_k, σ_k) for the mixture (the density its experts and gate predict). Reported: the
training time (scoring excluded) until each reaches the single decoder's final validation NLL, and their
ratio (bar: <= 2). ``--seeds 0 1 2 3 4`` trains both models once per seed and compares the curves averaged
over the seeds (at each scoring point: the mean training time and the mean validation NLL), the single
decoder's final mean NLL the target; each seed's own comparison is printed beside it. One training run's final
NLL moves by about 0.03 with the seed alone (the initialization and the draws: see docs/mixture.md),
as much as the mixture's whole margin, so one seed's verdict is noisy. Last line: one JSON object.
"""

from __future__ import annotations

import argparse
import itertools
import json
import time

import numpy as np

from bench.common import CONFIG, DATASET, add_mixture_arguments, api_model, config, mixture_report, mixture_settings
from bench.time_to_error import PHASES, first_below, validation_set


def validation_nll(model, val) -> float:
    """Mean over tasks and path points of -log Σ_k π_k Π_d N(y_d | μ_kd, σ_kd) (K = 1: Eq. 1)."""
    out = []
    for conds, path in val:
        means, stds, probs = model.predict_mixture(PHASES, conds)  # [K, M, D], [K, M, D], [K]
        log_n = (-0.5 * ((path[None] - means) / stds) ** 2 - np.log(stds) - 0.5 * np.log(2 * np.pi)).sum(-1)
        log_mix = np.log(np.maximum(probs, 1e-30))[:, None] + log_n  # [K, M]
        top = log_mix.max(0)
        out.append(-(top + np.log(np.exp(log_mix - top).sum(0))).mean())
    return float(np.mean(out))


def run(cfg: dict, steps: int, every: int, val, seed: int, **overrides) -> tuple[list[tuple[int, float, float]], object]:
    """(steps, training seconds, validation NLL) every ``every`` steps, and the fitted model's CNMPConfig."""
    import torch

    from lerobot_cnmp.data.demos import load_demos

    torch.manual_seed(seed)
    model = api_model(cfg)
    model.overrides.update(overrides)
    points, clock = [], {"train": 0.0, "since": time.perf_counter()}

    def callback(done, m):
        clock["train"] += time.perf_counter() - clock["since"]
        points.append((done, clock["train"], validation_nll(m, val)))
        clock["since"] = time.perf_counter()

    model.fit(load_demos(DATASET)["demos"], steps=steps, batch_size=cfg["batch_size"], seed=seed, progress=False,
              callback=callback, callback_every=every)
    return points, model.config


def main() -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--experts", type=int, default=4)
    add_mixture_arguments(p)
    p.add_argument("--steps", type=int, default=3000)
    p.add_argument("--mixture_steps", type=int, default=None,
                   help="the mixture's steps, its learning-rate decay spread over them (default: --steps)")
    p.add_argument("--every", type=int, default=250)
    p.add_argument("--validation", type=int, default=40, help="validation tasks")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--seeds", type=int, nargs="+", default=None,
                   help="train both models once per seed and compare their mean curves (default: --seed alone)")
    args = p.parse_args()

    cfg = config(CONFIG)
    val = validation_set(args.validation, 500000)
    coefs = mixture_settings(args)
    seeds = args.seeds or [args.seed]
    if len(set(seeds)) != len(seeds):
        raise SystemExit(f"--seeds must be distinct, got {seeds}")
    per_seed, mix_cfg = [], None
    for seed in seeds:
        curves = {"cnmp": run(cfg, args.steps, args.every, val, seed)[0]}
        curves["mixture"], mix_cfg = run(cfg, args.mixture_steps or args.steps, args.every, val, seed,
                                         n_experts=args.experts, mixture=coefs)
        per_seed.append(compare(curves))
        if len(seeds) > 1:
            print(f"seed {seed}: " + verdict(per_seed[-1], args.experts), flush=True)
    coefs.update(mixture_report(mix_cfg))  # the values it trained with
    curves = {k: mean_curve([c["curves"][k] for c in per_seed]) for k in ("cnmp", "mixture")}
    res: dict = {"experts": args.experts, **coefs, "steps": args.steps,
                 "mixture_steps": args.mixture_steps or args.steps, "seeds": seeds}
    mean = compare(curves)
    print(f"validation NLL per path point (fresh tasks, start + via point) every {args.every} steps"
          + (f", mean over seeds {seeds}" if len(seeds) > 1 else ""))
    print(f"{'steps':>6}" + "".join(f"{k + ' s':>12}{k + ' NLL':>14}" for k in curves))
    for row in itertools.zip_longest(*curves.values()):
        step = next(r[0] for r in row if r is not None)
        print(f"{step:>6}" + "".join(" " * 26 if r is None else f"{r[1]:>12.1f}{r[2]:>14.3f}" for r in row))
    res.update({k: v for k, v in mean.items() if k != "curves"})
    if len(seeds) > 1:
        res["per_seed"] = [{"seed": s, **{k: v for k, v in c.items() if k != "curves"}} for s, c in zip(seeds, per_seed)]
    print(("mean over the seeds: " if len(seeds) > 1 else "") + verdict(mean, args.experts))
    print(json.dumps(res))
    return res


def mean_curve(curves: list[list[tuple[int, float, float]]]) -> list[tuple[int, float, float]]:
    """(steps, mean training seconds, mean validation NLL) at each scoring point of runs of the same steps."""
    return [(pts[0][0], float(np.mean([p[1] for p in pts])), float(np.mean([p[2] for p in pts])))
            for pts in zip(*curves, strict=True)]


def compare(curves: dict) -> dict:
    """The time (and steps) each curve takes to the single decoder's final validation NLL, and their ratio."""
    target = curves["cnmp"][-1][2]
    res: dict = {"target_validation_nll": round(target, 3)}
    for k, pts in curves.items():
        steps, seconds = first_below(pts, target)
        res[f"time_to_target_s_{k}"] = None if seconds is None else round(seconds, 1)
        res[f"steps_to_target_{k}"] = steps
        res[f"final_validation_nll_{k}"] = round(pts[-1][2], 3)
        res[f"total_train_s_{k}"] = round(pts[-1][1], 1)
    if res["time_to_target_s_mixture"] is not None:
        res["time_ratio_mixture_vs_cnmp"] = round(res["time_to_target_s_mixture"] / res["time_to_target_s_cnmp"], 2)
    return {**res, "curves": curves}


def verdict(res: dict, experts: int) -> str:
    return (f"the single decoder's final validation NLL {res['target_validation_nll']:.3f}: CNMP after "
            f"{res['time_to_target_s_cnmp']} s, the mixture (K={experts}) after {res['time_to_target_s_mixture']} s "
            f"at {res['steps_to_target_mixture']} steps (ratio {res.get('time_ratio_mixture_vs_cnmp', 'not reached')})")


if __name__ == "__main__":
    main()

"""The weight switch as a change of mode: a mixture CNMP's gate on ``cnmp_weights`` before the grasp and
after the lift (issue 17).

    python -m bench.mixture_weights [--experts 4] [--gate_entropy_coef C] [--batch_entropy_coef B]
                                    [--shared_decoder_layers S] [--assignment_draws P]
                                    [--steps N] [--save DIR]

Fits the config's CNMP (``configs/cnmp_weights.json``: model, sampling, learning rate, steps, batch size)
with ``n_experts`` decoders on the 20 demos of ``datasets/cnmp_weights`` with the in-memory API. Then, for
each container shape x unseen mass (``TEST_MASSES`` plus a grid between the demos' masses; the mass is never
an input, only what the F/T sensor reads after the lift), the scripted expert runs one episode and the
mixture is conditioned as in ``weights_report.py``: on the start state only (before the grasp: all four zones
are possible), then also on the sensed SM right after the lift. Reported: the gate's probabilities before
the grasp (bar: four experts near 1/4 each), the share of masses where one expert has π > 0.9 after the
lift (bar: >= 95 %), and whether that expert's predicted end lies in the true zone; ``bars_met`` says
whether both bars hold ("near 1/4": max |π - 1/K| <= 0.1 over experts and masses). Last line: one JSON.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from bench.common import REPO, add_mixture_arguments, api_model, config, mixture_report, mixture_settings
from bench.weights_report import start_and_lift

CONFIG = REPO / "configs" / "cnmp_weights.json"
NEAR_UNIFORM = 0.1  # "near 1/4" before the grasp: every expert's π within 0.1 of 1/K on every mass


def unseen_masses() -> list[float]:
    """TEST_MASSES and 6 more masses per weight category, none of them a demo's mass."""
    from lerobot_cnmp.sims.weights.task import TEST_MASSES

    grid = {"light": np.linspace(0.16, 0.34, 6), "heavy": np.linspace(0.66, 0.94, 6)}
    out = sorted({round(float(m), 4) for cat in TEST_MASSES for m in (*TEST_MASSES[cat], *grid[cat])})
    demo = {round(0.15 + 0.05 * i, 4) for i in range(5)} | {round(0.65 + 0.075 * i, 4) for i in range(5)}
    return [m for m in out if m not in demo]


def main() -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--experts", type=int, default=4)
    add_mixture_arguments(p)
    p.add_argument("--steps", type=int, default=None, help="training steps (default: the config's)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--save", default=None, help="write the fitted checkpoint here")
    args = p.parse_args()

    import torch

    from lerobot_cnmp.data.demos import load_demos
    from lerobot_cnmp.sims.weights.env import WeightsEnv
    from lerobot_cnmp.sims.weights.task import HEAVY_THRESHOLD, SHAPES, ZONE_XY

    torch.manual_seed(args.seed)
    cfg = config(CONFIG)
    data = load_demos(REPO / cfg["dataset"]["root"])
    model = api_model(cfg)
    model.overrides.update(n_experts=args.experts, mixture=mixture_settings(args))
    t0 = time.perf_counter()
    model.fit(data["demos"], task_params=data["task_params"], steps=args.steps or cfg["steps"],
              batch_size=cfg["batch_size"], seed=args.seed, progress=False)
    fit_s = time.perf_counter() - t0
    if args.save:
        model.save(args.save)

    env = WeightsEnv(render_mode=None, terminate_on_success=False)
    rows = []
    for shape in range(len(SHAPES)):
        for mass in unseen_masses():
            start, lifted = start_and_lift(env, shape, mass)
            means_before, _, before = model.predict_mixture([1.0], [start])
            zones_before = [int(np.argmin(np.linalg.norm(ZONE_XY - m[0, :2], axis=1))) for m in means_before]
            means, _, after = model.predict_mixture([1.0], [start, lifted])
            k = int(after.argmax())
            zone = int(np.argmin(np.linalg.norm(ZONE_XY - means[k, 0, :2], axis=1)))
            truth = 2 * shape + int(mass > HEAVY_THRESHOLD)
            rows.append({"shape": SHAPES[shape][0], "mass": mass, "truth": truth, "zone": zone, "expert": k,
                         "before": before, "zones_before": zones_before, "after": after})

    print(f"{'shape':<10}{'mass kg':>9}{'zone':>6}{'pred':>6}  {'π before the grasp':<28}{'π after the lift'}")
    fmt = lambda v: "[" + " ".join(f"{x:.2f}" for x in v) + "]"  # noqa: E731
    for r in rows:
        print(f"{r['shape']:<10}{r['mass']:>9.4f}{r['truth']:>6}{r['zone']:>6}  {fmt(r['before']):<28}{fmt(r['after'])}")
    before = np.stack([r["before"] for r in rows])
    after_max = np.array([r["after"].max() for r in rows])
    # which expert each true zone is given to after the lift
    zone_expert = {z: sorted({r["expert"] for r in rows if r["truth"] == z}) for z in range(4)}
    res = {
        "mixture_experts": args.experts, **mixture_report(model.config),
        "fit_s": round(fit_s, 1),
        "steps": args.steps or cfg["steps"], "episodes": len(rows),
        "gate_before_grasp_mean": [round(float(v), 3) for v in before.mean(0)],
        "gate_before_grasp_max_abs_dev_from_uniform": round(float(np.abs(before - 1 / args.experts).max()), 3),
        "after_lift_max_gate_above_0.9_pct": round(100.0 * float((after_max > 0.9).mean()), 1),
        "after_lift_max_gate_min": round(float(after_max.min()), 3),
        "expert_zones_before_grasp": sorted({tuple(r["zones_before"]) for r in rows}),
        "committed_expert_zone_accuracy_pct": round(100.0 * np.mean([r["zone"] == r["truth"] for r in rows]), 1),
        "experts_per_zone": zone_expert,
    }
    res["bars_met"] = {"before_grasp_near_uniform": res["gate_before_grasp_max_abs_dev_from_uniform"] <= NEAR_UNIFORM,
                       "after_lift_committed": res["after_lift_max_gate_above_0.9_pct"] >= 95.0}
    print(f"before the grasp: mean π {res['gate_before_grasp_mean']} (max |π - 1/K| "
          f"{res['gate_before_grasp_max_abs_dev_from_uniform']}); after the lift: max π > 0.9 on "
          f"{res['after_lift_max_gate_above_0.9_pct']} % of {len(rows)} unseen masses (min {res['after_lift_max_gate_min']}); "
          f"the committed expert ends in the true zone on {res['committed_expert_zone_accuracy_pct']} %; "
          f"experts per zone {zone_expert}; zone of each expert's end before the grasp "
          f"{res['expert_zones_before_grasp']}; fit {fit_s:.0f} s; bars met: {res['bars_met']}")
    print(json.dumps(res))
    return res


if __name__ == "__main__":
    main()

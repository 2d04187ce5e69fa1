"""Latency of one control step (condition on the goals + the current state, predict the next SM target).

    python bench/latency.py [--calls 2000]

Two figures, p50 over ``--calls`` calls on CPU, same policy and observation stream:
- ``control_step_p50_ms``: in-process, the pure-torch CNMP (encode + aggregate + decode) on a ready context;
- ``select_action_p50_ms``: what ``lerobot-eval`` runs per step: preprocessor (normalize, batch, device) ->
  ``CNMPPolicy.select_action`` -> postprocessor (unnormalize).
Latency does not depend on the weights, so the policy is built from the dataset without training.
Last line: one JSON object.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]


def p50_ms(fn, calls: int, warmup: int = 50) -> float:
    for _ in range(warmup):
        fn()
    times = np.empty(calls)
    for i in range(calls):
        t0 = time.perf_counter()
        fn()
        times[i] = time.perf_counter() - t0
    return float(np.median(times) * 1e3)


def main() -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--calls", type=int, default=2000)
    p.add_argument("--dataset", default=str(REPO / "datasets" / "cnmp_obstacle2d"))
    args = p.parse_args()
    torch.set_num_threads(1)

    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata
    from lerobot.policies.factory import make_policy
    from lerobot.utils.constants import OBS_ENV_STATE, OBS_STATE

    from lerobot_cnmp.conditions import Condition, encode_conditions
    from lerobot_cnmp.configuration_cnmp import CNMPConfig
    from lerobot_cnmp.processor_cnmp import make_cnmp_pre_post_processors

    meta = LeRobotDatasetMetadata("lerobot-cnmp/cnmp_obstacle2d", root=args.dataset)
    cfg = CNMPConfig(device="cpu")
    policy = make_policy(cfg, ds_meta=meta).eval()
    pre, post = make_cnmp_pre_post_processors(cfg, meta.stats)

    env_state = encode_conditions([Condition(0.5, (0.5, 0.4)), Condition(1.0, (1.0, 0.13))], 2, 4)
    obs = {OBS_STATE: torch.tensor([[0.1, 0.13]]), OBS_ENV_STATE: torch.from_numpy(env_state)[None]}

    # In-process: the context the policy builds each step, then the network alone.
    policy.reset()
    ctx = policy.execution_context(pre(dict(obs)), torch.full((1,), 0.3))
    query = torch.full((1, 1), 0.3)

    def control_step():
        with torch.inference_mode():
            policy.model(ctx, query)

    def select_action():
        with torch.inference_mode():
            post(policy.select_action(pre(dict(obs))))

    policy.reset()
    res = {
        "control_step_p50_ms": round(p50_ms(control_step, args.calls), 4),
        "select_action_p50_ms": round(p50_ms(select_action, args.calls), 4),
        "calls": args.calls,
        "context_points": int(ctx.valid.sum()),
        "torch_threads": torch.get_num_threads(),
        "machine": f"{platform.processor() or platform.machine()}, {torch.get_num_threads()} torch thread(s), CPU",
    }
    print(f"{'figure':<24}{'p50 (ms)':>10}")
    print(f"{'control step (torch)':<24}{res['control_step_p50_ms']:>10.4f}")
    print(f"{'select_action + procs':<24}{res['select_action_p50_ms']:>10.4f}")
    print(json.dumps(res))
    return res


if __name__ == "__main__":
    main()

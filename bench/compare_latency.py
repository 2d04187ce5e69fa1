"""``select_action`` latency of a trained checkpoint with its processors, on the task's env (LeRobot's rollout order)."""

from __future__ import annotations

import time
from pathlib import Path

from bench.compare_cells import RENAME_ENV_STATE, SEED, TASKS, env_config


def measure_latency(task: str, method: str, ckpt: Path, n_calls: int = 600) -> dict:
    """p50 / p95 / max (ms) of ``select_action`` alone and of preprocessor + select_action + postprocessor on
    one env of the task, LeRobot's rollout order, episodes seeded from ``SEED``, ``n_calls`` steps."""
    import numpy as np
    import torch
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.envs.factory import make_env, make_env_pre_post_processors
    from lerobot.envs.utils import preprocess_observation
    from lerobot.policies.factory import make_policy, make_pre_post_processors

    torch.set_num_threads(1)
    env_cfg = env_config(task)
    cfg = PreTrainedConfig.from_pretrained(ckpt)
    cfg.pretrained_path = Path(ckpt)
    cfg.device = "cpu"
    rename = RENAME_ENV_STATE if method in TASKS[task].get("env_state_copy", ()) else {}
    policy = make_policy(cfg=cfg, env_cfg=env_cfg, rename_map=rename)
    policy.eval()
    pre, post = make_pre_post_processors(policy_cfg=cfg, pretrained_path=ckpt, preprocessor_overrides={
        "device_processor": {"device": "cpu"}, "rename_observations_processor": {"rename_map": rename}})
    env_pre, env_post = make_env_pre_post_processors(env_cfg=env_cfg, policy_cfg=cfg)
    env = next(iter(make_env(env_cfg, n_envs=1, use_async_envs=False)[env_cfg.type].values()))
    sel, whole = [], []
    seed = SEED
    try:
        obs, _ = env.reset(seed=[seed])
        policy.reset()
        while len(sel) < n_calls:
            t0 = time.perf_counter()
            batch = preprocess_observation(obs)
            batch["task"] = [""]
            batch = pre(env_pre(batch))
            t1 = time.perf_counter()
            with torch.inference_mode():
                action = policy.select_action(batch)
            t2 = time.perf_counter()
            action = env_post({"action": post(action)})["action"]
            t3 = time.perf_counter()
            sel.append(t2 - t1)
            whole.append(t3 - t0)
            obs, _, term, trunc, _ = env.step(action.to("cpu").numpy())
            if term[0] or trunc[0]:
                seed += 1
                obs, _ = env.reset(seed=[seed])
                policy.reset()
    finally:
        env.close()

    def q(x, p):
        return round(float(np.percentile(np.asarray(x) * 1e3, p)), 4)

    return {"select_action_p50_ms": q(sel, 50), "select_action_p95_ms": q(sel, 95),
            "select_action_max_ms": round(max(sel) * 1e3, 4), "step_with_processors_p50_ms": q(whole, 50),
            "latency_calls": n_calls, "latency_episode_seeds": list(range(SEED, seed + 1))}



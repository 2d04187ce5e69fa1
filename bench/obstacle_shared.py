"""Overlapping modes, executed: CNMP vs ProMP on the obstacle sim's ``shared`` family (paper Sec. IV-A setting).

    python -m bench.obstacle_shared [--checkpoint CKPT | --train] [--episodes 50] [--seed 900000]

In ``--env.family=shared`` both avoidance modes start at (0, y0) and end at (1, y0) with the same y0: a
start and a goal do not name the mode, and the average of the two modes runs through the obstacle. Both
methods are trained on the same demos (``datasets/cnmp_obstacle2d_shared``, 64 demos, modes balanced) and
run in the sim on the same episodes (reset seeds ``--seed`` + i), for each condition choice:

- ``start_goal_early``: start, goal and an early point (phase 0.15-0.3) of the episode's reference, which
  names the mode;
- ``random``: one of the sim's random condition sets (via / early / end / via+end / via-y; ``end`` alone does
  not name the mode in this family);
- ``start_goal``: start and goal only; no information about the mode at all.

CNMP runs as ``lerobot-eval`` runs it (``select_action`` with the config's online feedback, PD and phase
stop). ProMP (``movement_primitives``, 31 RBFs per dim) is conditioned on the episode's conditions and its
mean is commanded open loop on the demos' schedule (step k -> phase k/199, then the goal). Reported per
choice, over the executed runs: collision-free % (no contact with the obstacle during the 300 steps) and
success % (the env's rule: goal, conditions, no contact), the collision-free % of each method's
predicted mean (the plan before execution), and the share of executed runs that pass over / under the
obstacle (which mode was chosen). A mixture checkpoint (``--policy.n_experts=K``) runs with its own
``expert_selection``: ``sample`` draws the mode from the gate at the first step. Last line: one JSON object (``checkpoint`` names the CNMP's).
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from bench.common import (REPO, add_checkpoint_args, add_episode_args, load_checkpoint_policy, parse_episode_args,
                          policy_batch, predict_sm, provenance)

CONFIG = REPO / "configs" / "cnmp_obstacle2d_shared.json"
DATASET = REPO / "datasets" / "cnmp_obstacle2d_shared"
CHECKPOINT = REPO / "outputs" / "shared" / "train" / "checkpoints" / "last" / "pretrained_model"
CHOICES = ("start_goal_early", "random", "start_goal")
STEPS = 300
DEMO_STEPS = 200


def clear_of_obstacle(path: np.ndarray) -> bool:
    from lerobot_cnmp.sims.obstacle2d.model import AGENT_RADIUS, OBSTACLE_CENTER, OBSTACLE_RADIUS

    return bool((np.linalg.norm(path - OBSTACLE_CENTER, axis=1) - OBSTACLE_RADIUS - AGENT_RADIUS).min() > 0)


def mode_of(path: np.ndarray) -> str:
    """``"over"`` or ``"under"``: the side of the obstacle the path passes, read where it crosses the obstacle's
    x (the point of the path nearest to that x)."""
    from lerobot_cnmp.sims.obstacle2d.model import OBSTACLE_CENTER

    k = int(np.argmin(np.abs(path[:, 0] - OBSTACLE_CENTER[0])))
    return "over" if path[k, 1] > OBSTACLE_CENTER[1] else "under"


def run_cnmp(policy, pre, post, env, seed: int) -> dict:
    import torch

    obs, _ = env.reset(seed=seed)
    policy.reset()
    plan, success, path = None, False, [obs["agent_pos"].copy()]
    for _ in range(STEPS):
        batch = policy_batch(pre, obs)
        with torch.no_grad():
            action = policy.select_action(batch)
        if plan is None:
            plan = predict_sm(policy, pre, post, batch, 0.0, np.linspace(0.0, 1.0, DEMO_STEPS))[0]
        obs, _, _, _, info = env.step(post(action)[0].numpy())
        path.append(obs["agent_pos"].copy())
        success |= bool(info["is_success"])
    return {"success": success, "contact": bool(info["contact"]), "plan_clear": clear_of_obstacle(plan),
            "mode": mode_of(np.array(path))}


def run_promp(promp, env, seed: int) -> dict:
    obs, _ = env.reset(seed=seed)
    mean, _ = promp.predict(np.linspace(0.0, 1.0, DEMO_STEPS), list(env.unwrapped.conditions))
    success, path = False, [obs["agent_pos"].copy()]
    for k in range(STEPS):
        obs, _, _, _, info = env.step(mean[min(k, DEMO_STEPS - 1)])
        path.append(obs["agent_pos"].copy())
        success |= bool(info["is_success"])
    return {"success": success, "contact": bool(info["contact"]), "plan_clear": clear_of_obstacle(mean),
            "mode": mode_of(np.array(path))}


def main() -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_checkpoint_args(p, CHECKPOINT, "a CNMP checkpoint trained on datasets/cnmp_obstacle2d_shared")
    add_episode_args(p, seed=900000)
    args = parse_episode_args(p)

    from lerobot_cnmp.promp.baselines import ProMPBaseline
    from lerobot_cnmp.data.demos import load_demos
    from lerobot_cnmp.sims.obstacle2d.env import Obstacle2DEnv

    ckpt, policy, pre, post = load_checkpoint_policy(args, "cnmp_obstacle2d_shared", CONFIG)
    promp = ProMPBaseline().fit(load_demos(DATASET)["demos"])
    res: dict = {"checkpoint": provenance(ckpt), "episodes": args.episodes, "seed": args.seed}
    res["cnmp_n_experts"] = policy.config.n_experts
    res["cnmp_expert_selection"] = policy.config.mixture.expert_selection
    print(f"{'conditions':<18}{'method':<7}{'exec. collision-free %':>24}{'exec. success %':>17}{'plan collision-free %':>23}"
          f"{'exec. over / under %':>22}")
    for choice in CHOICES:
        env = Obstacle2DEnv(conditions=choice, family="shared", render_mode=None, terminate_on_success=False)
        for name, run in (("cnmp", lambda s: run_cnmp(policy, pre, post, env, s)), ("promp", lambda s: run_promp(promp, env, s))):
            runs = [run(args.seed + i) for i in range(args.episodes)]
            free = 100.0 * np.mean([not r["contact"] for r in runs])
            succ = 100.0 * np.mean([r["success"] for r in runs])
            plan = 100.0 * np.mean([r["plan_clear"] for r in runs])
            res[f"shared_{choice}_collision_free_{name}"] = round(free, 1)
            res[f"shared_{choice}_success_{name}"] = round(succ, 1)
            res[f"shared_{choice}_plan_collision_free_{name}"] = round(plan, 1)
            over = 100.0 * np.mean([r["mode"] == "over" for r in runs])
            res[f"shared_{choice}_mode_over_{name}"] = round(over, 1)
            print(f"{choice:<18}{name:<7}{free:>24.1f}{succ:>17.1f}{plan:>23.1f}{f'{over:.0f} / {100 - over:.0f}':>22}")
        env.close()
    print(json.dumps(res))
    return res


if __name__ == "__main__":
    main()

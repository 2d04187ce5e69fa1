"""The weight switch in closed loop, counted: open loop vs online feedback on ``cnmp_weights`` over seed sets.

    python -m bench.weights_switch [--checkpoint CKPT | --train] [--episodes 20] [--seeds 1000 100000 ...]

Each seed set is ``--episodes`` episodes of ``--env.type=cnmp_weights --env.perturbation=weight_switch`` run
by LeRobot's ``rollout`` as ``lerobot-eval`` runs them (batches of ``--batch`` envs, reset seeds ``seed`` + i;
1000 is ``lerobot-eval``'s default seed). A light container gets 0.5 kg at a step drawn in the transport
window, but only while it is carried: an arm already descending (or one that dropped it) gets no switch, and
then the episode tests nothing about the switch. So per seed set and execution the bench reports the
episodes in which the switch actually happened (``info["weight_switched"]`` at the episode's end), the
success rate on those (the container must end on the heavy zone) and on all episodes, and over the seed
sets the mean, min and max of the success on switched episodes. Online feedback is the config's execution;
open loop replays the trajectory predicted at the first step (``online_feedback=false``), which cannot
react to the switch. Last line: one JSON object (``checkpoint`` names the checkpoint).
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from bench.common import REPO, add_checkpoint_args, checkpoint_from_args, make_sim, provenance

CONFIG = REPO / "configs" / "cnmp_weights.json"
CHECKPOINT = REPO / "outputs" / "weights" / "train" / "checkpoints" / "last" / "pretrained_model"
SEEDS = (1000, 100000, 200000, 300000, 400000)


def run_set(policy, pre, post, feedback: bool, episodes: int, batch: int, seed: int) -> list[dict]:
    """Per episode: did the switch happen, success (any step, as lerobot-eval counts it)."""
    from lerobot.scripts.lerobot_eval import rollout

    from lerobot_cnmp.sims.weights.config import CNMPWeightsEnv

    policy.config.execution.online_feedback = feedback
    env, env_pre, env_post = make_sim(CNMPWeightsEnv(perturbation="weight_switch", render_mode=None), policy, batch)
    out = []
    try:
        for start in range(0, episodes, batch):
            trace = []  # after each step: every sub-env's weight_switched (read before any autoreset)
            data = rollout(env, policy, env_pre, env_post, pre, post, seeds=list(range(seed + start, seed + start + batch)),
                           render_callback=lambda e: trace.append(list(e.call("weight_switched"))))
            done = data["done"]
            for b in range(batch):
                last = int(done[b].float().argmax()) if bool(done[b].any()) else done.shape[1] - 1
                out.append({"switched": bool(trace[last][b]), "success": bool(data["success"][b, : last + 1].any())})
    finally:
        env.close()
    return out[:episodes]


def main() -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_checkpoint_args(p, CHECKPOINT, "a CNMP checkpoint trained on cnmp_weights")
    p.add_argument("--episodes", type=int, default=20, help="episodes per seed set")
    p.add_argument("--batch", type=int, default=10)
    p.add_argument("--seeds", type=int, nargs="+", default=list(SEEDS), help="first reset seed of each set")
    args = p.parse_args()
    if args.episodes < 1 or args.batch < 1:
        p.error("--episodes and --batch must be >= 1")
    from lerobot_cnmp.api import load_pretrained

    ckpt = checkpoint_from_args(args, "cnmp_weights", config_path=CONFIG)
    policy, pre, post = load_pretrained(ckpt)
    res: dict = {"checkpoint": provenance(ckpt), "episodes_per_set": args.episodes, "seeds": args.seeds}
    print(f"{'execution':<11}{'seed':>8}{'switched':>10}{'success on switched %':>23}{'success all %':>15}")
    for fb in (True, False):
        mode = "feedback" if fb else "open_loop"
        rates = []
        for seed in args.seeds:
            runs = run_set(policy, pre, post, fb, args.episodes, args.batch, seed)
            sw = [r for r in runs if r["switched"]]
            on_sw = 100.0 * np.mean([r["success"] for r in sw]) if sw else None
            all_ = 100.0 * np.mean([r["success"] for r in runs])
            res[f"{mode}/{seed}"] = {"switched": len(sw), "episodes": len(runs),
                                     "success_on_switched_pct": None if on_sw is None else round(on_sw, 1),
                                     "success_all_pct": round(all_, 1)}
            if on_sw is not None:
                rates.append(on_sw)
            shown = "n/a" if on_sw is None else f"{on_sw:.1f}"
            print(f"{mode:<11}{seed:>8}{len(sw):>6} / {len(runs):<3}{shown:>21}{all_:>15.1f}", flush=True)
        res[f"{mode}_success_on_switched_mean_pct"] = round(float(np.mean(rates)), 1) if rates else None
        res[f"{mode}_success_on_switched_min_pct"] = round(float(np.min(rates)), 1) if rates else None
        res[f"{mode}_success_on_switched_max_pct"] = round(float(np.max(rates)), 1) if rates else None
        res[f"{mode}_switched_episodes"] = sum(res[f"{mode}/{s}"]["switched"] for s in args.seeds)
    print(json.dumps(res))
    return res


if __name__ == "__main__":
    main()
